//! `lifegom-eval`: scores a trained model on a THuman-style validation split.
//!
//! ```text
//! lifegom-eval --config configs/quickstart.toml --checkpoint runs/quickstart/checkpoints/latest.lgck
//!              [--data <root>] [--out runs/eval] [--device flex|ndarray]
//!              [--subdivide S] [--iterations T] [--baseline] [--freeview N]
//!              [--motion [walk,arm-raise,squat,path/to/poses.json]]
//!              [--sweep [--sweep-sizes 64,128] [--sweep-subjects 2]] [--per-scene 10,30,100,300]
//!              [--weights weights/]
//! ```
//!
//! Writes `per_view.csv`, `per_subject.csv`, `summary.json`, `report.md`, `preds/`, `sheets/`,
//! and with the options `freeview.gif`, `motion_*.gif` (each motion's frames and `poses.json`
//! under `motion/<name>/`), `pareto.png`.

use std::path::PathBuf;

use clap::Parser;
use lifegom_cli::eval_run::{EvalOptions, run};
use lifegom_eval::perceptual::PerceptualModels;
use lifegom_render::device::DeviceChoice;
use lifegom_render::motion::MotionSource;

#[derive(Parser, Debug)]
#[command(
    about = "Evaluate a trained LIFe-GoM model on a validation split",
    version
)]
struct Args {
    /// Experiment config (its `[data]` section names the split).
    #[arg(long)]
    config: PathBuf,
    /// Trained-model file: a `.lgck` (e.g. `runs/<name>/checkpoints/latest.lgck`), or an
    /// official LIFe-GoM checkpoint (`.pth` from `torch.save`, or `.safetensors`) loaded into the
    /// network the config's `[model]` describes.
    #[arg(long)]
    checkpoint: PathBuf,
    /// Dataset root (overrides `[data] root`).
    #[arg(long)]
    data: Option<PathBuf>,
    /// Output folder.
    #[arg(long, default_value = "runs/eval")]
    out: PathBuf,
    /// Backend.
    #[arg(long, default_value = "flex")]
    device: DeviceChoice,
    /// Subdivisions of the Gaussians' mesh (default: the model's test setting).
    #[arg(long)]
    subdivide: Option<u32>,
    /// Feedback steps (default: the model's).
    #[arg(long)]
    iterations: Option<usize>,
    /// Comparison sheets to write.
    #[arg(long, default_value_t = 6)]
    sheets: usize,
    /// Also score the baselines (template in one colour, projective texturing).
    #[arg(long)]
    baseline: bool,
    /// Other trained models to score on the same views (comma-separated `.lgck` files).
    #[arg(long, value_delimiter = ',')]
    compare: Vec<PathBuf>,
    /// Free-view turntable with this many frames (PNG frames + GIF).
    #[arg(long, num_args = 0..=1, default_missing_value = "36")]
    freeview: Option<usize>,
    /// Novel-pose sequences: procedural names (walk, arm-raise, squat), pose-sequence files
    /// (`docs/motions.md`) or SMPL capture files (AIST++ `.pkl`, `.npz`), comma-separated; alone,
    /// the three procedural ones.
    #[arg(long, num_args = 0..=1, value_delimiter = ',', default_missing_value = "walk,arm-raise,squat", value_parser = lifegom_data::capture::parse_motion)]
    motion: Option<Vec<MotionSource>>,
    /// Accuracy vs time: T = 1..5 × subdivisions 0..2.
    #[arg(long)]
    sweep: bool,
    /// Extra image sides for the sweep.
    #[arg(long, value_delimiter = ',')]
    sweep_sizes: Vec<u32>,
    /// Subjects the sweep scores (default: as many as are evaluated; each size costs 15
    /// evaluations).
    #[arg(long)]
    sweep_subjects: Option<usize>,
    /// Per-scene optimisation baseline: fit each subject and score it after each of these
    /// gradient-step counts (e.g. `10,30,100,300`), on the accuracy-vs-time plot.
    #[arg(long, value_delimiter = ',')]
    per_scene: Vec<usize>,
    /// Subjects the per-scene optimisation fits (default: as many as are evaluated).
    #[arg(long)]
    per_scene_subjects: Option<usize>,
    /// Evaluate at most this many subjects.
    #[arg(long)]
    max_subjects: Option<usize>,
    /// Test-time refinement: after the feed-forward pass, this many gradient steps of the
    /// per-scene fit on the source views (the model's and the baselines' avatars alike).
    #[arg(long, default_value_t = 0)]
    refine_steps: usize,
    /// Folder with converted LPIPS/Inception weights (default: $LIFEGOM_WEIGHTS or weights/).
    #[arg(long)]
    weights: Option<PathBuf>,
    /// Score every trained model after each feedback step t = 1..T too.
    #[arg(long)]
    feedback_steps: bool,
    /// Evaluate the config's held-out set (`[data] held_out_dir`, design.md §8.11) instead of
    /// its validation split.
    #[arg(long)]
    held_out: bool,
}

fn main() -> anyhow::Result<()> {
    use anyhow::Context as _;
    lifegom_cli::allocator::keep_freed_memory();
    lifegom_cli::init_tracing();
    let args = Args::parse();
    // SAFETY: the first thing `main` does after parsing; no thread has started yet.
    unsafe { lifegom_cli::make_default_device(args.device) };
    let mut experiment = lifegom_train::config::ExperimentConfig::load(&args.config)?;
    if let Some(root) = &args.data {
        experiment = experiment.with_root(root);
    }
    let official_network = experiment.reconstructor();
    let mut cfg = experiment.file;
    if args.held_out {
        cfg.data = cfg.data.held_out().with_context(|| {
            format!(
                "{}: --held-out needs a held-out set: [data] held_out_dir and held_out_split",
                args.config.display()
            )
        })?;
    }
    let command: Vec<String> = std::env::args().collect();
    let outcome = run(&EvalOptions {
        data: cfg.data,
        checkpoint: args.checkpoint.clone(),
        official_network,
        out: args.out.clone(),
        device: args.device.device(),
        subdivide: args.subdivide,
        iterations: args.iterations,
        sheets: args.sheets,
        freeview_frames: args.freeview.unwrap_or(0),
        motions: args.motion.clone().unwrap_or_default(),
        sweep: args.sweep,
        sweep_sizes: args.sweep_sizes.clone(),
        sweep_subjects: args.sweep_subjects,
        baseline: args.baseline,
        other_models: args.compare.clone(),
        per_scene: args.per_scene.clone(),
        per_scene_subjects: args.per_scene_subjects,
        max_subjects: args.max_subjects,
        refine_steps: args.refine_steps,
        weights_dir: args
            .weights
            .clone()
            .unwrap_or_else(PerceptualModels::default_dir),
        context: vec![format!("`{}` on {}", command.join(" "), args.device.name())],
        feedback_steps: args.feedback_steps,
    })?;
    println!(
        "{}",
        serde_json::json!({
            "report": outcome.report.display().to_string(),
            "model": outcome.summary,
            "baselines": lifegom_cli::eval_run::baselines_json(&outcome.baselines),
            "sweep_points": outcome.sweep.len(),
        })
    );
    Ok(())
}
