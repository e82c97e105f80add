//! `fusion-bench`: what the fusion block's CPU custom ops (attention core, `LN(x + r)` with the
//! residual's dropout folded in) save against Burn's tensor-op composition of the same layers
//! (design.md §7.4), and what dropout costs on each.
//!
//! ```text
//! cargo run --release -p lifegom-cli --bin fusion-bench -- --config tiny
//! cargo run --release -p lifegom-cli --bin fusion-bench -- --config cpu --runs 4
//! ```
//!
//! The two fusion layers at the preset's width and heads run over the template's vertices and
//! `N` views on the autodiff Flex device, as a training step calls them on the source branch:
//! forward, a weighted-sum loss, backward, and the features' gradient read back. The four
//! variants (host ops or tensor ops, dropout 0.1 with fixed masks or none) alternate within one
//! process, on the same weights and inputs: the VM's speed drifts by ±15 % between runs, more
//! than the differences measured here. Prints one JSON line of medians.

use lifegom_model::norm_folds::NormFolds;
use std::time::Instant;

use anyhow::Context;
use burn::tensor::{Device, Distribution, Tensor};
use clap::{Parser, ValueEnum};
use lifegom_model::fusion::{Attend, FusionConfig, FusionKernel, LayerRun};
use lifegom_model::reconstructor::ReconstructorConfig;
use lifegom_ops::dropout::MaskSeed;
use lifegom_render::readback;
use lifegom_render::template::{BodyTemplate, full_template_path, lowres_template_path};

#[derive(Debug, Clone, Copy, ValueEnum)]
enum Preset {
    /// Tiny network, low-res template (the quickstart's).
    Tiny,
    /// Quarter-width encoder (288 + 32 channels), paper heads, full template.
    Cpu,
}

#[derive(Parser, Debug)]
#[command(about = "Benchmark the fusion block: CPU custom ops against tensor ops")]
struct Args {
    /// Network preset (width, heads) and its template (vertex count).
    #[arg(long, value_enum, default_value = "tiny")]
    config: Preset,
    /// Source views N.
    #[arg(long, default_value_t = 3)]
    views: usize,
    /// Timed calls per variant (medians reported), after one warm-up each.
    #[arg(long, default_value_t = 20)]
    runs: usize,
    /// Run only this variant (0: host ops, 1: host ops without dropout, 2: tensor ops, 3:
    /// tensor ops without dropout), e.g. under a profiler; the others report null.
    #[arg(long)]
    only: Option<usize>,
}

fn main() -> anyhow::Result<()> {
    lifegom_cli::allocator::keep_freed_memory();
    lifegom_cli::init_tracing();
    let args = Args::parse();
    let (cfg, path) = match args.config {
        Preset::Tiny => (
            ReconstructorConfig::tiny(args.views),
            lowres_template_path(),
        ),
        Preset::Cpu => (ReconstructorConfig::cpu(args.views), full_template_path()),
    };
    let body = BodyTemplate::load(&path).with_context(|| format!("loading {}", path.display()))?;
    let device = Device::flex().autodiff();
    let normal = Distribution::Normal(0.0, 1.0);
    let (v, n, d) = (body.num_vertices(), args.views, cfg.feature_dim());
    let fusion = FusionConfig::new(d).with_n_heads(cfg.n_heads).init(&device);
    let features = Tensor::<3>::random([v, n, d], normal, &device).require_grad();
    let embed = Tensor::<3>::random([v, 1, d], normal, &device);
    let weights = Tensor::<3>::random([v, 1, d], normal, &device);

    // The four masks of a training call (fixed seeds, so both kernels apply the same), or none.
    let dropout = [11, 12, 13, 14].map(MaskSeed::Given);
    let no_dropout = [MaskSeed::Off; 4];
    let variants = [
        (FusionKernel::Ops, dropout),
        (FusionKernel::Ops, no_dropout),
        (FusionKernel::TensorOps, dropout),
        (FusionKernel::TensorOps, no_dropout),
    ];
    let call = |(kernel, masks): (FusionKernel, [MaskSeed; 4])| -> anyhow::Result<f64> {
        let start = Instant::now();
        let folds = NormFolds::new();
        let run = |masks| LayerRun { kernel, masks };
        let across_views = Attend::Cross {
            query: features.clone(),
            context: features.clone(),
        };
        let views = fusion
            .views
            .forward(&folds, across_views, run([masks[0], masks[1]]));
        let into_vertex = Attend::Cross {
            query: embed.clone(),
            context: views,
        };
        let out = fusion
            .query
            .forward(&folds, into_vertex, run([masks[2], masks[3]]));
        let grads = (out * weights.clone()).sum().backward();
        let grad = features.grad(&grads).context("the features take part")?;
        readback::read::<f32, 3, _>("feature gradient", grad)?;
        Ok(start.elapsed().as_secs_f64() * 1e3)
    };
    let chosen = |i: usize| args.only.is_none_or(|only| only == i);
    for (i, &variant) in variants.iter().enumerate() {
        if chosen(i) {
            call(variant)?; // warm-up: first-touch allocations, thread-pool start
        }
    }
    let mut times = vec![Vec::new(); variants.len()];
    for _ in 0..args.runs.max(1) {
        for (i, (variant, times)) in variants.into_iter().zip(&mut times).enumerate() {
            if chosen(i) {
                times.push(call(variant)?);
            }
        }
    }
    let medians: Vec<Option<f64>> = times
        .into_iter()
        .map(|mut t| {
            t.sort_by(f64::total_cmp);
            t.get(t.len() / 2).map(|m| (m * 100.0).round() / 100.0)
        })
        .collect();
    println!(
        "{}",
        serde_json::json!({
            "bench": "fusion",
            "config": format!("{:?}", args.config).to_lowercase(),
            "vertices": v,
            "views": n,
            "width": d,
            "heads": cfg.n_heads,
            "dropout": 0.1,
            "runs": args.runs,
            "host_ops_ms": medians[0],
            "host_ops_no_dropout_ms": medians[1],
            "tensor_ops_ms": medians[2],
            "tensor_ops_no_dropout_ms": medians[3],
        })
    );
    Ok(())
}
