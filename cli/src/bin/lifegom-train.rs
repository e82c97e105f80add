//! `lifegom-train`: trains the LIFe-GoM reconstructor on a THuman-style split.
//!
//! ```text
//! lifegom-train --config configs/synthetic-tiny.toml --out runs/tiny [--device flex|ndarray]
//!               [--data <root>] [--resume] [--max-minutes M] [--steps N]
//! ```
//!
//! Ctrl-C finishes the current step, writes a checkpoint and exits; `--resume` continues it.

use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};

use anyhow::Context;
use clap::Parser;
use lifegom_render::device::DeviceChoice;
use lifegom_train::config::ExperimentConfig;
use lifegom_train::run::{RunOptions, StopReason, train};

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
    tracing_subscriber::fmt()
        .with_env_filter(tracing_subscriber::EnvFilter::from_default_env())
        .with_writer(std::io::stderr)
        .init();
    let args = Args::parse();
    let mut cfg = ExperimentConfig::load(&args.config)?;
    if let Some(root) = &args.data {
        cfg = cfg.with_root(root);
    }
    let stop = Arc::new(AtomicBool::new(false));
    {
        let stop = stop.clone();
        ctrlc::set_handler(move || {
            if stop.swap(true, Ordering::SeqCst) {
                eprintln!("second Ctrl-C: exiting without a checkpoint");
                std::process::exit(130);
            }
            eprintln!(
                "Ctrl-C: finishing this step and writing a checkpoint (Ctrl-C again to abort)"
            );
        })
        .context("installing the Ctrl-C handler")?;
    }
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
