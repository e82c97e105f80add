//! Kernel launches of one network part, forward and backward, on the wgpu device: a quick way to
//! see what a change to one module saves without running a whole training step (minutes on
//! lavapipe). Prints one JSON line per part.
//!
//! ```text
//! cargo run -p lifegom-cli --example launch-probe -- --part point-transformer
//! cargo run -p lifegom-cli --example launch-probe -- --part fusion --top 30
//! ```
//!
//! The part runs at the tiny preset on the low-res template's vertex count, as in the
//! quickstart's training step: once to compile its kernels, then once counted. The loss is a
//! weighted sum of the output, so the backward is the part's own.

use anyhow::Context;
use burn::tensor::{Distribution, Tensor};
use clap::{Parser, ValueEnum};
use lifegom_cli::launches::{KernelTiming, LaunchCounter, LaunchTally};
use lifegom_model::fusion::FusionRun;
use lifegom_model::point_transformer::{Hierarchy, NormFolds};
use lifegom_model::reconstructor::ReconstructorConfig;
use lifegom_render::device::DeviceChoice;
use lifegom_render::readback;
use lifegom_render::template::{BodyTemplate, lowres_template_path};

#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
enum Part {
    /// The Point Transformer over the low-res vertices.
    PointTransformer,
    /// The two fusion layers over `views` view tokens per vertex.
    Fusion,
}

#[derive(Parser, Debug)]
struct Args {
    /// Which part.
    #[arg(long, value_enum, default_value = "point-transformer")]
    part: Part,
    /// Source views (fusion tokens per vertex).
    #[arg(long, default_value_t = 3)]
    views: usize,
    /// Times the part runs on the same input within one pass, with one set of BN folds (as the
    /// T feedback passes of a reconstruction do); the difference between two counts is what
    /// one more feedback pass costs.
    #[arg(long, default_value_t = 1)]
    repeat: usize,
    /// Kernels listed per phase.
    #[arg(long, default_value_t = 20)]
    top: usize,
}

fn top(tally: &LaunchTally, n: usize) -> serde_json::Value {
    let mut kernels: Vec<(&String, u64)> = tally
        .kernels
        .iter()
        .map(|(name, k)| (name, k.launches))
        .collect();
    kernels.sort_by(|a, b| b.1.cmp(&a.1).then(a.0.cmp(b.0)));
    kernels
        .into_iter()
        .take(n)
        .map(|(name, n)| serde_json::json!([name, n]))
        .collect()
}

fn main() -> anyhow::Result<()> {
    let args = Args::parse();
    let base = DeviceChoice::Wgpu.device();
    let device = base.clone().autodiff();
    let template =
        BodyTemplate::load(lowres_template_path()).context("the low-res template (assets/body)")?;
    let v = template.num_vertices();
    let cfg = ReconstructorConfig::tiny(args.views);
    let model = cfg.init(v, &device)?;
    let counter = LaunchCounter::on_cube_device(&device, KernelTiming::Off)
        .context("wgpu is not a CubeCL device here")?;

    // One pass: forward, loss, backward; returns the launches of the forward and the backward.
    let pass = || -> anyhow::Result<(LaunchTally, LaunchTally)> {
        let folds = NormFolds::new();
        let (out, w) = match args.part {
            Part::PointTransformer => {
                let d_in = cfg.point_transformer.in_dim - 3;
                let p = Tensor::<2>::random([v, 3], Distribution::Uniform(-1.0, 1.0), &device)
                    .require_grad();
                let x = Tensor::<2>::random([v, d_in], Distribution::Normal(0.0, 1.0), &device)
                    .require_grad();
                // Inputs are made (and their kernels launched) before counting.
                readback::read::<f32, 1, _>("probe input", x.clone().sum())?;
                readback::read::<f32, 1, _>("probe input", p.clone().sum())?;
                counter.take();
                let mut out = model.point_transformer.forward(
                    &folds,
                    p.clone(),
                    x.clone(),
                    Hierarchy::Plan,
                )?;
                for _ in 1..args.repeat {
                    out = out
                        + model.point_transformer.forward(
                            &folds,
                            p.clone(),
                            x.clone(),
                            Hierarchy::Plan,
                        )?;
                }
                let w = Tensor::<2>::random(out.dims(), Distribution::Normal(0.0, 1.0), &base);
                (out, w)
            }
            Part::Fusion => {
                let d = model.vertex_embed.val().dims()[1];
                let feats = Tensor::<3>::random(
                    [v, args.views, d],
                    Distribution::Normal(0.0, 1.0),
                    &device,
                )
                .require_grad();
                let embed = model.vertex_embed.val();
                readback::read::<f32, 1, _>("probe input", feats.clone().sum())?;
                counter.take();
                let mut out = model.fusion.forward(
                    &NormFolds::new(),
                    feats.clone(),
                    embed.clone(),
                    FusionRun::default(),
                );
                for _ in 1..args.repeat {
                    out = out
                        + model.fusion.forward(
                            &NormFolds::new(),
                            feats.clone(),
                            embed.clone(),
                            FusionRun::default(),
                        );
                }
                let w = Tensor::<2>::random(out.dims(), Distribution::Normal(0.0, 1.0), &base);
                (out, w)
            }
        };
        let w = Tensor::from_inner(w);
        let loss = (out * w).sum();
        readback::read::<f32, 1, _>("probe loss", loss.clone())?;
        let forward = counter.take();
        let grads = loss.backward();
        drop(grads);
        readback::read::<f32, 1, _>("probe sync", Tensor::<1>::zeros([1], &base).sum())?;
        let backward = counter.take();
        Ok((forward, backward))
    };
    pass()?;
    let (forward, backward) = pass()?;
    println!(
        "{}",
        serde_json::json!({
            "part": format!("{:?}", args.part),
            "repeat": args.repeat,
            "forward_launches": forward.total_launches(),
            "backward_launches": backward.total_launches(),
            "forward_top": top(&forward, args.top),
            "backward_top": top(&backward, args.top),
        })
    );
    Ok(())
}
