//! `train-bench`: where a training step's time goes.
//!
//! ```text
//! cargo run --release -p lifegom-cli --bin train-bench -- --config configs/quickstart.toml
//! cargo run --release -p lifegom-cli --bin train-bench -- --config configs/synthetic-tiny.toml
//! cargo run --release -p lifegom-cli --bin train-bench -- --config configs/synthetic-default.toml --steps 4
//! ```
//!
//! Runs the trainer's real step (the same data schedule, model and losses as `lifegom-train`) on
//! a config's synthetic split, after warm-up steps, and prints ONE JSON line: the median step
//! time, the process's CPU time per wall second (2.0 = both cores of a 2-core machine busy) and
//! the kernel's share of it (`system_per_wall`: page faults on fresh memory land there), the
//! peak resident memory, and the median milliseconds of every stage, keyed by span path
//! (`profile` module docs), e.g. `train_step/reconstruct/feedback_step/render_views` (summed
//! over the T feedback steps; the source and rendered fusion branches run on two threads, so
//! their sum can exceed their parent). With `--stage-cpu` the line also has
//! `stages_cpu_per_wall`: per stage, the process's CPU seconds per wall second inside it over all
//! timed steps (a stage near 1.0 on a 2-core machine leaves one core idle); reading the process
//! CPU clock at every span slows the step, so compare step times only between runs without it.
//! Each step's wall time also goes to stderr as it ends.
//!
//! On a CubeCL device (wgpu) the line also has `kernel_launches`, the median kernel
//! launches per step, `top_kernels`, the kernels launched most per step, and `device_reads`,
//! the median read-backs per step (each a sync after which the card idles until the host queues
//! more), per tensor in `device_reads_by_tensor` ([`lifegom_cli::launches`]). With `--kernel-times` every launch is also timed on the device
//! and `top_kernels` is ordered by device time; the kernels then run one at a time, so the step
//! times of such a run are not the step's time. With `--attribute-launches` the launches are
//! also counted per model stage that queued them (`launches_per_step_by_stage`, e.g.
//! `step/train_step/batch_gradients/reconstruct/feedback_step/point_transformer`), the device
//! waited for at every stage boundary; again the step times are not the step's.
//!
//! If the config trains on its split (`[train] subjects = "split"`) and the split is missing, it
//! is generated first, with at most `--subjects` training subjects (the timing does not depend on
//! how many there are), under `bench-data/<config>`. With `subjects = "procedural"` each step
//! generates its own subject (on the prefetch thread, or in the `data` stage with `--data
//! serial`).
//!
//! `--concurrency alternate` compares the model's two host threading modes
//! ([`HostConcurrency`]) in one process: timed steps alternate between them, and the line gains
//! each mode's median step, forward and backward (`by_concurrency`). The VM this project is
//! measured on drifts by more than such a change between runs; within one process, the drift
//! hits both modes alike.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::Context;
use clap::Parser;
use lifegom_cli::launches::{KernelTiming, LaunchCounter, StageAttribution};
use lifegom_cli::profile::{StageTimer, median, peak_resident_mib, process_cpu_times};
use lifegom_data::synth;
use lifegom_model::inputs::model_inputs;
use lifegom_model::reconstructor::{HostConcurrency, MeshPurpose};
use lifegom_render::device::{DeviceChoice, runs_on_host};
use lifegom_train::config::{ExperimentConfig, TrainingSubjects};
use lifegom_train::data_parallel::BatchLayout;
use lifegom_train::losses::UniformLaplacian;
use lifegom_train::prefetch::Prefetcher;
use lifegom_train::source::{StepSample, TrainingSource};
use lifegom_train::trainer::Trainer;
use tracing_subscriber::layer::SubscriberExt;

#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
enum DataLoading {
    /// One sample ahead on another thread.
    Prefetch,
    /// On the training thread, before each step.
    Serial,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
enum Concurrency {
    /// Independent parts of a feedback step side by side (the default).
    Branches,
    /// The same parts one after the other, in program order.
    Sequential,
    /// Timed steps alternate between the two (module docs).
    Alternate,
}

impl Concurrency {
    /// The mode of step `i`. Alternating, steps `2p` and `2p + 1` train on the same sample,
    /// one in each mode, in the order `(Branches, Sequential)` for even `p` and the reverse for
    /// odd `p`: neither the sample nor the position in a pair favours a mode.
    fn mode(self, i: u64) -> HostConcurrency {
        match self {
            Self::Branches => HostConcurrency::Branches,
            Self::Sequential => HostConcurrency::Sequential,
            Self::Alternate if i.is_multiple_of(2) == (i / 2).is_multiple_of(2) => {
                HostConcurrency::Branches
            }
            Self::Alternate => HostConcurrency::Sequential,
        }
    }
}

#[derive(Parser, Debug)]
#[command(about = "Profile LIFe-GoM training steps (one JSON line)")]
struct Args {
    /// Experiment config (data, model preset, training settings).
    #[arg(long, default_value = "configs/quickstart.toml")]
    config: PathBuf,
    /// Timed steps (the median is reported).
    #[arg(long, default_value_t = 10)]
    steps: u64,
    /// Untimed steps first (allocator and thread-pool warm-up).
    #[arg(long, default_value_t = 2)]
    warmup: u64,
    /// Backend.
    #[arg(long, default_value = "flex")]
    device: DeviceChoice,
    /// Data root; defaults to the config's root if its split exists, else `bench-data/<config>`.
    #[arg(long)]
    data_root: Option<PathBuf>,
    /// How samples are read: on a prefetch thread (as `lifegom-train` does) or on the training
    /// thread (to measure what prefetching saves).
    #[arg(long, value_enum, default_value = "prefetch")]
    data: DataLoading,
    /// How the model spreads a step over threads on the host (module docs).
    #[arg(long, value_enum, default_value = "branches")]
    concurrency: Concurrency,
    /// Also time each stage's process CPU (`stages_cpu_per_wall`); slows the step (module docs).
    #[arg(long)]
    stage_cpu: bool,
    /// Training subjects to generate when the split is missing.
    #[arg(long, default_value_t = 3)]
    subjects: usize,
    /// On a CubeCL device, time every kernel launch too (module docs).
    #[arg(long)]
    kernel_times: bool,
    /// How many kernels `top_kernels` lists.
    #[arg(long, default_value_t = 15)]
    top_kernels: usize,
    /// On a CubeCL device, file each launch under the model stage that queued it
    /// (`launches_per_step_by_stage`): the device is waited for at every stage boundary, so
    /// the step times are not the step's (`lifegom_cli::launches::StageAttribution`).
    #[arg(long)]
    attribute_launches: bool,
    /// Rows per chunk of split-k weight gradients on a CubeCL device (`0`: one product each, as
    /// before f6dd65c, 2026-11-28); by default the `lifegom_ops::split_k` rule.
    #[arg(long)]
    split_k_rows: Option<usize>,
}

fn ms(seconds: f64) -> serde_json::Value {
    serde_json::json!((seconds * 1e5).round() / 100.0)
}

fn main() -> anyhow::Result<()> {
    lifegom_cli::allocator::keep_freed_memory();
    let args = Args::parse();
    // SAFETY: the first thing `main` does after parsing; no thread has started yet.
    unsafe { lifegom_cli::make_default_device(args.device) };
    // The training loop, and so every backward, runs on this thread.
    lifegom_ops::split_k::force_split_k_rows(args.split_k_rows);
    let mut cfg = ExperimentConfig::load(&args.config)?;
    let stem = args
        .config
        .file_stem()
        .map_or_else(|| "bench".into(), |s| s.to_string_lossy().into_owned());
    let split_exists = |cfg: &ExperimentConfig| {
        cfg.file
            .data
            .root
            .join(&cfg.file.data.train_dir)
            .join(&cfg.file.data.train_split)
            .exists()
    };
    let on_disk = cfg.train.subjects == TrainingSubjects::Split;
    if let Some(root) = &args.data_root {
        cfg = cfg.with_root(root);
    } else if on_disk && !split_exists(&cfg) {
        cfg = cfg.with_root(PathBuf::from("bench-data").join(&stem));
    }
    if on_disk && !split_exists(&cfg) {
        let mut synth_cfg = cfg.file.synthetic.clone().with_context(|| {
            format!(
                "{}: no [synthetic] section to generate a split from",
                args.config.display()
            )
        })?;
        synth_cfg.train_subjects = synth_cfg.train_subjects.min(args.subjects.max(1));
        synth_cfg.val_subjects = 1;
        eprintln!(
            "generating {} training subjects into {}",
            synth_cfg.train_subjects,
            cfg.file.data.root.display()
        );
        synth::generate_split(
            &synth_cfg,
            &cfg.file.data,
            &cfg.file.data.root,
            synth_cfg.seed,
            &|| {},
        )?;
    }

    let device = args.device.device();
    let source = std::sync::Arc::new(TrainingSource::open(&cfg)?);
    let rig = source.reference_rig();
    let mut trainer = Trainer::new(cfg.reconstructor(), rig.num_vertices(), &cfg.train, &device)?;
    let mesh = trainer
        .config
        .mesh(&rig.topology, MeshPurpose::Training, trainer.device())?;
    let laplacian = UniformLaplacian::new(&rig.topology.faces, rig.num_vertices())?;
    let (w, h) = (cfg.file.data.img_size[0], cfg.file.data.img_size[1]);

    let timer = if args.stage_cpu {
        StageTimer::with_process_cpu()
    } else {
        StageTimer::default()
    };
    let attribution = (args.attribute_launches && !runs_on_host(&device)).then(|| {
        let device = device.clone();
        StageAttribution::new(move || {
            // A read-back on the model's thread drains its fusion stream.
            let _ = burn::tensor::Tensor::<1>::zeros([1], &device).into_data();
        })
    });
    tracing::subscriber::set_global_default(
        tracing_subscriber::registry()
            .with(timer.clone())
            .with(attribution),
    )
    .context("installing the stage timer")?;

    let launches =
        LaunchCounter::on_cube_device(&device, KernelTiming::from_flag(args.kernel_times));
    let mut step_launches = Vec::new();
    let mut step_seconds = Vec::new();
    // Alternating, the sample of the pair's first step, for its second.
    let mut repeat = None;
    // Per mode: step, forward and backward seconds of its timed steps.
    let mut by_mode: std::collections::BTreeMap<String, [Vec<f64>; 3]> = Default::default();
    let mut stages: std::collections::BTreeMap<String, Vec<f64>> = Default::default();
    // Per stage, summed over the timed steps: wall and process CPU seconds.
    let mut stage_cpu: std::collections::BTreeMap<String, [f64; 2]> = Default::default();
    let mut cpu_seconds = 0.0;
    let mut system_seconds = 0.0;
    let mut wall_seconds = 0.0;
    // The warm-up steps compile every kernel: what a process pays once, kept apart from the median.
    let mut warmup_seconds = Vec::new();
    let mut prefetch = (args.data == DataLoading::Prefetch).then(|| {
        Prefetcher::new(
            source.clone(),
            trainer.seed(),
            BatchLayout::alone(trainer.samples),
        )
    });
    for i in 0..args.warmup + args.steps.max(1) {
        let mode = args.concurrency.mode(i);
        trainer.model = trainer.model.clone().with_concurrency(mode);
        let cpu_before = process_cpu_times();
        let start = Instant::now();
        {
            let _span = tracing::info_span!("step").entered();
            let inputs = match repeat.take() {
                Some(inputs) => inputs,
                None => {
                    let _span = tracing::debug_span!("data").entered();
                    let StepSample { sample, rig, .. } = match prefetch.as_mut() {
                        Some(p) => p.next_sample()?,
                        None => source.sample(trainer.seed(), trainer.samples)?,
                    };
                    let inputs = model_inputs(&rig, &sample, w, h, trainer.device())?;
                    if args.concurrency == Concurrency::Alternate {
                        repeat = Some(inputs.clone());
                    }
                    inputs
                }
            };
            trainer.train_step(&inputs, &mesh, &laplacian)?;
        }
        let wall = start.elapsed().as_secs_f64();
        let totals = timer.take();
        let step_tally = launches.as_ref().map(LaunchCounter::take);
        // A slow preset may be stopped before the JSON line: each step's time is on stderr.
        eprintln!(
            "{} step {}: {:.0} ms",
            if i < args.warmup { "warm-up" } else { "timed" },
            i + 1,
            wall * 1e3
        );
        if i < args.warmup {
            warmup_seconds.push(wall);
            continue;
        }
        step_seconds.push(wall);
        step_launches.extend(step_tally);
        wall_seconds += wall;
        if let (Some(a), Some(b)) = (cpu_before, process_cpu_times()) {
            cpu_seconds += (b.user + b.system) - (a.user + a.system);
            system_seconds += b.system - a.system;
        }
        let stage = |name: &str| {
            totals
                .get(&format!("step/train_step/{name}"))
                .map_or(f64::NAN, |t| t.wall.as_secs_f64())
        };
        let mode_times = by_mode
            .entry(format!("{mode:?}").to_lowercase())
            .or_default();
        mode_times[0].push(wall);
        mode_times[1].push(stage("reconstruct"));
        mode_times[2].push(stage("backward"));
        for (path, t) in totals {
            let sums = stage_cpu.entry(path.clone()).or_default();
            sums[0] += t.wall.as_secs_f64();
            sums[1] += t.cpu.as_secs_f64();
            stages.entry(path).or_default().push(t.wall.as_secs_f64());
        }
    }

    let model = &trainer.config;
    let stage_ms: serde_json::Map<String, serde_json::Value> = stages
        .iter()
        .filter_map(|(path, v)| Some((path.clone(), ms(median(v)?))))
        .collect();
    let stage_cpu_per_wall: serde_json::Map<String, serde_json::Value> = stage_cpu
        .iter()
        .filter(|(_, [wall, _])| *wall > 0.0)
        .map(|(path, [wall, cpu])| {
            (
                path.clone(),
                serde_json::json!((cpu / wall * 100.0).round() / 100.0),
            )
        })
        .collect();
    let by_concurrency: serde_json::Map<String, serde_json::Value> = by_mode
        .iter()
        .map(|(mode, [step, forward, backward])| {
            let m = |v: &Vec<f64>| ms(median(v).unwrap_or(f64::NAN));
            (
                mode.clone(),
                serde_json::json!({
                    "steps": step.len(),
                    "median_step_ms": m(step),
                    "reconstruct_ms": m(forward),
                    "backward_ms": m(backward),
                }),
            )
        })
        .collect();
    let mut line = serde_json::json!({
        "bench": "train-step",
        "config": stem,
        "preset": cfg.model.preset,
        "backend": args.device.name(),
        "size": [w, h],
        "views": cfg.file.data.n_input_frames,
        "iterations": model.iterations,
        "subdivide_train": model.subdivide_train,
        "gaussians": mesh.num_gaussians(),
        "vertices": rig.num_vertices(),
        "data": format!("{:?}", args.data).to_lowercase(),
        "steps": step_seconds.len(),
        "median_step_ms": ms(median(&step_seconds).unwrap_or(f64::NAN)),
        "min_step_ms": ms(step_seconds.iter().copied().fold(f64::INFINITY, f64::min)),
        "warmup_ms": warmup_seconds.iter().map(|&s| ms(s)).collect::<Vec<_>>(),
        "cpu_per_wall": (cpu_seconds / wall_seconds * 100.0).round() / 100.0,
        // Kernel time per wall second: page faults on fresh memory show up here.
        "system_per_wall": (system_seconds / wall_seconds * 100.0).round() / 100.0,
        "peak_rss_mib": peak_resident_mib().map(f64::round),
        "runtime": lifegom_render::device::cube_runtime_name(&device),
        "kernel_fusion": lifegom_render::device::KernelFusion::on_device(&device).map(|k| k.name()),
        "conv_kernel": lifegom_ops::gemm_conv::ConvKernel::on_device(&device).map(|k| k.name()),
        "hierarchy_planning": lifegom_model::point_transformer::HierarchyPlanning::on_device(&device).name(),
        "threads": rayon::current_num_threads(),
        "split_k_rows": args.split_k_rows.map_or_else(|| "default".to_owned(), |r| r.to_string()),
        "concurrency": format!("{:?}", args.concurrency).to_lowercase(),
        "by_concurrency": by_concurrency,
        "stages_ms": stage_ms,
    });
    if args.stage_cpu {
        line["stages_cpu_per_wall"] = serde_json::Value::Object(stage_cpu_per_wall);
    }
    if let Some(counter) = &launches {
        for (key, value) in counter.json_fields(&step_launches, args.top_kernels) {
            line[key] = value;
        }
    }
    println!("{line}");
    Ok(())
}
