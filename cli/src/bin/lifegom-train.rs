//! `lifegom-train`: trains the LIFe-GoM reconstructor on a THuman-style split.
//!
//! ```text
//! lifegom-train --config configs/synthetic-tiny.toml --out runs/tiny [--device flex|ndarray]
//!               [--data <root>] [--resume] [--max-minutes M] [--steps N] [--accumulate K]
//!               [--init WEIGHTS]
//! lifegom-train --out runs/demo --export assets/demo/demo.lgck [--from latest|best|FILE] [--subdivide-test S]
//! ```
//!
//! Ctrl-C (or SIGTERM, or SIGUSR1) finishes the current step, writes a checkpoint and exits;
//! `--resume` continues it.
//! `--export` trains nothing: it writes the run's latest checkpoint (or, with `--from best`, its
//! best validated weights, or with `--from FILE` any model file) without the optimizer state (an
//! inference-only model file, a third of the size). An export to `*.safetensors` writes the
//! official code's state dict instead (its key names and layouts), for PyTorch users.
//!
//! Model files are a `.lgck` or an official LIFe-GoM checkpoint (`.pth` written by
//! `torch.save`, zip or legacy, or `.safetensors`), told apart by content. An official file
//! holds weights only: they are loaded into the network of `--config`'s `[model]`.
//! `--init WEIGHTS` fine-tunes: the run starts from those weights with a fresh optimizer; with
//! `--resume`, a run that has its own checkpoint continues from that instead.
//!
//! Built with the `mpi` feature, `mpirun -np N lifegom-train …` trains one model on N ranks,
//! each one replica on its own share of every batch (docs/data-parallel.md). A rank that fails
//! ends the whole job.

use std::path::PathBuf;

use clap::Parser;
use lifegom_cli::train_run::{
    RunOptions, StopReason, best_checkpoint, export_model, latest_checkpoint, train_with,
};
use lifegom_render::device::DeviceChoice;
use lifegom_train::config::ExperimentConfig;
use lifegom_train::data_parallel::{Replicas, SingleProcess};

/// The end of `--help`: how to run data-parallel, and whether this binary can.
#[cfg(feature = "mpi")]
const DATA_PARALLEL_HELP: &str = "Data-parallel training: `mpirun -np N lifegom-train …` (or `srun` under Slurm) trains one model on N ranks, a batch of N × accumulate samples a step (docs/data-parallel.md). This binary is built with MPI.";
#[cfg(not(feature = "mpi"))]
const DATA_PARALLEL_HELP: &str = "Data-parallel training: `mpirun -np N lifegom-train …` (or `srun` under Slurm) trains one model on N ranks, a batch of N × accumulate samples a step (docs/data-parallel.md). This binary is built WITHOUT MPI: build with `--features lifegom-cli/mpi`.";

#[derive(Parser, Debug)]
#[command(about = "Train the LIFe-GoM reconstructor", version, after_help = DATA_PARALLEL_HELP)]
struct Args {
    /// Experiment config (configs/*.toml).
    #[arg(long, required_unless_present = "export")]
    config: Option<PathBuf>,
    /// Start from these weights (a `.lgck`, or an official `.pth` / `.safetensors` loaded into
    /// `--config`'s network) with a fresh optimizer: fine-tuning. `--resume` still continues a
    /// run from its own checkpoint when it has one.
    #[arg(long, conflicts_with = "export")]
    init: Option<PathBuf>,
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
    /// Override `[train] accumulate`: samples whose gradients each process sums before a step
    /// (the step takes the batch's mean gradient, so the learning rates keep their meaning).
    #[arg(long, value_parser = clap::value_parser!(u64).range(1..))]
    accumulate: Option<u64>,
    /// Write the run's latest checkpoint (or `--from best`'s) without its optimizer state to
    /// this file and exit.
    #[arg(long)]
    export: Option<PathBuf>,
    /// With `--export`: which model to export: `latest` or `best` of the run in `--out`, or a
    /// model file (`.lgck`, or an official checkpoint with `--config`).
    #[arg(long, default_value = "latest", requires = "export")]
    from: ExportSource,
    /// With `--export`: the Gaussians' subdivision the exported model renders at by default
    /// (the run's `subdivide_test` otherwise). The weights serve every level; pick the one the
    /// image size calls for (docs/design.md §10.9).
    #[arg(long, requires = "export")]
    subdivide_test: Option<u32>,
}

/// The model `--export` writes out.
#[derive(Clone, Debug)]
enum ExportSource {
    /// `<out>/checkpoints/latest.lgck`: where the run stopped.
    Latest,
    /// `<out>/checkpoints/best.lgck`: the best validation at the last feedback step.
    Best,
    /// A model file.
    File(PathBuf),
}

impl std::str::FromStr for ExportSource {
    type Err = std::convert::Infallible;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        Ok(match s {
            "latest" => Self::Latest,
            "best" => Self::Best,
            file => Self::File(file.into()),
        })
    }
}

fn main() -> anyhow::Result<()> {
    lifegom_cli::allocator::keep_freed_memory();
    lifegom_cli::init_tracing();
    let args = Args::parse();
    // SAFETY: the first thing `main` does after parsing; no thread has started yet.
    unsafe { lifegom_cli::make_default_device(args.device) };
    if let Some(dest) = &args.export {
        // Exporting a run's own checkpoint takes the run folder as training does (one process
        // on a run at a time).
        let _lock = match &args.from {
            ExportSource::Latest | ExportSource::Best if args.out.is_dir() => {
                Some(lifegom_cli::run_lock::RunLock::acquire(&args.out)?)
            }
            _ => None,
        };
        let source = match &args.from {
            ExportSource::Latest => latest_checkpoint(&args.out),
            ExportSource::Best => best_checkpoint(&args.out),
            ExportSource::File(path) => path.clone(),
        };
        let network = match &args.config {
            Some(config) => Some(ExperimentConfig::load(config)?.reconstructor()),
            None => None,
        };
        let bytes = export_model(
            &source,
            dest,
            args.subdivide_test,
            network.as_ref(),
            &args.device.device(),
        )?;
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
    if let Some(k) = args.accumulate {
        cfg.train.accumulate = usize::try_from(k)?;
    }
    #[cfg(feature = "mpi")]
    let mpi = lifegom_train::data_parallel::mpi::MpiReplicas::from_launcher()?;
    #[cfg(feature = "mpi")]
    let replicas: &dyn Replicas = match &mpi {
        Some(m) => m,
        None => &SingleProcess,
    };
    #[cfg(not(feature = "mpi"))]
    let replicas: &dyn Replicas = {
        if let Some(var) = lifegom_train::data_parallel::launcher_rank_variable() {
            anyhow::bail!(
                "started by an MPI launcher ({var} is set) but built without MPI: every rank would train alone into the same folder. Build with `--features lifegom-cli/mpi` (docs/data-parallel.md)"
            );
        }
        &SingleProcess
    };
    let stop = lifegom_cli::stop_on_ctrl_c("finishing this step and writing a checkpoint")?;
    lifegom_cli::stop_on_job_signals(&stop)?;
    let opts = RunOptions {
        out: args.out.clone(),
        resume: args.resume,
        init: args.init.clone(),
        max_minutes: args.max_minutes,
        steps: args.steps,
        device: args.device.device(),
        progress: true,
    };
    let summary = match train_with(&cfg, &opts, stop, replicas) {
        Ok(summary) => summary,
        #[cfg(feature = "mpi")]
        Err(e) if replicas.size() > 1 => {
            // The other ranks wait in a collective for this one: end them all.
            eprintln!("rank {}: error: {e:#}", replicas.rank());
            if let Some(m) = &mpi {
                m.abort(1);
            }
            return Err(e);
        }
        Err(e) => return Err(e),
    };
    let interrupted = summary.stop == StopReason::Interrupted;
    if replicas.rank() > 0 {
        return Ok(());
    }
    let last = summary.history.last();
    println!(
        "{}",
        serde_json::json!({
            "stop": format!("{:?}", summary.stop),
            "step": summary.step,
            "steps_this_run": summary.steps_this_run,
            "seconds": summary.seconds,
            "backend": args.device.name(),
            "ranks": replicas.size(),
            "checkpoint": summary.checkpoint.display().to_string(),
            "last_losses": last.map(|s| s.losses.clone()),
            "last_psnr_target": last.map(|s| s.psnr_target),
        })
    );
    if interrupted {
        // MPI must be finalised (the universe dropped) before the process exits.
        #[cfg(feature = "mpi")]
        drop(mpi);
        std::process::exit(130);
    }
    Ok(())
}
