//! `lifegom-train`: trains the LIFe-GoM reconstructor on a THuman-style split.
//!
//! ```text
//! lifegom-train --config configs/synthetic-tiny.toml --out runs/tiny [--device flex|ndarray]
//!               [--data <root>] [--resume] [--max-minutes M] [--steps N]
//! lifegom-train --out runs/demo --export assets/demo/demo.lgck [--subdivide-test S]
//! ```
//!
//! Ctrl-C finishes the current step, writes a checkpoint and exits; `--resume` continues it.
//! `--export` trains nothing: it writes the run's latest checkpoint without the optimizer state
//! (an inference-only model file, a third of the size).

use std::path::PathBuf;

use clap::Parser;
use lifegom_cli::train_run::{RunOptions, StopReason, export_model, latest_checkpoint, train};
use lifegom_render::device::DeviceChoice;
use lifegom_train::config::ExperimentConfig;

#[derive(Parser, Debug)]
#[command(about = "Train the LIFe-GoM reconstructor", version)]
struct Args {
    /// Experiment config (configs/*.toml).
    #[arg(long, required_unless_present = "export")]
    config: Option<PathBuf>,
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
    /// Write `<out>/checkpoints/latest.lgck` without its optimizer state to this file and exit.
    #[arg(long)]
    export: Option<PathBuf>,
    /// With `--export`: the Gaussians' subdivision the exported model renders at by default
    /// (the run's `subdivide_test` otherwise). The weights serve every level; pick the one the
    /// image size calls for (docs/design.md §10.9).
    #[arg(long, requires = "export")]
    subdivide_test: Option<u32>,
}

fn main() -> anyhow::Result<()> {
    lifegom_cli::allocator::keep_freed_memory();
    lifegom_cli::init_tracing();
    let args = Args::parse();
    // SAFETY: the first thing `main` does after parsing; no thread has started yet.
    unsafe { lifegom_cli::make_default_device(args.device) };
    if let Some(dest) = &args.export {
        let source = latest_checkpoint(&args.out);
        let bytes = export_model(&source, dest, args.subdivide_test, &args.device.device())?;
        println!(
            "{}",
            serde_json::json!({
                "exported": dest.display().to_string(),
                "from": source.display().to_string(),
                "bytes": bytes,
            })
        );
        return Ok(());
    }
    let Some(config) = &args.config else {
        anyhow::bail!("--config is required to train");
    };
    let mut cfg = ExperimentConfig::load(config)?;
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
