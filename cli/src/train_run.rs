//! The training loop behind `lifegom-train` and the quickstart.
//!
//! Output folder layout (`--out`, e.g. `runs/<name>`):
//!
//! | path | what |
//! |---|---|
//! | `config.toml` | the experiment config the run was started with |
//! | `checkpoints/latest.lgck` | weights + optimiser + step, replaced atomically every `checkpoint_every` steps, at the end, on the time limit and on Ctrl-C |
//! | `checkpoints/best.lgck` | the weights (no optimiser state: for evaluation and export) with the best validation PSNR at the last feedback step (the mean over the validation split and the held-out set when both are scored) since the file appeared (its header's `meta.validation` says step and PSNR), replaced atomically when a validation beats it |
//! | `metrics.jsonl` | one JSON object per logged step: losses, target PSNR, seconds, elapsed |
//! | `snapshots/step_NNNNNNN.png` | target ground truth, last-iteration render, error map |
//! | `loss_curve.png` | the logged losses against the step (written at every checkpoint) |
//! | `validation.jsonl` | every `validate_every` steps: PSNR and SSIM of each feedback step `t` on the validation split |
//! | `validation_baselines.json` | the same scores of the baselines that need no training (template in one colour, projective texturing) |
//! | `validation_curve.png` | validation PSNR (and LPIPS-alex) of each `t` against the step, with the baselines |
//! | `validation_baselines_held_out.json`, `validation_curve_held_out.png` | the same for the held-out set (design.md §8.11), when `[data] held_out_dir` names one; its scores are the `held_out` object of each `validation.jsonl` line |
//!
//! On `--resume` the loop restarts from `checkpoints/latest.lgck`, drops log lines past the
//! checkpoint's step (they belong to work that was lost), and continues the same data schedule.
//!
//! A batch whose loss or gradient is not finite is not applied (`StepStats::applied`): the
//! loop logs it with its samples (a `"skipped": true` line), keeps the weights and the step
//! counter, and goes on with the next samples; [`MAX_SKIPPED_IN_A_ROW`] such batches in a row
//! end the run with an error, the last checkpoint untouched.
//!
//! **Several ranks** (`mpirun -np N lifegom-train …`, [`train_with`]): every rank runs this loop
//! on its share of each batch (`lifegom_train::data_parallel`); rank 0 alone writes the folder
//! above, scores the validation split and shows progress. Every rank reads the checkpoint it
//! resumes from, so `--out` must be visible to all of them (a shared filesystem on a
//! cluster). Stop requests and time limits are agreed between the ranks, so all stop after the
//! same step, and the ranks compare a checksum of their weights before every checkpoint.

use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Instant;

use anyhow::{Context, bail};
use burn::module::Module;
use burn::tensor::Device;
use lifegom_data::dataset::{Dataset, Split};
use lifegom_eval::evaluate::{EvalSettings, Method, evaluate_split, mean_of};
use lifegom_eval::images::{Image, error_map, grid};
use lifegom_eval::metrics::{ErrorByRegion, SILHOUETTE_BAND_PX};
use lifegom_eval::perceptual::{
    LPIPS_ALEX_FILE, LPIPS_VGG_FILE, Lpips, LpipsNet, PerceptualModels,
};
use lifegom_eval::perceptual_scores::mean_lpips;
use lifegom_eval::plot::{Chart, PALETTE, Scale, Series, Style, render_panels};
use lifegom_eval::report::Summary;
use lifegom_eval::validation::score_feedback_steps;
use lifegom_model::inputs::model_inputs;
use lifegom_model::reconstructor::{MeshPurpose, ReconstructorConfig};
use lifegom_model::trained;

use lifegom_train::config::{ExperimentConfig, LpipsFallback, LpipsWeights};
use lifegom_train::data_parallel::{BatchLayout, Replicas, SingleProcess, weights_checksum};
use lifegom_train::losses::UniformLaplacian;
use lifegom_train::prefetch::Prefetcher;
use lifegom_train::source::{StepSample, TrainingSource};
use lifegom_train::trainer::{BatchSample, StepStats, Trainer};

use crate::dashboard::{Display, DisplayKind};
use crate::eval_run::{BASELINE_PROJECTIVE, BASELINE_TEMPLATE};

/// Options of a training run (the command line).
#[derive(Debug, Clone)]
pub struct RunOptions {
    /// Output folder.
    pub out: PathBuf,
    /// Continue from `out/checkpoints/latest.lgck` if it exists.
    pub resume: bool,
    /// Fine-tune: start a new run from these weights (a `.lgck` or an official checkpoint)
    /// with a fresh optimiser. A run resumed from its own checkpoint ignores it (it started
    /// from these weights).
    pub init: Option<PathBuf>,
    /// Stop (with a checkpoint) after this many minutes of training.
    pub max_minutes: Option<f64>,
    /// Override of `[train] steps`.
    pub steps: Option<u64>,
    /// The (non-autodiff) device to train on.
    pub device: Device,
    /// Show progress: burn-train's dashboard in a terminal, a progress line elsewhere (off in
    /// tests; `crate::dashboard`).
    pub progress: bool,
}

/// Where `--export` writes to, told by the destination's extension.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ExportFormat {
    /// A lifegom trained-model file (`.lgck`; any other extension too).
    Lifegom,
    /// The official code's state dict, under its key names and PyTorch layouts, in a
    /// SafeTensors file (`.safetensors`): for PyTorch users; weights only.
    OfficialSafetensors,
}

impl ExportFormat {
    /// The format `dest` asks for.
    pub fn of(dest: &Path) -> Self {
        if dest
            .extension()
            .is_some_and(|e| e.eq_ignore_ascii_case("safetensors"))
        {
            Self::OfficialSafetensors
        } else {
            Self::Lifegom
        }
    }
}

/// Writes the model of `source` (a run's checkpoint, or any `.lgck` or official checkpoint;
/// weights, config, metadata) to `dest` without the trainer's payload (optimizer state, data
/// position): what inference needs. An official checkpoint carries no config: it is loaded
/// into `official_network` (the experiment's network), and refused without one.
/// `subdivide_test` replaces the default subdivision at inference (the weights serve every
/// level). A `dest` ending in `.safetensors` gets the official state dict instead
/// ([`ExportFormat`]). Returns the size written.
pub fn export_model(
    source: &Path,
    dest: &Path,
    subdivide_test: Option<u32>,
    official_network: Option<&ReconstructorConfig>,
    device: &Device,
) -> anyhow::Result<u64> {
    let mut loaded = match official_network {
        Some(network) => trained::load_any(source, network, device)?,
        None if !trained::is_lifegom_file(source)? => bail!(
            "{}: not a lifegom model file; an official checkpoint holds weights only: pass the \
             experiment's `--config` so that its `[model]` network receives them",
            source.display()
        ),
        None => trained::load(source, device)?,
    };
    if let Some(s) = subdivide_test {
        loaded.config.subdivide_test = s;
    }
    // Best-weights files written before they recorded their step name it only in `validation`.
    let validated_step = loaded.header.meta["validation"]["step"].as_u64();
    if let Some(meta) = loaded.header.meta.as_object_mut()
        && !meta.contains_key("step")
        && let Some(step) = validated_step
    {
        meta.insert("step".into(), step.into());
    }
    if let Some(dir) = dest.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    }
    match ExportFormat::of(dest) {
        ExportFormat::Lifegom => {
            trained::save(dest, &loaded.model, &loaded.config, loaded.header.meta, &[])?;
        }
        ExportFormat::OfficialSafetensors => {
            lifegom_model::checkpoint::save_official_safetensors(&loaded.model, dest)?;
        }
    }
    Ok(std::fs::metadata(dest)
        .with_context(|| format!("reading {}", dest.display()))?
        .len())
}

/// Batches with a non-finite loss or gradient that the loop skips in a row before it stops
/// with an error (one is a bad sample; ten in a row is a broken run).
pub const MAX_SKIPPED_IN_A_ROW: u32 = 10;

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
    // Bytes, not a string: a line torn by a full disk or a kill may end inside a UTF-8
    // character, and must cost that line only.
    let bytes = std::fs::read(path).unwrap_or_default();
    String::from_utf8_lossy(&bytes)
        .lines()
        .filter_map(|l| serde_json::from_str::<serde_json::Value>(l).ok())
        .filter(|v| v["step"].as_u64().is_some_and(|s| s <= up_to))
        .collect()
}

/// The validation PSNR of a `validation.jsonl` line at its last feedback step (`T`).
fn final_step_psnr(line: &serde_json::Value) -> Option<f64> {
    line["psnr"].as_array()?.last()?.as_f64()
}

/// `<out>/checkpoints/best.lgck`: see the module docs.
pub fn best_checkpoint(out: &Path) -> PathBuf {
    out.join("checkpoints").join("best.lgck")
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
                ..Default::default()
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
    chart.render(720, 420).save_png_and_svg(&path)?;
    Ok(())
}

/// A validation set the run scores: the generator's validation split, or the held-out set
/// (design.md §8.11), whose scores go under `key` in each `validation.jsonl` line.
struct ValidationSet {
    /// `None` for the validation split (its scores at the top level of a line); `Some("held_out")`.
    key: Option<&'static str>,
    dataset: Dataset,
}

impl ValidationSet {
    /// The baselines' scores file of this set.
    fn baselines_file(&self) -> String {
        baselines_file(self.key)
    }
}

/// `validation_baselines.json`, or `validation_baselines_<key>.json` for the held-out set.
fn baselines_file(key: Option<&str>) -> String {
    match key {
        None => "validation_baselines.json".into(),
        Some(k) => format!("validation_baselines_{k}.json"),
    }
}

/// The validation sets and their baselines' scores, when `[train] validate_every` asks for it.
struct Validation {
    sets: Vec<ValidationSet>,
    subjects: usize,
    subdivide: u32,
    /// LPIPS-alex, when its weights are in the weights folder (`lifegom-weights fetch`).
    lpips: Option<Lpips>,
}

impl Validation {
    /// Opens the validation split (and the held-out set, when the config names one) and scores
    /// the baselines once (they do not train); `None` with a message when validation is off or
    /// the split is missing.
    fn open(cfg: &ExperimentConfig, subdivide: u32, out: &Path, device: &Device) -> Option<Self> {
        if cfg.train.validate_every == 0 {
            return None;
        }
        let open = |data: &lifegom_data::dataset::DataConfig, what: &str| match Dataset::open(
            data,
            Split::Val,
        ) {
            Ok(d) if !d.is_empty() => Some(d),
            Ok(_) => {
                eprintln!("validation: the {what} is empty; no validation curves for it");
                None
            }
            Err(e) => {
                eprintln!("validation: {e}; no validation curves for the {what}");
                None
            }
        };
        let dataset = open(&cfg.file.data, "validation split")?;
        let mut sets = vec![ValidationSet { key: None, dataset }];
        if let Some(held) = cfg.file.data.held_out()
            && let Some(dataset) = open(&held, "held-out set")
        {
            sets.push(ValidationSet {
                key: Some(HELD_OUT),
                dataset,
            });
        }
        let lpips_path = PerceptualModels::default_dir().join(LPIPS_ALEX_FILE);
        let lpips = if lpips_path.is_file() {
            match Lpips::load(LpipsNet::Alex, &lpips_path, device) {
                Ok(net) => Some(net),
                Err(e) => {
                    eprintln!("validation: {e}; no LPIPS on validation");
                    None
                }
            }
        } else {
            None
        };
        let v = Self {
            sets,
            subjects: cfg.train.validate_subjects.max(1),
            subdivide,
            lpips,
        };
        for set in &v.sets {
            v.score_baselines(set, out, device);
        }
        Some(v)
    }

    /// Scores the no-learning baselines on `set` into its baselines file.
    fn score_baselines(&self, set: &ValidationSet, out: &Path, device: &Device) {
        let subdivide = self.subdivide;
        let mut baselines = serde_json::Map::new();
        for (name, method) in [
            (BASELINE_TEMPLATE, Method::TemplateBaseline { subdivide }),
            (
                BASELINE_PROJECTIVE,
                Method::ProjectiveTexturing { subdivide },
            ),
        ] {
            let settings = EvalSettings {
                out: out.to_path_buf(),
                subdivide: Some(subdivide),
                iterations: None,
                save_predictions: false,
                sheets: 0,
                max_subjects: Some(self.subjects),
                refine_steps: 0,
            };
            match evaluate_split(&method, &set.dataset, &settings, device) {
                Ok(s) => {
                    let psnr = mean_of(&s.views, |x| Some(x.psnr));
                    let ssim = mean_of(&s.views, |x| Some(x.ssim));
                    let mut entry = serde_json::json!({"psnr": psnr, "ssim": ssim});
                    if let Some(e) = Summary::of(&s, None).regions {
                        entry[SILHOUETTE_MSE] = serde_json::json!(e.silhouette * 1e4);
                        entry[INSIDE_MSE] = serde_json::json!(e.inside * 1e4);
                    }
                    if let Some(net) = &self.lpips {
                        match mean_lpips(net, &s.images.pred, &s.images.gt, device) {
                            Ok(d) => entry["lpips_alex"] = serde_json::json!(d),
                            Err(e) => eprintln!("validation: baseline {name}: LPIPS: {e}"),
                        }
                    }
                    baselines.insert(name.into(), entry);
                }
                Err(e) => eprintln!("validation: baseline {name}: {e}"),
            }
        }
        let path = out.join(set.baselines_file());
        if let Err(e) = lifegom_render::atomic_file::write_atomic(
            &path,
            serde_json::to_string_pretty(&baselines)
                .unwrap_or_default()
                .as_bytes(),
        ) {
            eprintln!("validation: writing {}: {e}", path.display());
        }
    }

    /// Scores every feedback step of the trainer's current weights on every set; one line of
    /// `validation.jsonl`.
    fn run(&self, trainer: &Trainer, device: &Device) -> anyhow::Result<serde_json::Value> {
        let _span = tracing::info_span!("validation", step = trainer.step).entered();
        let model = trainer.model.valid();
        let mut line = serde_json::json!({ "step": trainer.step });
        for set in &self.sets {
            let scores = score_feedback_steps(
                &model,
                &set.dataset,
                self.subdivide,
                Some(self.subjects),
                self.lpips.as_ref(),
                device,
            )?;
            let mut entry = serde_json::json!({
                "psnr": scores.iter().map(|s| s.psnr).collect::<Vec<_>>(),
                "ssim": scores.iter().map(|s| s.ssim).collect::<Vec<_>>(),
            });
            if self.lpips.is_some() {
                entry["lpips_alex"] =
                    serde_json::json!(scores.iter().map(|s| s.lpips_alex).collect::<Vec<_>>());
            }
            let per_t = |f: fn(&ErrorByRegion) -> f64| {
                scores
                    .iter()
                    .map(|s| s.regions.as_ref().map(|e| f(e) * 1e4))
                    .collect::<Option<Vec<_>>>()
            };
            if let (Some(band), Some(inside)) = (per_t(|e| e.silhouette), per_t(|e| e.inside)) {
                entry[SILHOUETTE_MSE] = serde_json::json!(band);
                entry[INSIDE_MSE] = serde_json::json!(inside);
            }
            match set.key {
                None => {
                    for (k, v) in entry.as_object().into_iter().flatten() {
                        line[k] = v.clone();
                    }
                }
                Some(key) => line[key] = entry,
            }
        }
        Ok(line)
    }
}

/// The key of the held-out set's scores in `validation.jsonl` (design.md §8.11).
pub const HELD_OUT: &str = "held_out";

/// The score a validation line is judged by for `best.lgck`: the final feedback step's PSNR,
/// averaged over the validation split and the held-out set when both were scored, so the kept
/// weights are the ones that do best on both kinds of people.
fn selection_psnr(line: &serde_json::Value) -> Option<f64> {
    let own = final_step_psnr(line)?;
    Some(match final_step_psnr(&line[HELD_OUT]) {
        Some(held) => 0.5 * (own + held),
        None => own,
    })
}

/// Draws `validation_curve.png` from `validation.jsonl` and `validation_baselines.json`, and
/// `validation_curve_held_out.png` from the held-out set's scores when they were logged.
pub fn write_validation_curve(out: &Path) -> anyhow::Result<()> {
    let lines = read_history(&out.join("validation.jsonl"), u64::MAX);
    let held: Vec<serde_json::Value> = lines
        .iter()
        .filter_map(|v| {
            let mut h = v.get(HELD_OUT)?.clone();
            h["step"] = v["step"].clone();
            Some(h)
        })
        .collect();
    for (key, lines, file, people) in [
        (None, &lines, "validation_curve.png", "unseen subjects"),
        (
            Some(HELD_OUT),
            &held,
            "validation_curve_held_out.png",
            "held-out family",
        ),
    ] {
        let baselines: serde_json::Value = std::fs::read_to_string(out.join(baselines_file(key)))
            .ok()
            .and_then(|t| serde_json::from_str(&t).ok())
            .unwrap_or_default();
        let Some(psnr) = validation_chart(lines, &baselines, "psnr", people) else {
            continue;
        };
        let path = out.join(file);
        let panels: Vec<Chart> = std::iter::once(psnr)
            .chain(validation_chart(lines, &baselines, "lpips_alex", people))
            .chain(validation_chart(lines, &baselines, SILHOUETTE_MSE, people))
            .collect();
        match panels.as_slice() {
            [one] => one.render(720, 420).save_png_and_svg(&path)?,
            many => render_panels(many, 640 * many.len() as u32, 420).save_png_and_svg(&path)?,
        }
    }
    Ok(())
}

/// `validation.jsonl`'s key for the MSE (×10⁴) within [`SILHOUETTE_BAND_PX`] of the
/// ground-truth silhouette, per feedback step ([`lifegom_eval::metrics::ErrorByRegion`]):
/// where the model's outline stands.
pub const SILHOUETTE_MSE: &str = "silhouette_mse_x1e4";
/// The same for the foreground farther in: where its appearance stands.
pub const INSIDE_MSE: &str = "inside_mse_x1e4";

/// One validation metric (`psnr`, `lpips_alex`, [`SILHOUETTE_MSE`]) of every feedback step
/// against the training step, with the baselines' level; `None` when no line logged it.
fn validation_chart(
    lines: &[serde_json::Value],
    baselines: &serde_json::Value,
    key: &str,
    people: &str,
) -> Option<Chart> {
    let t_max = lines
        .iter()
        .filter_map(|v| v[key].as_array())
        .map(Vec::len)
        .max()?;
    let mut series: Vec<Series> = (0..t_max)
        .map(|t| Series {
            name: format!("model, t = {}", t + 1),
            points: lines
                .iter()
                .filter_map(|v| Some((v["step"].as_f64()?, v[key][t].as_f64()?)))
                .collect(),
            labels: vec![],
            color: PALETTE[t % PALETTE.len()],
            ..Default::default()
        })
        .collect();
    let first = lines
        .first()
        .and_then(|v| v["step"].as_f64())
        .unwrap_or(0.0);
    let last = lines.last().and_then(|v| v["step"].as_f64()).unwrap_or(1.0);
    if let Some(map) = baselines.as_object() {
        for (k, (name, b)) in map.iter().enumerate() {
            if let Some(level) = b[key].as_f64() {
                series.push(Series {
                    name: name.clone(),
                    points: vec![(first, level), (last.max(first + 1.0), level)],
                    labels: vec![],
                    color: PALETTE[(t_max + k) % PALETTE.len()],
                    ..Default::default()
                });
            }
        }
    }
    let (title, y_label) = match key {
        "psnr" => (
            format!("validation PSNR per feedback step ({people})"),
            "PSNR (dB, higher is better)".to_owned(),
        ),
        SILHOUETTE_MSE => (
            format!("MSE near the silhouette per feedback step ({people})"),
            format!("MSE ×1e4 within {SILHOUETTE_BAND_PX} px of the outline (lower is better)"),
        ),
        _ => (
            format!("validation LPIPS-alex per feedback step ({people})"),
            "LPIPS-alex (lower is better)".to_owned(),
        ),
    };
    Some(Chart {
        title,
        x_label: "training step".into(),
        y_label,
        x_scale: Scale::Linear,
        y_scale: Scale::Linear,
        series,
        style: Style::Lines,
    })
}

/// Trains `cfg` until its steps are done, the time limit, or `stop` is raised.
pub fn train(
    cfg: &ExperimentConfig,
    opts: &RunOptions,
    stop: Arc<AtomicBool>,
) -> anyhow::Result<RunSummary> {
    train_with(cfg, opts, stop, &SingleProcess)
}

/// [`train`] as one rank of a data-parallel job (module docs).
pub fn train_with(
    cfg: &ExperimentConfig,
    opts: &RunOptions,
    stop: Arc<AtomicBool>,
    replicas: &dyn Replicas,
) -> anyhow::Result<RunSummary> {
    let _span =
        tracing::info_span!("train", out = %opts.out.display(), rank = replicas.rank()).entered();
    let root = replicas.rank() == 0;
    // One writer per run folder; the other ranks of a data-parallel job write nothing there.
    let _lock = if root {
        Some(crate::run_lock::RunLock::acquire(&opts.out)?)
    } else {
        None
    };
    if root {
        std::fs::create_dir_all(opts.out.join("snapshots"))
            .with_context(|| format!("creating {}", opts.out.display()))?;
        // A run killed while writing left its temporary file; the folder is this rank's alone.
        let stale = lifegom_render::atomic_file::remove_stale_temporaries(&opts.out, 2)
            .with_context(|| format!("clearing stale temporary files in {}", opts.out.display()))?;
        if stale > 0 {
            tracing::info!(stale, "removed temporary files a killed run left");
        }
    }
    let lpips_weights = if PerceptualModels::default_dir()
        .join(LPIPS_VGG_FILE)
        .is_file()
    {
        LpipsWeights::Present
    } else {
        LpipsWeights::Absent
    };
    if cfg.train.loss_lpips > 0.0
        && lpips_weights == LpipsWeights::Absent
        && cfg.train.lpips_fallback == LpipsFallback::Refuse
    {
        bail!(
            "{}: [train] loss_lpips = {} but the LPIPS-VGG weights are not in {} (the AIST++ setting, docs/design.md §9.2): fetch them with `lifegom-weights fetch`, set loss_lpips to 0, or train with 1 - SSIM in its place with [train] lpips_fallback = \"ssim\"",
            cfg.file.source.display(),
            cfg.train.loss_lpips,
            PerceptualModels::default_dir().display()
        );
    }
    if let Some(note) = cfg.train.lpips_note(lpips_weights) {
        eprintln!("{note}");
    }
    let source = Arc::new(
        TrainingSource::open(cfg)
            .with_context(|| format!("training data of {}", cfg.file.source.display()))?,
    );
    let rig = source.reference_rig();
    let num_vertices = rig.num_vertices();
    let ckpt = latest_checkpoint(&opts.out);
    // Only rank 0 talks; the others would repeat it N times.
    let say = |line: &str| {
        if root {
            eprintln!("{line}");
        }
    };
    let mut trainer = if opts.resume && ckpt.exists() {
        let t = Trainer::resume(&ckpt, &cfg.train, &opts.device)?;
        say(&format!(
            "resuming from {} at step {}",
            ckpt.display(),
            t.step
        ));
        t
    } else {
        if opts.resume {
            say(&format!(
                "--resume: no checkpoint at {}, starting fresh",
                ckpt.display()
            ));
        }
        if root {
            if cfg.file.source.exists() {
                std::fs::copy(&cfg.file.source, opts.out.join("config.toml"))
                    .with_context(|| format!("copying {}", cfg.file.source.display()))?;
            }
            let _ = std::fs::remove_file(opts.out.join("metrics.jsonl"));
        }
        if let Some(init) = &opts.init {
            let (t, line) = Trainer::from_weights(
                init,
                cfg.reconstructor(),
                num_vertices,
                &cfg.train,
                &opts.device,
            )?;
            say(&line);
            t
        } else {
            let mut t = Trainer::new(cfg.reconstructor(), num_vertices, &cfg.train, &opts.device)?;
            if let Some(path) = &cfg.model.encoder_weights {
                let report = t.load_encoder_weights(path)?;
                say(&report);
            } else {
                say(
                    "no ImageNet ResNet-18 weights configured ([model] encoder_weights): the encoder starts from RANDOM initialisation",
                );
            }
            t
        }
    };
    let layout = BatchLayout {
        first_sample: trainer.samples,
        accumulate: cfg.train.accumulate,
        rank: replicas.rank(),
        ranks: replicas.size(),
    };
    if layout.batch() > 1 {
        say(&format!(
            "batch of {} samples a step ([train] accumulate = {} × {} rank(s)); the step takes their mean gradient, so the learning rates are unchanged (encoder {}, reconstructor {})",
            layout.batch(),
            layout.accumulate,
            layout.ranks,
            cfg.train.lr_encoder,
            cfg.train.lr_reconstructor
        ));
    }
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
        .mesh(&rig.topology, MeshPurpose::Training, trainer.device())?;
    let laplacian = UniformLaplacian::new(&rig.topology.faces, num_vertices)?;
    let total_steps = opts.steps.unwrap_or(cfg.train.steps);
    let (w, h) = (cfg.file.data.img_size[0], cfg.file.data.img_size[1]);

    // Rank 0's files (module docs). Keep the logs consistent with the checkpoint: lines past it
    // describe lost work.
    let keep_log = |path: &Path| -> anyhow::Result<(std::fs::File, Vec<serde_json::Value>)> {
        let kept = read_history(path, trainer.step);
        // Rewritten whole and renamed into place, then appended to: a full disk here leaves
        // the old log, never a truncated one.
        let text: String = kept.iter().map(|v| format!("{v}\n")).collect();
        lifegom_render::atomic_file::write_atomic(path, text.as_bytes())
            .with_context(|| format!("writing {}", path.display()))?;
        let file = std::fs::OpenOptions::new()
            .append(true)
            .open(path)
            .with_context(|| format!("writing {}", path.display()))?;
        Ok((file, kept))
    };
    let (mut val_log, mut log, elapsed_before) = if root {
        let (val_log, _) = keep_log(&opts.out.join("validation.jsonl"))?;
        let (log, kept) = keep_log(&opts.out.join("metrics.jsonl"))?;
        let elapsed = kept
            .last()
            .and_then(|v| v["elapsed"].as_f64())
            .unwrap_or(0.0);
        (Some(val_log), Some(log), elapsed)
    } else {
        (None, None, 0.0)
    };
    let validation = root
        .then(|| Validation::open(cfg, trainer.config.subdivide_test, &opts.out, &opts.device))
        .flatten();

    let mut display = Display::start(
        DisplayKind::choose(opts.progress && root),
        trainer.step,
        total_steps,
    );
    let started = Instant::now();
    let meta = serde_json::json!({ "config": cfg.file.source.display().to_string() });
    // With a constant learning rate the validation score swings between evaluations (demo v2:
    // ±0.6 dB), so the run keeps its best weights beside its latest. The score to beat is the
    // kept file's own, so a resumed run never replaces it with worse weights.
    let best_path = best_checkpoint(&opts.out);
    let mut best_psnr = lifegom_model::trained::read_header(&best_path)
        .ok()
        .and_then(|h| h.meta["validation"]["psnr"].as_f64())
        .unwrap_or(f64::NEG_INFINITY);
    // A checkpoint is every rank's model only if they all hold the same weights.
    let save = |trainer: &Trainer| -> anyhow::Result<()> {
        if replicas.size() > 1 {
            replicas.agree(trainer.step, weights_checksum(&trainer.model)?)?;
        }
        if root {
            trainer.save(&ckpt, meta.clone())?;
            write_loss_curve(&opts.out)?;
        }
        Ok(())
    };
    if replicas.size() > 1 {
        // Fresh replicas start from the same seed, resumed ones from the same file: check it.
        replicas.agree(trainer.step, weights_checksum(&trainer.model)?)?;
    }
    let mut history = Vec::new();
    let mut skipped_in_a_row = 0;
    let mut stop_reason = StopReason::Finished;
    let mut prefetch = Prefetcher::new(source.clone(), trainer.seed(), layout);
    while trainer.step < total_steps {
        // Every rank must take the same steps: one rank's stop request stops them all.
        let interrupted = stop.load(Ordering::SeqCst) || display.stop_requested();
        let timed_out = opts
            .max_minutes
            .is_some_and(|m| started.elapsed().as_secs_f64() > m * 60.0);
        if replicas.any(interrupted || timed_out) {
            stop_reason = if replicas.any(interrupted) {
                StopReason::Interrupted
            } else {
                StopReason::TimeLimit
            };
            break;
        }
        let step = trainer.step;
        let mut samples = Vec::with_capacity(layout.accumulate);
        {
            let _span = tracing::debug_span!("data").entered();
            for _ in 0..layout.accumulate {
                let StepSample { index, sample, rig } = prefetch.next_sample()?;
                let inputs = model_inputs(&rig, &sample, w, h, trainer.device())?;
                samples.push((index, sample, inputs));
            }
        }
        let batch: Vec<BatchSample> = samples
            .iter()
            .map(|(index, _, inputs)| BatchSample {
                index: *index,
                inputs,
            })
            .collect();
        let names = || {
            samples
                .iter()
                .map(|(_, s, _)| s.frame_name.as_str())
                .collect::<Vec<_>>()
                .join(", ")
        };
        let out = trainer
            .train_batch(&batch, &mesh, &laplacian, replicas)
            .with_context(|| format!("training step {step} ({})", names()))?;
        let stats = out.stats;
        if !stats.applied {
            skipped_in_a_row += 1;
            say(&format!(
                "step {} skipped: the loss or gradient of {} is not finite ({:?}); the weights are unchanged",
                step + 1,
                names(),
                stats.losses
            ));
            if let Some(log) = &mut log {
                let line = serde_json::json!({
                    "step": trainer.step,
                    "skipped": true,
                    "sample": names(),
                    "losses": stats.losses,
                });
                writeln!(log, "{line}")?;
                log.flush()?;
            }
            if skipped_in_a_row >= MAX_SKIPPED_IN_A_ROW {
                bail!(
                    "{MAX_SKIPPED_IN_A_ROW} batches in a row had a non-finite loss or gradient (the last: {}); stopping. Last good checkpoint: {}",
                    names(),
                    ckpt.display()
                );
            }
            continue;
        }
        skipped_in_a_row = 0;
        display.step(&stats);
        if let Some(log) = &mut log
            && (trainer.step.is_multiple_of(cfg.train.log_every) || trainer.step == 1)
        {
            let mut line = serde_json::Map::new();
            line.insert("step".into(), trainer.step.into());
            for (n, v) in &stats.losses {
                line.insert(n.clone(), (*v).into());
            }
            line.insert("psnr_target".into(), stats.psnr_target.into());
            line.insert(
                "psnr_target_steps".into(),
                stats.psnr_target_steps.clone().into(),
            );
            line.insert(
                "psnr_source_steps".into(),
                stats.psnr_source_steps.clone().into(),
            );
            line.insert("seconds".into(), stats.seconds.into());
            line.insert(
                "elapsed".into(),
                (elapsed_before + started.elapsed().as_secs_f64()).into(),
            );
            if stats.batch > 1 {
                line.insert("batch".into(), stats.batch.into());
            }
            if replicas.size() > 1 {
                line.insert("ranks".into(), replicas.size().into());
                line.insert("exchange_seconds".into(), stats.exchange_seconds.into());
            }
            // This rank's samples (rank 0's share of the batch).
            line.insert("sample".into(), names().into());
            writeln!(log, "{}", serde_json::Value::Object(line))?;
            log.flush()?;
        }
        if root && trainer.step.is_multiple_of(cfg.train.snapshot_every) {
            let (_, _, inputs) = samples
                .last()
                .ok_or_else(|| anyhow::anyhow!("empty batch"))?;
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
            save(&trainer)?;
        }
        if let (Some(v), Some(val_log)) = (&validation, &mut val_log)
            && trainer.step.is_multiple_of(cfg.train.validate_every)
        {
            let line = v.run(&trainer, &opts.device)?;
            if let Some(psnr) = line["psnr"].as_array() {
                display.validation(&psnr.iter().filter_map(|p| p.as_f64()).collect::<Vec<_>>());
            }
            writeln!(val_log, "{line}")?;
            val_log.flush()?;
            write_validation_curve(&opts.out)?;
            if let Some(psnr) = selection_psnr(&line)
                && psnr > best_psnr
            {
                let mut best_meta = meta.clone();
                best_meta["validation"] = serde_json::json!({ "step": trainer.step, "psnr": psnr });
                best_meta["step"] = trainer.step.into();
                // Weights only, as `--export` writes them: runs resume from `latest.lgck`.
                trained::save(&best_path, &trainer.model, &trainer.config, best_meta, &[])?;
                best_psnr = psnr;
            }
        }
        history.push(stats);
    }
    display.finish();
    save(&trainer)?;
    Ok(RunSummary {
        stop: stop_reason,
        step: trainer.step,
        steps_this_run: history.len() as u64,
        history,
        checkpoint: ckpt,
        seconds: started.elapsed().as_secs_f64(),
    })
}
