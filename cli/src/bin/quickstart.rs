//! The README's main job: from a fresh clone to a trained avatar model and its report.
//!
//! ```text
//! cargo run --release -p lifegom-cli --bin quickstart [-- --minutes 20 --out runs/quickstart]
//! ```
//!
//! 1. generates the synthetic THuman-style split of `configs/quickstart.toml` if it is missing;
//! 2. trains the tiny network for `--minutes` (a checkpoint every 100 steps; Ctrl-C stops early
//!    with a checkpoint);
//! 3. evaluates on the validation subjects: PSNR/SSIM (LPIPS/FID when weights exist), the
//!    template-only baseline, comparison sheets, a free-view turntable, three procedural motions
//!    and the accuracy-vs-time sweep (T = 1..5 × subdivisions 0..2);
//! 4. writes `runs/quickstart/report.md` with the pictures.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::Context;
use clap::Parser;
use lifegom_cli::eval_run::{EvalOptions, run as run_eval};
use lifegom_cli::train_run::{RunOptions, train};
use lifegom_data::synth;
use lifegom_eval::perceptual::PerceptualModels;
use lifegom_render::device::DeviceChoice;
use lifegom_train::config::ExperimentConfig;

#[derive(Parser, Debug)]
#[command(
    about = "Generate synthetic data, train for a bounded time, evaluate, report",
    version
)]
struct Args {
    /// Experiment config.
    #[arg(long, default_value = "configs/quickstart.toml")]
    config: PathBuf,
    /// Training time budget in minutes.
    #[arg(long, default_value_t = 20.0)]
    minutes: f64,
    /// Output folder.
    #[arg(long, default_value = "runs/quickstart")]
    out: PathBuf,
    /// Backend.
    #[arg(long, default_value = "flex")]
    device: DeviceChoice,
    /// Continue training from `<out>/checkpoints/latest.lgck` instead of starting fresh.
    #[arg(long)]
    resume: bool,
    /// Skip the accuracy-vs-time sweep.
    #[arg(long)]
    no_sweep: bool,
}

fn main() -> anyhow::Result<()> {
    lifegom_cli::init_tracing();
    let args = Args::parse();
    let started = Instant::now();
    let cfg = ExperimentConfig::load(&args.config)?;
    let root = cfg.file.data.root.clone();
    if !root
        .join(&cfg.file.data.train_dir)
        .join(&cfg.file.data.train_split)
        .exists()
    {
        let synth_cfg = cfg
            .file
            .synthetic
            .clone()
            .context("the quickstart config needs a [synthetic] section")?;
        eprintln!(
            "[1/3] generating the synthetic split into {}",
            root.display()
        );
        let s = synth::generate_split(&synth_cfg, &cfg.file.data, &root, synth_cfg.seed, &|| {})?;
        eprintln!(
            "      {} train + {} val subjects, {} frames",
            s.train.len(),
            s.val.len(),
            s.frames
        );
    } else {
        eprintln!("[1/3] using the existing split in {}", root.display());
    }

    let stop = lifegom_cli::stop_on_ctrl_c("stopping training with a checkpoint, then evaluating")?;
    eprintln!(
        "[2/3] training {} for {} min on {}",
        args.config.display(),
        args.minutes,
        args.device.name()
    );
    let summary = train(
        &cfg,
        &RunOptions {
            out: args.out.clone(),
            resume: args.resume,
            max_minutes: Some(args.minutes),
            steps: None,
            device: args.device.device(),
            progress: true,
        },
        stop,
    )?;
    eprintln!(
        "      {} steps ({} this run) in {:.0} s, stopped: {:?}",
        summary.step, summary.steps_this_run, summary.seconds, summary.stop
    );

    eprintln!("[3/3] evaluating on the validation subjects");
    let outcome = run_eval(&EvalOptions {
        data: cfg.file.data.clone(),
        checkpoint: summary.checkpoint.clone(),
        out: args.out.clone(),
        device: args.device.device(),
        subdivide: None,
        iterations: None,
        sheets: 6,
        freeview_frames: 36,
        motion: true,
        sweep: !args.no_sweep,
        sweep_sizes: vec![],
        sweep_subjects: 2,
        baseline: true,
        per_scene: vec![],
        per_scene_subjects: None,
        max_subjects: None,
        weights_dir: PerceptualModels::default_dir(),
        context: vec![
            format!(
                "`cargo run --release -p lifegom-cli --bin quickstart -- --minutes {}` on {} ({} threads available)",
                args.minutes,
                args.device.name(),
                std::thread::available_parallelism().map_or(0, |n| n.get())
            ),
            format!(
                "trained {} steps in {:.1} min; loss curve: ![loss](loss_curve.png)",
                summary.step,
                summary.seconds / 60.0
            ),
        ],
    })?;
    let s = &outcome.summary;
    println!(
        "{}",
        serde_json::json!({
            "report": outcome.report.display().to_string(),
            "steps": summary.step,
            "psnr": s.psnr,
            "ssim": s.ssim,
            "baselines": lifegom_cli::eval_run::baselines_json(&outcome.baselines),
            "lpips_vgg_x1000": s.lpips_vgg_x1000,
            "recon_ms": s.recon_ms,
            "render_ms": s.render_ms,
            "total_minutes": started.elapsed().as_secs_f64() / 60.0,
        })
    );
    Ok(())
}
