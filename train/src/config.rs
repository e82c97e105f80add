//! Experiment configs: one TOML file per experiment (`configs/*.toml`).
//!
//! `lifegom-data` reads `[data]` (and `[synthetic]`); this module adds `[model]` and `[train]`.
//! Both sections are optional: the defaults are the reference's THuman view3 settings (design.md §9.3:
//! T = 3, subdivisions 1 in training and 2 at test, lr 1e-4 encoder / 5e-5 reconstructor, losses
//! 1/5/1/0/100, seed 42) with the paper network. Unknown keys are errors, so a typo never
//! silently falls back to a default.

use std::path::{Path, PathBuf};

use lifegom_data::config::ConfigFile;
use lifegom_model::reconstructor::ReconstructorConfig;
use serde::{Deserialize, Serialize};

use crate::losses::LossWeights;

/// Errors reading an experiment config; each names the file.
#[derive(Debug, thiserror::Error)]
pub enum ConfigError {
    /// The `[data]` part.
    #[error(transparent)]
    Data(#[from] lifegom_data::DataError),
    /// The `[model]` or `[train]` part.
    #[error("{path}: {reason}")]
    Invalid {
        /// The config file.
        path: PathBuf,
        /// What is wrong.
        reason: String,
    },
}

/// Which network size.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "lowercase")]
pub enum Preset {
    /// Every component at toy width: tests and the 2-core quickstart.
    Tiny,
    /// ¼-width encoder with the paper's fusion and Point Transformer.
    Cpu,
    /// The paper's network (1152 channels).
    #[default]
    Paper,
}

/// `[model]`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ModelSection {
    /// Network size.
    pub preset: Preset,
    /// Feedback steps T.
    pub iterations: usize,
    /// Subdivisions of the Gaussians' mesh while training.
    pub subdivide_train: u32,
    /// Subdivisions at inference.
    pub subdivide_test: u32,
    /// Optional torchvision ResNet-18 weights for the encoder (`.pth` / `.safetensors`).
    pub encoder_weights: Option<PathBuf>,
}

impl Default for ModelSection {
    fn default() -> Self {
        Self {
            preset: Preset::Paper,
            iterations: 3,
            subdivide_train: 1,
            subdivide_test: 2,
            encoder_weights: None,
        }
    }
}

impl ModelSection {
    /// The reconstructor config for `num_views` source views.
    pub fn reconstructor(&self, num_views: usize) -> ReconstructorConfig {
        let base = match self.preset {
            Preset::Tiny => ReconstructorConfig::tiny(num_views),
            Preset::Cpu => ReconstructorConfig::cpu(num_views),
            Preset::Paper => ReconstructorConfig::paper(num_views),
        };
        base.with_iterations(self.iterations)
            .with_subdivide_train(self.subdivide_train)
            .with_subdivide_test(self.subdivide_test)
    }
}

/// Where training samples come from (`[train] subjects`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "lowercase")]
pub enum TrainingSubjects {
    /// The training split on disk (`[data] train_dir`), in epochs: the reference's setting.
    #[default]
    Split,
    /// A fresh synthetic subject for every step, drawn as `[synthetic]` describes
    /// (`lifegom_data::synth::stream`): no person is seen twice.
    Procedural,
}

/// What the LPIPS training term is when `[train] loss_lpips > 0` (the paper's AIST++ setting)
/// and the LPIPS-VGG weights are not in the weights folder (`lifegom-weights fetch` puts them
/// there; with them the term is the real LPIPS-VGG, design.md §9.2).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum LpipsFallback {
    /// No stand-in: without the weights, a config with `loss_lpips > 0` is refused when
    /// training starts.
    #[default]
    Refuse,
    /// `1 − SSIM` (the training SSIM, design.md §9.2) at the LPIPS weight, added to the SSIM
    /// term; the training log says so in its first lines. SSIM is the other structural loss
    /// of the paper (its THuman setting) and needs no weights.
    Ssim,
}

/// Whether the trainer has the LPIPS-VGG network for the LPIPS term.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LpipsWeights {
    /// Loaded: the term is LPIPS-VGG.
    Present,
    /// Not in the weights folder: [`LpipsFallback`] decides.
    Absent,
}

/// `[train]`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct TrainSection {
    /// Optimiser steps.
    pub steps: u64,
    /// Samples whose gradients each process sums before a step (the reference's batch size is
    /// 1). The step takes their mean (over all ranks of an MPI job too:
    /// `crate::data_parallel`), so the learning rates keep their meaning; the batch is
    /// `accumulate × ranks`.
    pub accumulate: usize,
    /// Where the samples come from.
    pub subjects: TrainingSubjects,
    /// Adam learning rate of the image encoder.
    pub lr_encoder: f64,
    /// Adam learning rate of everything else (fusion, Point Transformer, heads, embeddings).
    pub lr_reconstructor: f64,
    /// Seed of the data order, the backgrounds, the source-view choice and dropout.
    pub seed: u64,
    /// Loss weight of the RGB L1.
    pub loss_rgb: f64,
    /// Loss weight of the mask L1.
    pub loss_mask: f64,
    /// Loss weight of 1 − SSIM.
    pub loss_ssim: f64,
    /// Loss weight of LPIPS-VGG (needs the LPIPS weights; see `lpips_fallback`).
    pub loss_lpips: f64,
    /// What stands in for LPIPS when `loss_lpips > 0` ([`LpipsFallback`]).
    pub lpips_fallback: LpipsFallback,
    /// Loss weight of the uniform Laplacian.
    pub loss_laplacian: f64,
    /// Write a checkpoint every this many steps (and at the end).
    pub checkpoint_every: u64,
    /// Write a snapshot PNG every this many steps.
    pub snapshot_every: u64,
    /// Append a line to `metrics.jsonl` every this many steps.
    pub log_every: u64,
    /// Score every feedback step on the validation split every this many steps (0: never);
    /// `validation.jsonl` and `validation_curve.png`.
    pub validate_every: u64,
    /// Validation subjects scored (the first ones of the split).
    pub validate_subjects: usize,
}

impl Default for TrainSection {
    fn default() -> Self {
        Self {
            steps: 200_000,
            accumulate: 1,
            subjects: TrainingSubjects::Split,
            lr_encoder: 1e-4,
            lr_reconstructor: 5e-5,
            seed: 42,
            loss_rgb: 1.0,
            loss_mask: 5.0,
            loss_ssim: 1.0,
            loss_lpips: 0.0,
            lpips_fallback: LpipsFallback::Refuse,
            loss_laplacian: 100.0,
            checkpoint_every: 10_000,
            snapshot_every: 1_000,
            log_every: 10,
            validate_every: 0,
            validate_subjects: 8,
        }
    }
}

impl TrainSection {
    /// The loss weights the trainer uses: the configured ones, with the LPIPS weight moved to
    /// the SSIM term under [`LpipsFallback::Ssim`] when the LPIPS weights are absent.
    pub fn loss_weights(&self, lpips: LpipsWeights) -> LossWeights {
        let (ssim, lpips) = match (self.lpips_fallback, lpips) {
            (LpipsFallback::Ssim, LpipsWeights::Absent) if self.loss_lpips > 0.0 => {
                (self.loss_ssim + self.loss_lpips, 0.0)
            }
            _ => (self.loss_ssim, self.loss_lpips),
        };
        LossWeights::new()
            .with_rgb(self.loss_rgb)
            .with_mask(self.loss_mask)
            .with_ssim(ssim)
            .with_lpips(lpips)
            .with_laplacian(self.loss_laplacian)
    }

    /// The line the training log starts with about the LPIPS term (`None` when it is off).
    pub fn lpips_note(&self, lpips: LpipsWeights) -> Option<String> {
        if self.loss_lpips <= 0.0 {
            return None;
        }
        Some(match (lpips, self.lpips_fallback) {
            (LpipsWeights::Present, _) => format!(
                "LPIPS training loss: LPIPS-VGG v0.1 at half resolution (nearest), weight {}",
                self.loss_lpips
            ),
            (LpipsWeights::Absent, LpipsFallback::Ssim) => format!(
                "LPIPS training loss: no LPIPS weights (run `lifegom-weights fetch`), so [train] lpips_fallback = \"ssim\" trains with 1 - SSIM in its place (loss_lpips = {} added to loss_ssim = {}: the logged `ssim` term carries both)",
                self.loss_lpips, self.loss_ssim
            ),
            (LpipsWeights::Absent, LpipsFallback::Refuse) => {
                "LPIPS training loss: no LPIPS weights and no fallback".into()
            }
        })
    }
}

#[derive(Deserialize)]
struct Sections {
    #[serde(default)]
    model: ModelSection,
    #[serde(default)]
    train: TrainSection,
}

/// A whole experiment: data, model and training settings.
#[derive(Debug, Clone)]
pub struct ExperimentConfig {
    /// `[data]` and `[synthetic]`.
    pub file: ConfigFile,
    /// `[model]`.
    pub model: ModelSection,
    /// `[train]`.
    pub train: TrainSection,
}

impl ExperimentConfig {
    /// Reads and validates a config file.
    pub fn load(path: &Path) -> Result<Self, ConfigError> {
        let file = ConfigFile::load(path)?;
        let text = std::fs::read_to_string(path).map_err(|e| ConfigError::Invalid {
            path: path.to_path_buf(),
            reason: e.to_string(),
        })?;
        Self::parse_sections(file, &text, path)
    }

    fn parse_sections(file: ConfigFile, text: &str, path: &Path) -> Result<Self, ConfigError> {
        let invalid = |reason: String| ConfigError::Invalid {
            path: path.to_path_buf(),
            reason,
        };
        let sections: Sections = toml::from_str(text).map_err(|e| invalid(e.to_string()))?;
        let (model, train) = (sections.model, sections.train);
        if model.iterations == 0 {
            return Err(invalid("[model] iterations must be ≥ 1".into()));
        }
        if model.subdivide_train > 3 || model.subdivide_test > 3 {
            return Err(invalid(
                "[model] subdivisions above 3 (≥ 7M Gaussians on SMPL-X) are not supported".into(),
            ));
        }
        for (name, lr) in [
            ("lr_encoder", train.lr_encoder),
            ("lr_reconstructor", train.lr_reconstructor),
        ] {
            if !(lr.is_finite() && lr >= 0.0) {
                return Err(invalid(format!("[train] {name} = {lr} must be ≥ 0")));
            }
        }
        for (name, w) in [
            ("loss_rgb", train.loss_rgb),
            ("loss_mask", train.loss_mask),
            ("loss_ssim", train.loss_ssim),
            ("loss_lpips", train.loss_lpips),
            ("loss_laplacian", train.loss_laplacian),
        ] {
            if !(w.is_finite() && w >= 0.0) {
                return Err(invalid(format!("[train] {name} = {w} must be ≥ 0")));
            }
        }
        for (name, n) in [
            ("checkpoint_every", train.checkpoint_every),
            ("snapshot_every", train.snapshot_every),
            ("log_every", train.log_every),
            ("accumulate", train.accumulate as u64),
        ] {
            if n == 0 {
                return Err(invalid(format!("[train] {name} must be ≥ 1")));
            }
        }
        if train.subjects == TrainingSubjects::Procedural && file.synthetic.is_none() {
            return Err(invalid(
                "[train] subjects = \"procedural\" needs a [synthetic] section describing the subjects".into(),
            ));
        }
        Ok(Self { file, model, train })
    }

    /// The reconstructor config for this experiment.
    pub fn reconstructor(&self) -> ReconstructorConfig {
        self.model.reconstructor(self.file.data.n_input_frames)
    }

    /// The same experiment with another data root.
    pub fn with_root(mut self, root: impl Into<PathBuf>) -> Self {
        self.file = self.file.with_root(root);
        self
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn configs_dir() -> PathBuf {
        PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../configs")
    }

    #[test]
    fn every_shipped_config_parses_as_an_experiment() {
        let mut n = 0;
        for entry in std::fs::read_dir(configs_dir()).unwrap() {
            let path = entry.unwrap().path();
            if path.extension().is_some_and(|e| e == "toml") {
                ExperimentConfig::load(&path).unwrap_or_else(|e| panic!("{e}"));
                n += 1;
            }
        }
        assert!(n >= 6);
    }

    #[test]
    fn defaults_are_the_thuman_view3_reference() {
        let cfg = ExperimentConfig::load(&configs_dir().join("thuman2.0-view3.toml")).unwrap();
        assert_eq!(cfg.model, ModelSection::default());
        let r = cfg.reconstructor();
        assert_eq!(
            (r.iterations, r.subdivide_train, r.subdivide_test),
            (3, 1, 2)
        );
        assert_eq!(r.feature_dim(), 1152);
        let w = cfg.train.loss_weights(LpipsWeights::Absent);
        assert_eq!(
            (w.rgb, w.mask, w.ssim, w.lpips, w.laplacian),
            (1.0, 5.0, 1.0, 0.0, 100.0)
        );
        assert_eq!(
            (cfg.train.lr_encoder, cfg.train.lr_reconstructor),
            (1e-4, 5e-5)
        );
    }

    #[test]
    fn the_lpips_fallback_moves_its_weight_to_ssim_and_says_so() {
        use LpipsWeights::{Absent, Present};
        let aist = TrainSection {
            loss_mask: 0.0,
            loss_ssim: 0.0,
            loss_lpips: 1.0,
            ..TrainSection::default()
        };
        let w = aist.loss_weights(Absent);
        assert_eq!((w.ssim, w.lpips), (0.0, 1.0), "refused later, not hidden");
        assert!(aist.lpips_note(Absent).unwrap().contains("no fallback"));
        let fallback = TrainSection {
            lpips_fallback: LpipsFallback::Ssim,
            ..aist
        };
        let w = fallback.loss_weights(Absent);
        assert_eq!((w.rgb, w.mask, w.ssim, w.lpips), (1.0, 0.0, 1.0, 0.0));
        assert!(fallback.lpips_note(Absent).unwrap().contains("SSIM"));
        // With the weights the real term stays, whatever the fallback.
        let w = fallback.loss_weights(Present);
        assert_eq!((w.ssim, w.lpips), (0.0, 1.0));
        assert!(fallback.lpips_note(Present).unwrap().contains("LPIPS-VGG"));
        // Without an LPIPS weight the fallback changes nothing.
        let thuman = TrainSection {
            lpips_fallback: LpipsFallback::Ssim,
            ..TrainSection::default()
        };
        assert_eq!(thuman.loss_weights(Absent).ssim, 1.0);
        assert!(thuman.lpips_note(Absent).is_none());
        let cfg = ExperimentConfig::load(&configs_dir().join("synthetic-multiframe.toml")).unwrap();
        assert_eq!(cfg.train.lpips_fallback, LpipsFallback::Ssim);
        assert!(cfg.train.lpips_note(Absent).is_some());
    }

    #[test]
    fn typos_and_bad_values_are_errors_naming_the_file() {
        let base = ConfigFile::load(&configs_dir().join("synthetic-tiny.toml")).unwrap();
        let path = Path::new("configs/x.toml");
        for (text, needle) in [
            ("[model]\niteration = 3\n", "iteration"),
            ("[train]\nlr_encoder = -1.0\n", "lr_encoder"),
            ("[model]\niterations = 0\n", "iterations"),
            ("[train]\nlog_every = 0\n", "log_every"),
            ("[train]\naccumulate = 0\n", "accumulate"),
            ("[model]\npreset = \"huge\"\n", "huge"),
            ("[train]\nsubjects = \"forever\"\n", "forever"),
            ("[train]\nlpips_fallback = \"vgg\"\n", "vgg"),
        ] {
            let err = ExperimentConfig::parse_sections(base.clone(), text, path)
                .unwrap_err()
                .to_string();
            assert!(
                err.contains("configs/x.toml") && err.contains(needle),
                "{err}"
            );
        }
    }
}
