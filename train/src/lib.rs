//! # lifegom-train
//!
//! Training of the LIFe-GoM reconstructor (design.md §9): the losses, one training step over all T
//! feedback iterations and N + 1 views, a deterministic data schedule, and checkpoints that
//! resume exactly. The commands built on it (`lifegom-train`, `quickstart`) are in `lifegom-cli`.
//!
//! ```no_run
//! use lifegom_train::{config::ExperimentConfig, trainer::{Trainer, sample_for_step}};
//! use lifegom_data::dataset::{Dataset, Split};
//! use lifegom_model::{reconstructor::MeshPurpose, inputs::{SubjectRig, model_inputs}};
//! use lifegom_train::losses::UniformLaplacian;
//! # fn main() -> Result<(), Box<dyn std::error::Error>> {
//! let cfg = ExperimentConfig::load("configs/synthetic-tiny.toml".as_ref())?.with_root("/tmp/synth-tiny");
//! let data = Dataset::open(&cfg.file.data, Split::Train)?;
//! let body = SubjectRig::new(&data.subjects[0].name, &data.subjects[0].canonical)?;
//! let device = burn::tensor::Device::flex();
//! let mut trainer = Trainer::new(cfg.reconstructor(), body.num_vertices(), &cfg.train, &device)?;
//! let mesh = trainer.config.mesh(&body.topology, MeshPurpose::Training, trainer.device())?;
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
//! - [`losses`]: the losses of design.md §9.2 (L1, mask L1, Gaussian-window SSIM, uniform mesh
//!   Laplacian) and the [`losses::LossWeights`] that combine them.
//! - [`config`]: `[model]` and `[train]` sections of an experiment TOML.
//! - [`trainer`]: the step, the data schedule and exact-resume checkpoints.
//! - [`source`]: where a step's sample comes from: the split on disk, or a fresh synthetic
//!   subject per step.
//! - [`fit`]: per-scene optimisation of one avatar on its source views (the baseline learned
//!   feedback competes with, and test-time refinement).
//! - [`data_parallel`]: batches of several samples: gradient accumulation, and replicas in
//!   several processes (MPI) that average their gradients.
//! - [`prefetch`]: the next step's sample read on another thread while this one computes.
//! - [`adam`]: Adam in a few batched kernels per step on CubeCL devices (Burn's `Adam` on the
//!   CPU backends), the trainer's optimizer.

pub mod adam;
pub mod config;
pub mod data_parallel;
pub mod fit;
pub mod losses;
pub mod prefetch;
pub mod source;
pub mod ssim_op;
pub mod trainer;
