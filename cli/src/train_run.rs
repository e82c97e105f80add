//! The training loop behind `lifegom-train` and the quickstart.
//!
//! Output folder layout (`--out`, e.g. `runs/<name>`):
//!
//! | path | what |
//! |---|---|
//! | `config.toml` | the experiment config the run was started with |
//! | `checkpoints/latest.lgck` | weights + optimiser + step, replaced atomically every `checkpoint_every` steps, at the end, on the time limit and on Ctrl-C |
//! | `metrics.jsonl` | one JSON object per logged step: losses, target PSNR, seconds, elapsed |
//! | `snapshots/step_NNNNNNN.png` | target ground truth, last-iteration render, error map |
//! | `loss_curve.png` | the logged losses against the step (written at every checkpoint) |
//!
//! On `--resume` the loop restarts from `checkpoints/latest.lgck`, drops log lines past the
//! checkpoint's step (they belong to work that was lost), and continues the same data schedule.

use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Instant;

use anyhow::{Context, bail};
use burn::tensor::Device;
use lifegom_data::dataset::{Dataset, Split};
use lifegom_eval::images::{Image, error_map, grid};
use lifegom_eval::plot::{Chart, PALETTE, Scale, Series, Style};
use lifegom_model::inputs::{SubjectRig, model_inputs};
use lifegom_model::reconstructor::MeshPurpose;

use lifegom_train::config::ExperimentConfig;
use lifegom_train::losses::UniformLaplacian;
use lifegom_train::prefetch::Prefetcher;
use lifegom_train::trainer::{StepStats, Trainer};

/// Options of a training run (the command line).
#[derive(Debug, Clone)]
pub struct RunOptions {
    /// Output folder.
    pub out: PathBuf,
    /// Continue from `out/checkpoints/latest.lgck` if it exists.
    pub resume: bool,
    /// Stop (with a checkpoint) after this many minutes of training.
    pub max_minutes: Option<f64>,
    /// Override of `[train] steps`.
    pub steps: Option<u64>,
    /// The (non-autodiff) device to train on.
    pub device: Device,
    /// Show a progress bar (off in tests).
    pub progress: bool,
}

/// Why the loop ended.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum StopReason {
    /// All steps done.
    Finished,
    /// `--max-minutes` reached.
    TimeLimit,
    /// Ctrl-C (or another stop request).
    Interrupted,
}

/// What a run did.
#[derive(Debug, Clone)]
pub struct RunSummary {
    /// Why it stopped.
    pub stop: StopReason,
    /// Optimiser steps at the end.
    pub step: u64,
    /// Steps taken in this invocation.
    pub steps_this_run: u64,
    /// Per-step statistics of this invocation.
    pub history: Vec<StepStats>,
    /// The final checkpoint.
    pub checkpoint: PathBuf,
    /// Wall time of this invocation's training (s).
    pub seconds: f64,
}

/// The checkpoint a run in `out` writes and resumes from.
pub fn latest_checkpoint(out: &Path) -> PathBuf {
    out.join("checkpoints").join("latest.lgck")
}

fn read_history(path: &Path, up_to: u64) -> Vec<serde_json::Value> {
    std::fs::read_to_string(path)
        .unwrap_or_default()
        .lines()
        .filter_map(|l| serde_json::from_str::<serde_json::Value>(l).ok())
        .filter(|v| v["step"].as_u64().is_some_and(|s| s <= up_to))
        .collect()
}

/// Draws `loss_curve.png` from `metrics.jsonl`.
pub fn write_loss_curve(out: &Path) -> anyhow::Result<()> {
    let lines = read_history(&out.join("metrics.jsonl"), u64::MAX);
    let mut series: Vec<Series> = Vec::new();
    for (k, name) in ["total", "rgb", "mask", "ssim", "laplacian"]
        .iter()
        .enumerate()
    {
        let points: Vec<(f64, f64)> = lines
            .iter()
            .filter_map(|v| Some((v["step"].as_f64()?, v[*name].as_f64()?)))
            .collect();
        if !points.is_empty() {
            series.push(Series {
                name: (*name).into(),
                points,
                labels: vec![],
                color: PALETTE[k % PALETTE.len()],
            });
        }
    }
    let chart = Chart {
        title: "training loss (weighted terms)".into(),
        x_label: "step".into(),
        y_label: "loss".into(),
        x_scale: Scale::Linear,
        y_scale: Scale::Log10,
        series,
        style: Style::Lines,
    };
    let path = out.join("loss_curve.png");
    chart
        .render(720, 420)
        .save(&path)
        .with_context(|| format!("writing {}", path.display()))
}

/// Trains `cfg` until its steps are done, the time limit, or `stop` is raised.
pub fn train(
    cfg: &ExperimentConfig,
    opts: &RunOptions,
    stop: Arc<AtomicBool>,
) -> anyhow::Result<RunSummary> {
    let _span = tracing::info_span!("train", out = %opts.out.display()).entered();
    std::fs::create_dir_all(opts.out.join("snapshots"))
        .with_context(|| format!("creating {}", opts.out.display()))?;
    if cfg.train.loss_lpips > 0.0 {
        bail!(
            "{}: [train] loss_lpips = {} but the LPIPS training loss (the AIST++ setting, docs/design.md §9.2) is not wired into the trainer yet; set it to 0",
            cfg.file.source.display(),
            cfg.train.loss_lpips
        );
    }
    let dataset = Arc::new(Dataset::open(&cfg.file.data, Split::Train)?);
    if dataset.is_empty() {
        bail!(
            "the training split of {} is empty",
            cfg.file.source.display()
        );
    }
    let bodies = SubjectRig::for_split(&dataset)?;
    let num_vertices = bodies[0].num_vertices();
    let ckpt = latest_checkpoint(&opts.out);
    let mut trainer = if opts.resume && ckpt.exists() {
        let t = Trainer::resume(&ckpt, &cfg.train, &opts.device)?;
        eprintln!("resuming from {} at step {}", ckpt.display(), t.step);
        t
    } else {
        if opts.resume {
            eprintln!(
                "--resume: no checkpoint at {}, starting fresh",
                ckpt.display()
            );
        }
        if cfg.file.source.exists() {
            std::fs::copy(&cfg.file.source, opts.out.join("config.toml"))
                .with_context(|| format!("copying {}", cfg.file.source.display()))?;
        }
        let _ = std::fs::remove_file(opts.out.join("metrics.jsonl"));
        let mut t = Trainer::new(cfg.reconstructor(), num_vertices, &cfg.train, &opts.device)?;
        if let Some(path) = &cfg.model.encoder_weights {
            let report = t.load_encoder_weights(path)?;
            eprintln!("{report}");
        } else {
            eprintln!(
                "no ImageNet ResNet-18 weights configured ([model] encoder_weights): the encoder starts from RANDOM initialisation"
            );
        }
        t
    };
    if trainer.model.vertex_embed.dims()[0] != num_vertices {
        bail!(
            "checkpoint {} has {} vertex embeddings, the data's template {} vertices",
            ckpt.display(),
            trainer.model.vertex_embed.dims()[0],
            num_vertices
        );
    }
    let mesh = trainer
        .config
        .mesh(&bodies[0].topology, MeshPurpose::Training, trainer.device())?;
    let laplacian = UniformLaplacian::new(&bodies[0].topology.faces, num_vertices)?;
    let total_steps = opts.steps.unwrap_or(cfg.train.steps);
    let (w, h) = (cfg.file.data.img_size[0], cfg.file.data.img_size[1]);

    // Keep the log consistent with the checkpoint: lines past it describe lost work.
    let log_path = opts.out.join("metrics.jsonl");
    let kept = read_history(&log_path, trainer.step);
    let mut log = std::fs::File::create(&log_path)
        .with_context(|| format!("writing {}", log_path.display()))?;
    for v in &kept {
        writeln!(log, "{v}")?;
    }
    let elapsed_before = kept
        .last()
        .and_then(|v| v["elapsed"].as_f64())
        .unwrap_or(0.0);

    let bar = if opts.progress {
        let bar = indicatif::ProgressBar::new(total_steps);
        bar.set_style(
            indicatif::ProgressStyle::with_template(
                "{elapsed_precise} [{bar:30}] {pos}/{len} {per_sec} ETA {eta} {msg}",
            )
            .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
        );
        bar.set_position(trainer.step);
        bar
    } else {
        indicatif::ProgressBar::hidden()
    };
    let started = Instant::now();
    let meta = serde_json::json!({ "config": cfg.file.source.display().to_string() });
    let mut history = Vec::new();
    let mut stop_reason = StopReason::Finished;
    let mut prefetch = Prefetcher::new(dataset.clone(), trainer.seed(), trainer.step);
    while trainer.step < total_steps {
        if stop.load(Ordering::SeqCst) {
            stop_reason = StopReason::Interrupted;
            break;
        }
        if opts
            .max_minutes
            .is_some_and(|m| started.elapsed().as_secs_f64() > m * 60.0)
        {
            stop_reason = StopReason::TimeLimit;
            break;
        }
        let step = trainer.step;
        let (sample, inputs) = {
            let _span = tracing::debug_span!("data").entered();
            let sample = prefetch.next_sample(&dataset, trainer.seed())?;
            let body = bodies
                .iter()
                .find(|b| b.name == sample.subject)
                .context("sample from an unknown subject")?;
            let inputs = model_inputs(body, &sample, w, h, trainer.device())?;
            (sample, inputs)
        };
        let out = trainer
            .train_step_with_render(&inputs, &mesh, &laplacian)
            .with_context(|| format!("training step {step} ({})", sample.frame_name))?;
        let stats = out.stats;
        let total = stats
            .losses
            .iter()
            .find(|(n, _)| n == "total")
            .map_or(f64::NAN, |(_, v)| *v);
        if !total.is_finite() {
            bail!(
                "non-finite loss at step {step} ({}): {:?}; last good checkpoint: {}",
                sample.frame_name,
                stats.losses,
                ckpt.display()
            );
        }
        bar.set_position(trainer.step);
        bar.set_message(format!("loss {total:.4} PSNR {:.2} dB", stats.psnr_target));
        if trainer.step.is_multiple_of(cfg.train.log_every) || trainer.step == 1 {
            let mut line = serde_json::Map::new();
            line.insert("step".into(), trainer.step.into());
            for (n, v) in &stats.losses {
                line.insert(n.clone(), (*v).into());
            }
            line.insert("psnr_target".into(), stats.psnr_target.into());
            line.insert("seconds".into(), stats.seconds.into());
            line.insert(
                "elapsed".into(),
                (elapsed_before + started.elapsed().as_secs_f64()).into(),
            );
            line.insert("sample".into(), sample.frame_name.clone().into());
            writeln!(log, "{}", serde_json::Value::Object(line))?;
            log.flush()?;
        }
        if trainer.step.is_multiple_of(cfg.train.snapshot_every) {
            let gt = Image::from_chw(inputs.target_rgb.clone())?;
            let pred = Image::from_chw(out.target_render)?;
            let err = error_map(&pred, &gt, 4.0)?;
            let path = opts
                .out
                .join("snapshots")
                .join(format!("step_{:07}.png", trainer.step));
            grid(&[vec![gt, pred, err]], 2, [1.0; 3]).save_png(&path)?;
        }
        if trainer.step.is_multiple_of(cfg.train.checkpoint_every) {
            trainer.save(&ckpt, meta.clone())?;
            write_loss_curve(&opts.out)?;
        }
        history.push(stats);
    }
    bar.finish_and_clear();
    trainer.save(&ckpt, meta)?;
    write_loss_curve(&opts.out)?;
    Ok(RunSummary {
        stop: stop_reason,
        step: trainer.step,
        steps_this_run: history.len() as u64,
        history,
        checkpoint: ckpt,
        seconds: started.elapsed().as_secs_f64(),
    })
}
