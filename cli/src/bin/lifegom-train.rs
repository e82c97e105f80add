//! `lifegom-train`: trains the LIFe-GoM reconstructor on a THuman-style split.
//!
//! ```text
//! lifegom-train --config configs/synthetic-tiny.toml --out runs/tiny [--device flex|ndarray]
//!               [--data <root>] [--resume] [--max-minutes M] [--steps N]
//! ```
//!
//! Ctrl-C finishes the current step, writes a checkpoint and exits; `--resume` continues it.

use std::path::PathBuf;

use clap::Parser;
use lifegom_cli::train_run::{RunOptions, StopReason, train};
use lifegom_render::device::DeviceChoice;
use lifegom_train::config::ExperimentConfig;

#[derive(Parser, Debug)]
#[command(about = "Train the LIFe-GoM reconstructor", version)]
struct Args {
    /// Experiment config (configs/*.toml).
    #[arg(long)]
    config: PathBuf,
    /// Backend.
    #[arg(long, default_value = "flex")]
    device: DeviceChoice,
    /// Output folder (checkpoints, logs, snapshots).
    #[arg(long, default_value = "runs/train")]
    out: PathBuf,
    /// Dataset root (overrides `[data] root`).
    #[arg(long)]
    data: Option<PathBuf>,
    /// Continue from `<out>/checkpoints/latest.lgck`.
    #[arg(long)]
    resume: bool,
    /// Stop after this many minutes, with a checkpoint.
    #[arg(long)]
    max_minutes: Option<f64>,
    /// Override `[train] steps`.
    #[arg(long)]
    steps: Option<u64>,
}

fn main() -> anyhow::Result<()> {
    lifegom_cli::init_tracing();
    let args = Args::parse();
    let mut cfg = ExperimentConfig::load(&args.config)?;
    if let Some(root) = &args.data {
        cfg = cfg.with_root(root);
    }
    let stop = lifegom_cli::stop_on_ctrl_c("finishing this step and writing a checkpoint")?;
    let opts = RunOptions {
        out: args.out.clone(),
        resume: args.resume,
        max_minutes: args.max_minutes,
        steps: args.steps,
        device: args.device.device(),
        progress: true,
    };
    let summary = train(&cfg, &opts, stop)?;
    let last = summary.history.last();
    println!(
        "{}",
        serde_json::json!({
            "stop": format!("{:?}", summary.stop),
            "step": summary.step,
            "steps_this_run": summary.steps_this_run,
            "seconds": summary.seconds,
            "backend": args.device.name(),
            "checkpoint": summary.checkpoint.display().to_string(),
            "last_losses": last.map(|s| s.losses.clone()),
            "last_psnr_target": last.map(|s| s.psnr_target),
        })
    );
    if summary.stop == StopReason::Interrupted {
        std::process::exit(130);
    }
    Ok(())
}
