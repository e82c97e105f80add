//! # lifegom-train
//!
//! Training of the LIFe-GoM reconstructor (spec §6): the losses, one training step over all T
//! feedback iterations and N + 1 views, a deterministic data schedule, and checkpoints that
//! resume exactly. Binaries: `lifegom-train` (the train command) and `quickstart` (generate the
//! synthetic split, train for a bounded time, evaluate, write a report).
//!
//! ```no_run
//! use lifegom_train::{config::ExperimentConfig, trainer::{Trainer, sample_for_step}};
//! use lifegom_data::dataset::{Dataset, Phase};
//! use lifegom_model::{feedback::Phase as MeshPhase, inputs::{SubjectBody, model_inputs}};
//! use lifegom_train::losses::UniformLaplacian;
//! # fn main() -> anyhow::Result<()> {
//! let cfg = ExperimentConfig::load("configs/synthetic-tiny.toml".as_ref())?.with_root("/tmp/synth-tiny");
//! let data = Dataset::open(&cfg.file.data, Phase::Train)?;
//! let body = SubjectBody::new(&data.subjects[0].name, &data.subjects[0].canonical)?;
//! let device = burn::tensor::Device::flex();
//! let mut trainer = Trainer::new(cfg.reconstructor(), body.num_vertices(), &cfg.train, &device)?;
//! let mesh = trainer.config.mesh(&body.topology, MeshPhase::Train, trainer.device())?;
//! let laplacian = UniformLaplacian::new(&body.topology.faces, body.num_vertices())?;
//! let sample = sample_for_step(&data, trainer.seed(), trainer.step)?;
//! let (w, h) = (cfg.file.data.img_size[0], cfg.file.data.img_size[1]);
//! let inputs = model_inputs(&body, &sample, w, h, trainer.device())?;
//! let stats = trainer.train_step(&inputs, &mesh, &laplacian)?;
//! println!("step {} loss {:?}", stats.step, stats.losses);
//! # Ok(()) }
//! ```
//!
//! ## Module map
//!
//! - [`losses`]: the losses of spec §6.2 (L1, mask L1, Gaussian-window SSIM, uniform mesh
//!   Laplacian) and the [`losses::LossWeights`] that combine them.
//! - [`config`]: `[model]` and `[train]` sections of an experiment TOML.
//! - [`trainer`]: the step, the data schedule and exact-resume checkpoints.
//! - [`run`]: the training loop behind the command (progress, logs, snapshots, Ctrl-C).

pub mod config;
pub mod losses;
pub mod run;
pub mod trainer;
