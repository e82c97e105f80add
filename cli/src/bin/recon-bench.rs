//! `recon-bench`: how long reconstruction takes, per feedback step and in total.
//!
//! ```text
//! cargo run --release -p lifegom-cli --bin recon-bench -- --config tiny --json
//! cargo run --release -p lifegom-cli --bin recon-bench -- --config cpu --size 256 --json
//! cargo run --release -p lifegom-cli --bin recon-bench -- --config paper --size 1024 --subdiv 2 --json
//! ```
//!
//! Random-initialised weights (timing does not depend on their values), source views rendered
//! from the template, inference mode (no autodiff). Prints one JSON line: total and per-stage
//! milliseconds of the median run, the median wall time of every `tracing` span path inside the
//! reconstruction (`spans_ms`, as `train-bench` keys them: summed over the T feedback steps, a
//! parent including its children), the parameter count, and the setup. The paper's anchor is
//! 907.92 ms for T = 3, 3 views, 1024², 2 subdivisions on one A100.
//!
//! On a CubeCL device (wgpu) the line also has `kernel_launches` per reconstruction,
//! `top_kernels`, and `device_reads` (read-backs, each a sync; per tensor in
//! `device_reads_by_tensor`; the benchmark's own read of the result is not counted)
//! ([`lifegom_cli::launches`]); `--kernel-times` times every launch on the device
//! too, which runs the kernels one at a time (the run's `total_ms` is then not the
//! reconstruction's time). `max_buffer_bytes` is the device's largest buffer: where a stage's
//! largest tensor would not fit it (the paper network on lavapipe's 128 MiB), the per-vertex
//! and face stages run in blocks, each with its own launches; `--buffer-floats` forces smaller
//! blocks, to count what one costs. `--warmup 0` makes the first run the figure: the first run
//! also initialises the weights, so its launch count is higher.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::Context;
use burn::module::Module;
use burn::tensor::{Distribution, Tensor};
use clap::{Parser, ValueEnum};
use glam::Vec3;
use lifegom_cli::launches::{KernelTiming, LaunchCounter};
use lifegom_cli::profile::{StageTimer, median};
use lifegom_model::reconstructor::{CanonicalSubject, ReconstructorConfig, SourceViews};
use lifegom_render::camera::{Camera, Intrinsics};
use lifegom_render::device::DeviceChoice;
use lifegom_render::gom::GomMesh;
use lifegom_render::skeleton::BodyPose;
use lifegom_render::template::{BodyTemplate, full_template_path, lowres_template_path};
use tracing_subscriber::layer::SubscriberExt;

#[derive(Debug, Clone, Copy, ValueEnum)]
enum Preset {
    /// Tiny network, low-res template.
    Tiny,
    /// Quarter-width encoder, paper fusion/Point Transformer, full template.
    Cpu,
    /// The paper's network (1152 channels), full template.
    Paper,
}

#[derive(Parser, Debug)]
#[command(about = "Benchmark LIFe-GoM reconstruction")]
struct Args {
    /// Network preset.
    #[arg(long, value_enum, default_value = "tiny")]
    config: Preset,
    /// Body template; defaults to the low-res one for `tiny`, the full one otherwise.
    #[arg(long)]
    template: Option<PathBuf>,
    /// Image side, pixels.
    #[arg(long, default_value_t = 128)]
    size: u32,
    /// Source views.
    #[arg(long, default_value_t = 3)]
    views: usize,
    /// Feedback steps T.
    #[arg(long, default_value_t = 3)]
    iterations: usize,
    /// Subdivision levels of the Gaussians.
    #[arg(long, default_value_t = 1)]
    subdiv: u32,
    /// Backend: ndarray or flex.
    #[arg(long, default_value = "flex")]
    device: DeviceChoice,
    /// Timed runs (median reported), after the warm-up runs.
    #[arg(long, default_value_t = 3)]
    runs: usize,
    /// Untimed runs first, which compile the kernels. 0 makes the first run the figure: enough
    /// for a launch count (the same every run), where a run takes minutes (the paper network
    /// on lavapipe).
    #[arg(long, default_value_t = 1)]
    warmup: usize,
    /// Only the JSON line.
    #[arg(long)]
    json: bool,
    /// On a CubeCL device, time every kernel launch too (module docs).
    #[arg(long)]
    kernel_times: bool,
    /// Hold a buffer of the per-vertex and face stages to this many floats, so that they run
    /// in more blocks (`Reconstructor::with_buffer_floats`): what a block costs. Unset, only
    /// the device's own limit blocks them.
    #[arg(long)]
    buffer_floats: Option<usize>,
    /// How many kernels `top_kernels` lists.
    #[arg(long, default_value_t = 15)]
    top_kernels: usize,
}

fn main() -> anyhow::Result<()> {
    lifegom_cli::allocator::keep_freed_memory();
    let args = Args::parse();
    // SAFETY: the first thing `main` does after parsing; no thread has started yet.
    unsafe { lifegom_cli::make_default_device(args.device) };
    let timer = StageTimer::default();
    tracing::subscriber::set_global_default(tracing_subscriber::registry().with(timer.clone()))
        .context("installing the stage timer")?;
    let device = args.device.device();
    let path = args.template.clone().unwrap_or_else(|| match args.config {
        Preset::Tiny => lowres_template_path(),
        _ => full_template_path(),
    });
    let body = BodyTemplate::load(&path).with_context(|| format!("loading {}", path.display()))?;
    let cfg = match args.config {
        Preset::Tiny => ReconstructorConfig::tiny(args.views),
        Preset::Cpu => ReconstructorConfig::cpu(args.views),
        Preset::Paper => ReconstructorConfig::paper(args.views),
    }
    .with_iterations(args.iterations);
    let model = cfg.init(body.num_vertices(), &device)?;
    let model = match args.buffer_floats {
        Some(floats) => model.with_buffer_floats(floats),
        None => model,
    };
    let params = model.num_params();
    let s = args.size;
    let k = Intrinsics {
        fx: 0.8 * s as f32,
        fy: 0.8 * s as f32,
        cx: s as f32 / 2.0,
        cy: s as f32 / 2.0,
    };
    let cameras: Vec<Camera> = (0..args.views)
        .map(|i| {
            let a = i as f32 / args.views as f32 * std::f32::consts::TAU;
            Camera::look_at(
                Vec3::new(2.5 * a.sin(), 0.1, 2.5 * a.cos()),
                Vec3::new(0.0, 0.1, 0.0),
                Vec3::Y,
                k,
                s,
                s,
            )
        })
        .collect::<Result<_, _>>()?;
    let rest = body
        .skeleton
        .skinning_transforms(&BodyPose::rest(body.num_joints()))?;
    let sources = SourceViews {
        images: Tensor::random(
            [args.views, 3, s as usize, s as usize],
            Distribution::Uniform(0.0, 1.0),
            &device,
        ),
        cameras,
        skinning: vec![rest; args.views],
        background: [1.0; 3],
    };
    let subject = CanonicalSubject {
        canonical_vertices: body.vertex_tensor(&device),
        lbs_weights: body.skin.tensor(&device),
        skeleton: body.skeleton.clone(),
    };
    let mesh = GomMesh::new(&body.topology, args.subdiv, &device)?;

    let launches =
        LaunchCounter::on_cube_device(&device, KernelTiming::from_flag(args.kernel_times));
    let mut run_launches = Vec::new();
    let mut runs = Vec::new();
    let mut warmup_ms = f64::NAN;
    let mut spans: std::collections::BTreeMap<String, Vec<f64>> = Default::default();
    for run in 0..args.warmup + args.runs.max(1) {
        timer.take();
        let start = Instant::now();
        let rec = model.forward(&subject, &mesh, &sources)?;
        // Reading the final colours back makes the time include all queued work.
        lifegom_render::device::wait_for_values(rec.last().faces.colors.clone());
        let total = start.elapsed().as_secs_f64() * 1e3;
        let tally = launches.as_ref().map(LaunchCounter::take);
        if run == 0 && args.warmup > 0 {
            // The warm-up compiles every kernel (and, with autotune, would tune them): what a
            // process pays once, kept apart from the median.
            warmup_ms = total;
        }
        if run >= args.warmup {
            run_launches.extend(tally);
            runs.push((total, rec.timings));
            for (path, t) in timer.take() {
                spans
                    .entry(path)
                    .or_default()
                    .push(t.wall.as_secs_f64() * 1e3);
            }
        }
    }
    runs.sort_by(|a, b| a.0.total_cmp(&b.0));
    let (total, stages) = &runs[runs.len() / 2];
    let stage_ms: serde_json::Map<String, serde_json::Value> = stages
        .iter()
        .map(|(n, d)| {
            (
                n.clone(),
                serde_json::json!((d.as_secs_f64() * 1e5).round() / 100.0),
            )
        })
        .collect();
    let steps: Vec<f64> = stages
        .iter()
        .filter(|(n, _)| n.starts_with("step_"))
        .map(|(_, d)| d.as_secs_f64() * 1e3)
        .collect();
    let mut line = serde_json::json!({
        "bench": "recon",
        "config": format!("{:?}", args.config).to_lowercase(),
        "backend": args.device.name(),
        "template": path.file_name().map(|f| f.to_string_lossy().into_owned()),
        "vertices": body.num_vertices(),
        "gaussians": mesh.num_gaussians(),
        "feature_dim": cfg.feature_dim(),
        "params": params,
        "views": args.views,
        "size": s,
        "iterations": args.iterations,
        "subdiv": args.subdiv,
        "total_ms": (total * 100.0).round() / 100.0,
        "warmup_ms": (warmup_ms * 100.0).round() / 100.0,
        "ms_per_step": (steps.iter().sum::<f64>() / steps.len().max(1) as f64 * 100.0).round() / 100.0,
        "stages_ms": stage_ms,
        "spans_ms": spans
            .iter()
            .map(|(path, ms)| {
                let ms = median(ms).map(|m| (m * 100.0).round() / 100.0);
                (path.clone(), serde_json::json!(ms))
            })
            .collect::<serde_json::Map<_, _>>(),
        "runtime": lifegom_render::device::cube_runtime_name(&device),
        "kernel_fusion": lifegom_render::device::KernelFusion::on_device(&device).map(|k| k.name()),
        "conv_kernel": lifegom_ops::gemm_conv::ConvKernel::on_device(&device).map(|k| k.name()),
        "hierarchy_planning": lifegom_model::point_transformer::HierarchyPlanning::on_device(&device).name(),
        "threads": rayon::current_num_threads(),
        "max_buffer_bytes": lifegom_render::device::max_buffer_bytes(&device),
        "buffer_floats": args.buffer_floats,
    });
    if let Some(counter) = &launches {
        for (key, value) in counter.json_fields(&run_launches, args.top_kernels) {
            line[key] = value;
        }
    }
    if !args.json {
        eprintln!(
            "reconstruction: {total:.1} ms total ({} params, random weights)",
            params
        );
    }
    println!("{line}");
    Ok(())
}
