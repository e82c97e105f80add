//! The training loop's step, its data schedule, and checkpoints that resume exactly.
//!
//! One sample's loss (design.md §9.1–§9.4): run the reconstructor's T feedback steps on the N
//! sources; render every step's state in the target view too; supervise the T·(N+1) composited
//! renders and alphas against the (broadcast) ground truth with L1 + λ(1−SSIM) + λ·mask L1, plus
//! λ·uniform Laplacian of the T low-res canonical meshes. One step: the mean gradient of a batch
//! of such samples (one, the reference's batch size, unless `[train] accumulate` or MPI ranks
//! make it larger: [`crate::data_parallel`]), then one Adam step with the encoder's learning
//! rate on the encoder's parameters and the reconstructor's on the rest.
//!
//! **Exact resume.** Nothing random depends on history: sample `s` of the run's stream is drawn
//! from the permutation of epoch `s / len` (seeded by `(seed, epoch)`), its backgrounds and source
//! views from `Rng(seed).fork(s)`, and Burn's RNG (dropout) is re-seeded from `(seed, s)` before
//! its forward. A checkpoint stores the weights (with their parameter ids), Adam's moments, the
//! step and the samples consumed, so a resumed run computes the same losses as an uninterrupted
//! one on the same backend, whatever batch it resumes with. Checkpoints are written between
//! steps only: a run stopped inside a batch redoes that batch when it resumes.

use lifegom_render::readback::ReadbackError;
use std::time::Instant;

use burn::module::{Module, ModuleVisitor, Param, ParamGroup};
use burn::optim::lr_scheduler::LrSchedulerConfig;
use burn::optim::lr_scheduler::module_lr_scheduler::{ModuleLearningRate, ModuleLrSchedulerConfig};
use burn::optim::{GradientsAccumulator, GradientsParams};

use crate::adam::{AdamOptimizer, FusedAdamConfig, GradientWatch};
use burn::tensor::{Bytes, Device, Tensor};
use lifegom_data::dataset::Dataset;
use lifegom_model::inputs::ModelInputs;
use lifegom_model::reconstructor::{Reconstructor, ReconstructorConfig, TargetViews};
use lifegom_model::trained::{self, TrainedError};
use lifegom_render::device::on_pool_thread;
use lifegom_render::device::runs_on_host;
use lifegom_render::gom::GomMesh;
use lifegom_render::rng::Rng;
use serde::{Deserialize, Serialize};

use crate::config::{LpipsWeights, TrainSection};
use crate::data_parallel::{self, ReplicaError, Replicas, SingleProcess};
use crate::losses::{
    LossTerms, LossWeights, UniformLaplacian, WeightedLoss, l1, mask_l1, ssim_loss,
};
use lifegom_perceptual::{LPIPS_VGG_FILE, Lpips, LpipsNet, PerceptualModels};

/// Errors of a training step or checkpoint.
#[derive(Debug, thiserror::Error)]
pub enum TrainError {
    /// The model failed (bad inputs, rendering).
    #[error(transparent)]
    Model(#[from] lifegom_model::error::ModelError),
    /// Loss assembly failed.
    #[error(transparent)]
    Loss(#[from] crate::losses::LossError),
    /// Reading or writing a checkpoint failed.
    #[error(transparent)]
    Checkpoint(#[from] TrainedError),
    /// Loss values could not be read back to the host.
    #[error(transparent)]
    Readback(#[from] ReadbackError),
    /// The learning-rate groups could not be built (a parameter in two groups).
    #[error("learning-rate groups: {0}")]
    LearningRates(String),
    /// The optimiser state could not be serialised for a checkpoint.
    #[error("serialising the optimizer state: {0}")]
    OptimizerState(String),
    /// The trainer's own metadata could not be serialised for a checkpoint.
    #[error("serialising the trainer state: {0}")]
    TrainerState(#[from] serde_json::Error),
    /// The ranks of a data-parallel job disagree or could not exchange their gradients.
    #[error(transparent)]
    Replicas(#[from] ReplicaError),
    /// A step was asked to train on no sample.
    #[error("a training step needs at least one sample")]
    EmptyBatch,
    /// Reading or generating a training sample failed.
    #[error(transparent)]
    Data(#[from] lifegom_data::DataError),
    /// The LPIPS network of the LPIPS term failed to load or to run.
    #[error(transparent)]
    Perceptual(#[from] lifegom_perceptual::PerceptualError),
    /// The training source cannot be used as configured.
    #[error("training data: {0}")]
    Source(String),
    /// A model configured with no feedback step has nothing to render or supervise.
    #[error("the reconstructor ran no feedback step (iterations = 0)")]
    NoFeedbackStep,
}

/// What one step measured (host values, read after the step).
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct StepStats {
    /// The step that was taken (1-based count of optimiser steps after it).
    pub step: u64,
    /// Weighted loss terms and `total`.
    pub losses: Vec<(String, f64)>,
    /// PSNR of the last feedback step's target-view render against the target (dB).
    pub psnr_target: f64,
    /// PSNR of the target-view render after each feedback step `t = 1…T` (dB): the novel view,
    /// which says whether a step helps on what the inputs do not show.
    #[serde(default)]
    pub psnr_target_steps: Vec<f64>,
    /// PSNR of the N source-view renders (their pooled MSE) after each feedback step (dB): what
    /// the feedback loop sees and corrects.
    #[serde(default)]
    pub psnr_source_steps: Vec<f64>,
    /// Wall time of the step (s).
    pub seconds: f64,
    /// Samples in the step's batch, over all ranks (the losses and PSNRs are their means).
    #[serde(default = "one")]
    pub batch: u64,
    /// Wall time of the gradient exchange between ranks (s; 0 in one process): the
    /// all-reduce, with the read-back and upload of the gradients around it.
    #[serde(default)]
    pub exchange_seconds: f64,
    /// Whether the optimizer step was taken: `false` when the batch's loss or a gradient was not
    /// finite (gradients are checked on the host on the CPU backends and under MPI, by the
    /// optimizer's kernels on a GPU, `crate::adam`). A skipped step leaves the weights, the
    /// optimizer state and `step` as they were and uses up its samples.
    #[serde(default = "yes")]
    pub applied: bool,
}

fn yes() -> bool {
    true
}

fn one() -> u64 {
    1
}

/// A step's statistics and its last-iteration target render (detached, `[3, H, W]`).
#[derive(Debug, Clone)]
pub struct StepOutput {
    /// The statistics.
    pub stats: StepStats,
    /// What the model rendered in the target view after the last feedback step.
    pub target_render: Tensor<3>,
}

/// A step's forward ([`Trainer::step_loss`]): the loss, still on the autodiff graph, and what
/// the step's statistics read once the optimiser has run.
pub struct StepLoss {
    /// The weighted terms; the step differentiates `total`.
    pub loss: WeightedLoss,
    /// One MSE per rendered image, `[T·(N+1)]`, detached.
    image_mse: Tensor<1>,
    /// The last feedback step's target render, `[1, 3, H, W]`.
    last_target: Tensor<4>,
    /// Feedback steps T.
    iterations: usize,
}

/// Trainer state that is not in the weights or the optimiser.
#[derive(Debug, Clone, Serialize, Deserialize)]
struct TrainerMeta {
    step: u64,
    /// Samples of the stream consumed (equal to `step` in runs with one sample a step, which is
    /// what files without the field are).
    #[serde(default)]
    samples: Option<u64>,
    seed: u64,
    /// Version of the data schedule ([`schedule`]) and the per-step seeding: a run resumes
    /// exactly only under the schedule it started with. Files without the field are version 1
    /// (an ad-hoc mixing function, replaced by [`Rng::fork`] in version 2).
    #[serde(default = "schedule_v1")]
    schedule_version: u32,
}

/// The data schedule and per-step seeding this trainer uses.
const SCHEDULE_VERSION: u32 = 2;

fn schedule_v1() -> u32 {
    1
}

/// A fresh Adam (`crate::adam`) and the watch its GPU kernels report non-finite gradients to.
fn fresh_optimizer() -> (AdamOptimizer, GradientWatch) {
    let watch = GradientWatch::default();
    let optim = AdamOptimizer::new(FusedAdamConfig::default(), watch.clone());
    (optim, watch)
}

/// The model, its optimiser and the step counter.
pub struct Trainer {
    /// The network, on an autodiff device.
    pub model: Reconstructor,
    /// The config it was built from.
    pub config: ReconstructorConfig,
    optim: AdamOptimizer,
    /// Reports a non-finite gradient from the optimizer's GPU kernels (`crate::adam`).
    watch: GradientWatch,
    lr: ModuleLearningRate,
    weights: LossWeights,
    /// LPIPS-VGG for the LPIPS term (frozen, on the autodiff device), when `[train]
    /// loss_lpips > 0` and its weights are in the weights folder.
    lpips: Option<Lpips>,
    /// Optimiser steps taken so far.
    pub step: u64,
    /// Samples of the run's stream consumed so far (the next batch starts here).
    pub samples: u64,
    seed: u64,
    device: Device,
}

/// One sample of a step's batch: its index in the run's sample stream (which seeds its dropout)
/// and its inputs.
#[derive(Clone, Copy)]
pub struct BatchSample<'a> {
    /// Index in the stream ([`crate::data_parallel::BatchLayout::sample_index`]).
    pub index: u64,
    /// The sample's inputs, built on [`Trainer::device`].
    pub inputs: &'a ModelInputs,
}

/// What one sample of a batch measured, as one flat row so that a batch's rows can be summed
/// over ranks: the loss terms, the target PSNR, then the per-step target and source PSNRs.
struct SampleRow {
    names: Vec<&'static str>,
    values: Vec<f64>,
}

/// Reads every parameter once (see [`Trainer::new`]).
struct DrawParameters;

impl ModuleVisitor for DrawParameters {
    fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
        let _ = param.val();
    }
}

/// A seed for `stream` of step-or-epoch `index`: unrelated for nearby seeds and indices.
fn derived_seed(seed: u64, stream: u64, index: u64) -> u64 {
    Rng::new(seed).fork(stream).fork(index).next_u64()
}

/// Stream keys of [`derived_seed`].
const EPOCH_ORDER: u64 = 1;
const DROPOUT: u64 = 2;

/// The sample index and sampling RNG of step `step` (module docs: a pure function of the seed).
pub fn schedule(seed: u64, step: u64, len: usize) -> (usize, Rng) {
    let len = len.max(1);
    let epoch = step / len as u64;
    let mut order: Vec<usize> = (0..len).collect();
    let mut rng = Rng::new(derived_seed(seed, EPOCH_ORDER, epoch));
    for i in (1..len).rev() {
        order.swap(i, rng.below(i + 1));
    }
    (
        order[(step % len as u64) as usize],
        Rng::new(seed).fork(step),
    )
}

/// Loads step `step`'s sample from `dataset`.
pub fn sample_for_step(
    dataset: &Dataset,
    seed: u64,
    step: u64,
) -> Result<lifegom_data::dataset::Sample, lifegom_data::DataError> {
    let (index, mut rng) = schedule(seed, step, dataset.len());
    dataset.sample(index, &mut rng)
}

fn learning_rates(
    model: &Reconstructor,
    train: &TrainSection,
) -> Result<ModuleLearningRate, TrainError> {
    // Groups by parameter id, not path: robust to renames, and ids survive checkpoints.
    let encoder = ParamGroup::ids_from_module(model.encoder.clone());
    let mut scheduler =
        ModuleLrSchedulerConfig::new(LrSchedulerConfig::Constant(train.lr_reconstructor))
            .with_group(encoder, LrSchedulerConfig::Constant(train.lr_encoder))
            .init()
            .map_err(TrainError::LearningRates)?;
    Ok(scheduler.step())
}

impl Trainer {
    /// A fresh model (Burn's RNG seeded from `train.seed`) on `device` (made autodiff here).
    pub fn new(
        config: ReconstructorConfig,
        num_vertices: usize,
        train: &TrainSection,
        device: &Device,
    ) -> Result<Self, TrainError> {
        let device = device.clone().autodiff();
        device.seed(train.seed);
        let model = config.init(num_vertices, &device)?;
        // Burn draws a parameter's values when it is first read. Read them all now, so the
        // initial weights are a function of the seed alone, not of whatever first touches them
        // (a first forward re-seeds the RNG for its dropout; the ranks of a data-parallel job
        // each start with a different sample).
        model.visit(&mut DrawParameters);
        let (optim, watch) = fresh_optimizer();
        Self::assemble(model, config, optim, watch, (0, 0), train, device)
    }

    /// Fine-tuning: the weights of `path` (a `.lgck`, or an official checkpoint loaded into
    /// `config`'s network) with a fresh optimiser at step 0, on `device` (made autodiff here).
    /// The network is `config`'s: a `.lgck` of another architecture is refused (feedback
    /// steps, subdivisions and dropout are `config`'s whatever the file says), as is a model
    /// for a template of other than `num_vertices` low-res vertices. Burn's RNG is seeded from
    /// `train.seed`, as [`Trainer::new`] seeds it. Returns the trainer and a line saying what
    /// was loaded.
    pub fn from_weights(
        path: &std::path::Path,
        config: ReconstructorConfig,
        num_vertices: usize,
        train: &TrainSection,
        device: &Device,
    ) -> Result<(Self, String), TrainError> {
        let device = device.clone().autodiff();
        device.seed(train.seed);
        let loaded = trained::load_any(path, &config, &device)?;
        loaded.check_template(path, num_vertices)?;
        if !loaded.same_architecture(&config) {
            return Err(TrainError::Checkpoint(TrainedError::Format {
                path: path.to_path_buf(),
                reason: format!(
                    "its network ({} views) is not the config's `[model]` network ({} views{}); \
                     fine-tuning keeps the architecture: use a `[model]` that matches the file",
                    loaded.config.num_views,
                    config.num_views,
                    if loaded.config.num_views == config.num_views {
                        ", another preset"
                    } else {
                        ""
                    }
                ),
            }));
        }
        let line = format!(
            "fine-tuning from {} ({}); fresh optimiser, step 0",
            path.display(),
            loaded.provenance()
        );
        let (optim, watch) = fresh_optimizer();
        let trainer = Self::assemble(loaded.model, config, optim, watch, (0, 0), train, device)?;
        Ok((trainer, line))
    }

    fn assemble(
        model: Reconstructor,
        config: ReconstructorConfig,
        optim: AdamOptimizer,
        watch: GradientWatch,
        (step, samples): (u64, u64),
        train: &TrainSection,
        device: Device,
    ) -> Result<Self, TrainError> {
        let lpips = lpips_network(train, &device)?;
        let present = if lpips.is_some() {
            LpipsWeights::Present
        } else {
            LpipsWeights::Absent
        };
        Ok(Self {
            lr: learning_rates(&model, train)?,
            model,
            config,
            optim,
            watch,
            weights: train.loss_weights(present),
            lpips,
            step,
            samples,
            seed: train.seed,
            device,
        })
    }

    /// Resumes from a checkpoint written by [`Trainer::save`]. The `[train]` section supplies
    /// learning rates and loss weights (so they may be changed on resume); the seed is the
    /// checkpoint's.
    pub fn resume(
        path: &std::path::Path,
        train: &TrainSection,
        device: &Device,
    ) -> Result<Self, TrainError> {
        let device = device.clone().autodiff();
        let loaded = trained::load(path, &device)?;
        let bad = |reason: String| {
            TrainError::Checkpoint(TrainedError::Format {
                path: path.to_path_buf(),
                reason,
            })
        };
        let payload = &loaded.payload;
        if payload.len() < 8 {
            return Err(bad(
                "no trainer state (an inference-only model file?)".into()
            ));
        }
        let n = u64::from_le_bytes(payload[..8].try_into().unwrap_or_default()) as usize;
        if payload.len() < 8 + n {
            return Err(bad("truncated trainer state".into()));
        }
        let meta: TrainerMeta = serde_json::from_slice(&payload[8..8 + n])
            .map_err(|e| bad(format!("trainer state: {e}")))?;
        if meta.schedule_version != SCHEDULE_VERSION {
            return Err(bad(format!(
                "written with data schedule version {}, this trainer uses version {SCHEDULE_VERSION}: \
                 resuming would not continue the same run (start a new run; the weights still load for evaluation)",
                meta.schedule_version
            )));
        }
        let (optim, watch) = fresh_optimizer();
        let optim = optim
            .from_bytes(Bytes::from_bytes_vec(payload[8 + n..].to_vec()))
            .map_err(|e| bad(format!("optimizer state: {e}")))?;
        let train = TrainSection {
            seed: meta.seed,
            ..train.clone()
        };
        Self::assemble(
            loaded.model,
            loaded.config,
            optim,
            watch,
            (meta.step, meta.samples.unwrap_or(meta.step)),
            &train,
            device,
        )
    }

    /// Writes weights, config, optimiser state and step to `path` atomically.
    pub fn save(&self, path: &std::path::Path, meta: serde_json::Value) -> Result<(), TrainError> {
        let state = serde_json::to_vec(&TrainerMeta {
            step: self.step,
            samples: Some(self.samples),
            seed: self.seed,
            schedule_version: SCHEDULE_VERSION,
        })?;
        let optim = self
            .optim
            .into_bytes()
            .map_err(|e| TrainError::OptimizerState(e.to_string()))?;
        let mut payload = Vec::with_capacity(8 + state.len() + optim.len());
        payload.extend_from_slice(&(state.len() as u64).to_le_bytes());
        payload.extend_from_slice(&state);
        payload.extend_from_slice(&optim);
        let mut meta = meta;
        if let serde_json::Value::Object(m) = &mut meta {
            m.insert("step".into(), self.step.into());
        }
        trained::save(path, &self.model, &self.config, meta, &payload)?;
        Ok(())
    }

    /// The autodiff device the model lives on.
    pub fn device(&self) -> &Device {
        &self.device
    }

    /// The seed the data schedule uses.
    pub fn seed(&self) -> u64 {
        self.seed
    }

    /// Loads torchvision ResNet-18 weights into the encoder; returns the loader's report.
    pub fn load_encoder_weights(&mut self, path: &std::path::Path) -> Result<String, TrainError> {
        let (encoder, report) = self
            .model
            .encoder
            .clone()
            .load_torchvision(path)
            .map_err(lifegom_model::error::ModelError::from)?;
        self.model.encoder = encoder;
        Ok(report.to_string())
    }

    /// One optimiser step on `inputs` (built on [`Trainer::device`]) alone: the next sample of
    /// the stream, in a batch of one, in this process alone.
    pub fn train_step(
        &mut self,
        inputs: &ModelInputs,
        mesh: &GomMesh,
        laplacian: &UniformLaplacian,
    ) -> Result<StepStats, TrainError> {
        Ok(self.train_step_with_render(inputs, mesh, laplacian)?.stats)
    }

    /// [`Trainer::train_step`], also returning the last iteration's target render.
    pub fn train_step_with_render(
        &mut self,
        inputs: &ModelInputs,
        mesh: &GomMesh,
        laplacian: &UniformLaplacian,
    ) -> Result<StepOutput, TrainError> {
        let sample = BatchSample {
            index: self.samples,
            inputs,
        };
        self.train_batch(&[sample], mesh, laplacian, &SingleProcess)
    }

    /// One optimiser step on the mean gradient of a batch: `batch` is this rank's share, and
    /// every rank of `replicas` calls this with a share of the same size (module docs,
    /// [`crate::data_parallel`]). A batch whose loss or gradient is not finite is not applied
    /// ([`StepStats::applied`]). The statistics are the batch's means over all ranks; the
    /// render is this rank's last sample's. On a CPU device the samples' forward and backward
    /// and the optimizer run on one of rayon's threads
    /// (`lifegom_render::device::on_pool_thread`); the collectives run on the calling thread.
    pub fn train_batch(
        &mut self,
        batch: &[BatchSample<'_>],
        mesh: &GomMesh,
        laplacian: &UniformLaplacian,
        replicas: &dyn Replicas,
    ) -> Result<StepOutput, TrainError> {
        if batch.is_empty() {
            return Err(TrainError::EmptyBatch);
        }
        let _span =
            tracing::info_span!("train_step", step = self.step, batch = batch.len()).entered();
        let start = Instant::now();
        let device = self.device.clone();
        let (grads, rows, target_render) = on_pool_thread(&device, |parent| {
            self.batch_gradients(batch, mesh, laplacian, parent)
        })?;
        let samples = (batch.len() * replicas.size()) as u64;

        // The batch's mean statistics, over all ranks: also what decides whether the step is
        // taken, so every rank decides the same.
        let mut sum = vec![0.0; rows[0].values.len()];
        for row in &rows {
            for (s, v) in sum.iter_mut().zip(&row.values) {
                *s += v;
            }
        }
        replicas.sum_f64(&mut sum);
        let mean: Vec<f64> = sum.iter().map(|s| s / samples as f64).collect();
        let names = &rows[0].names;
        let (losses, rest) = mean.split_at(names.len());

        // A step on a non-finite loss or gradient would put NaN into every weight it touches:
        // it is skipped (the samples count as used, the step counter does not move).
        let exchange = Instant::now();
        let averaged = if losses.iter().all(|l| l.is_finite()) {
            data_parallel::average_gradients(&self.model, grads, batch.len(), replicas)?
        } else {
            None
        };
        let exchange_seconds = if replicas.size() > 1 {
            exchange.elapsed().as_secs_f64()
        } else {
            0.0
        };
        let mut applied = false;
        if let Some(grads) = averaged {
            // On a GPU the gradients are only seen by the step's kernels (`crate::adam`): keep
            // what a step with a non-finite one is undone to (handles, not copies). Not on the
            // host backends, whose gradients were checked above and whose optimizer updates
            // in place only while nothing else holds the weights.
            let before = (!runs_on_host(&device)).then(|| (self.model.clone(), self.optim.clone()));
            self.watch.arm(&device);
            on_pool_thread(&device, |parent| {
                let _span = tracing::debug_span!(parent: parent, "optimizer").entered();
                self.model = self.optim.step(self.lr.clone(), self.model.clone(), grads);
            });
            if let (true, Some(before)) = (self.watch.tripped()?, before) {
                (self.model, self.optim) = before;
            } else {
                self.step += 1;
                applied = true;
            }
        }
        self.samples += samples;

        let t = (rest.len() - 1) / 2;
        let stats = StepStats {
            step: self.step,
            losses: names
                .iter()
                .zip(losses)
                .map(|(n, v)| (n.to_string(), *v))
                .collect(),
            psnr_target: rest[0],
            psnr_target_steps: rest[1..1 + t].to_vec(),
            psnr_source_steps: rest[1 + t..].to_vec(),
            seconds: start.elapsed().as_secs_f64(),
            batch: samples,
            exchange_seconds,
            applied,
        };
        Ok(StepOutput {
            stats,
            target_render,
        })
    }

    /// The summed gradients of this rank's share of a batch, each sample's statistics, and the
    /// last sample's target render; on the calling thread, its span a child of `parent`.
    fn batch_gradients(
        &self,
        batch: &[BatchSample<'_>],
        mesh: &GomMesh,
        laplacian: &UniformLaplacian,
        parent: &tracing::Span,
    ) -> Result<(GradientsParams, Vec<SampleRow>, Tensor<3>), TrainError> {
        let _span = tracing::debug_span!(parent: parent, "batch_gradients").entered();
        // One sample needs no adding up: its gradients skip the accumulator's pass.
        let mut alone = None;
        let mut accumulated = GradientsAccumulator::<Reconstructor>::new();
        let mut rows = Vec::with_capacity(batch.len());
        let mut target_render = None;
        for sample in batch {
            let StepLoss {
                loss,
                image_mse,
                last_target,
                iterations: t,
            } = self.sample_loss(sample, mesh, laplacian)?;
            let grads = {
                let _span = tracing::debug_span!("backward").entered();
                GradientsParams::from_grads(loss.total.backward(), &self.model)
            };
            if batch.len() == 1 {
                alone = Some(grads);
            } else {
                accumulated.accumulate(&self.model, grads);
            }
            let render = last_target.detach().squeeze_dim::<3>(0);
            rows.push(Self::sample_row(
                sample.inputs,
                &loss,
                image_mse,
                &render,
                t,
            )?);
            target_render = Some(render);
        }
        let render = target_render.ok_or(TrainError::EmptyBatch)?;
        let grads = alone.unwrap_or_else(|| accumulated.grads());
        Ok((grads, rows, render))
    }

    /// A sample's statistics ([`SampleRow`]).
    fn sample_row(
        inputs: &ModelInputs,
        loss: &WeightedLoss,
        image_mse: Tensor<1>,
        target_render: &Tensor<3>,
        t: usize,
    ) -> Result<SampleRow, TrainError> {
        let mse = (target_render.clone() - inputs.target_rgb.clone())
            .powf_scalar(2.0)
            .mean();
        // One read-back for the losses, the target's MSE and the per-image MSEs.
        let (names, mut values) = loss.scalars_with(&[mse, image_mse])?;
        let extra = values.split_off(names.len());
        let (&mse, image_mse) = extra.split_first().unwrap_or((&f64::NAN, &[]));
        let views = image_mse.len() / t.max(1);
        let psnr = |mse: f64| 10.0 * (1.0 / mse.max(1e-12)).log10();
        let per_step = image_mse.chunks(views.max(1));
        values.push(10.0 * (1.0 / mse).log10());
        values.extend(per_step.clone().map(|c| psnr(c[views - 1])));
        values.extend(
            per_step.map(|c| psnr(c[..views - 1].iter().sum::<f64>() / (views - 1).max(1) as f64)),
        );
        Ok(SampleRow { names, values })
    }

    /// The forward half of the next [`Trainer::train_step`] (same dropout masks, same loss),
    /// without the backward or the optimiser step, so the step's loss and gradients can be
    /// inspected, e.g. compared between two implementations of the geometry. Calling it twice
    /// draws the same masks only once the weights exist: Burn initialises parameters lazily,
    /// from the RNG re-seeded here, so a model's first forward draws its weights too.
    pub fn step_loss(
        &self,
        inputs: &ModelInputs,
        mesh: &GomMesh,
        laplacian: &UniformLaplacian,
    ) -> Result<StepLoss, TrainError> {
        let sample = BatchSample {
            index: self.samples,
            inputs,
        };
        self.sample_loss(&sample, mesh, laplacian)
    }

    /// The loss of one sample of a batch, its dropout seeded by the sample's stream index.
    fn sample_loss(
        &self,
        sample: &BatchSample<'_>,
        mesh: &GomMesh,
        laplacian: &UniformLaplacian,
    ) -> Result<StepLoss, TrainError> {
        let inputs = sample.inputs;
        self.device
            .seed(derived_seed(self.seed, DROPOUT, sample.index));
        // Every state rendered in the N source views and the target view, `[N + 1, …]`.
        let targets = TargetViews {
            cameras: vec![inputs.target_camera],
            skinning: vec![inputs.target_skinning.clone()],
        };
        let rec =
            self.model
                .forward_with_targets(&inputs.subject, mesh, &inputs.sources, &targets)?;
        let t = rec.states.len();
        let n = inputs.sources.cameras.len();
        let preds: Vec<Tensor<4>> = rec.renders.iter().map(|r| r.rgb.clone()).collect();
        let alphas: Vec<Tensor<4>> = rec.renders.iter().map(|r| r.alpha.clone()).collect();
        let last_target = preds.last().map(|rgb| rgb.clone().narrow(0, n, 1));
        let span = tracing::debug_span!("losses").entered();
        let gt_rgb = Tensor::cat(
            vec![
                inputs.sources.images.clone(),
                inputs.target_rgb.clone().unsqueeze_dim(0),
            ],
            0,
        );
        let gt_mask = Tensor::cat(
            vec![
                inputs.source_masks.clone(),
                inputs.target_mask.clone().unsqueeze_dim(0),
            ],
            0,
        );
        let pred = Tensor::cat(preds, 0);
        let alpha = Tensor::cat(alphas, 0);
        let gt_rgb = gt_rgb.repeat_dim(0, t);
        // One MSE per rendered image, `[T·(N+1)]`, for the per-step statistics.
        let image_mse = (pred.clone().detach() - gt_rgb.clone())
            .powf_scalar(2.0)
            .flatten::<2>(1, 3)
            .mean_dim(1)
            .flatten::<1>(0, 1);
        let gt_mask = gt_mask.repeat_dim(0, t);
        let meshes = Tensor::stack(rec.states.iter().map(|s| s.xyz.clone()).collect(), 0);
        let terms = LossTerms {
            rgb: l1(pred.clone(), gt_rgb.clone()),
            mask: mask_l1(alpha, gt_mask),
            lpips: match &self.lpips {
                Some(net) => Some(lpips_loss(net, pred.clone(), gt_rgb.clone())?),
                None => None,
            },
            ssim: ssim_loss(pred, gt_rgb),
            laplacian: laplacian.loss(meshes),
        };
        let loss = self.weights.total(terms)?;
        drop(span);
        Ok(StepLoss {
            loss,
            image_mse,
            last_target: last_target.ok_or(TrainError::NoFeedbackStep)?,
            iterations: t,
        })
    }
}

/// LPIPS-VGG for the LPIPS term when `[train] loss_lpips > 0` and the converted weights are in
/// the weights folder (`$LIFEGOM_WEIGHTS` or `weights/`), frozen; `None` otherwise.
fn lpips_network(train: &TrainSection, device: &Device) -> Result<Option<Lpips>, TrainError> {
    if train.loss_lpips <= 0.0 {
        return Ok(None);
    }
    let path = PerceptualModels::default_dir().join(LPIPS_VGG_FILE);
    if !path.is_file() {
        return Ok(None);
    }
    Ok(Some(Lpips::load(LpipsNet::Vgg, &path, device)?.frozen()))
}

/// The official AIST++ LPIPS term: LPIPS-VGG of every render against its ground truth after
/// `F.interpolate(scale_factor=0.5)` (nearest: every other pixel from the first), mean over
/// the images (design.md §9.2).
fn lpips_loss(net: &Lpips, pred: Tensor<4>, gt: Tensor<4>) -> Result<Tensor<1>, TrainError> {
    let d = net.try_distance(half_nearest(pred), half_nearest(gt))?;
    Ok(d.mean())
}

/// `[B, C, H, W]` → `[B, C, ⌊H/2⌋, ⌊W/2⌋]`, keeping the even rows and columns.
fn half_nearest(x: Tensor<4>) -> Tensor<4> {
    let [b, c, h, w] = x.dims();
    let (h2, w2) = (h / 2, w / 2);
    x.narrow(2, 0, h2 * 2)
        .narrow(3, 0, w2 * 2)
        .reshape([b, c, h2, 2, w2, 2])
        .narrow(3, 0, 1)
        .narrow(5, 0, 1)
        .reshape([b, c, h2, w2])
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::tensor::TensorData;
    use lifegom_perceptual::lpips::LpipsConfig;

    /// `F.interpolate(scale_factor=0.5)` (nearest) keeps the even rows and columns, and drops
    /// an odd last one.
    #[test]
    fn half_nearest_keeps_even_pixels() {
        let device = Device::flex();
        let x = Tensor::<4>::from_data(
            TensorData::new((0..2 * 5 * 7).map(|v| v as f32).collect(), [1, 2, 5, 7]),
            &device,
        );
        let h = half_nearest(x);
        assert_eq!(h.dims(), [1, 2, 2, 3]);
        let v: Vec<f32> = h.into_data().convert::<f32>().try_to_vec().unwrap();
        // Channel 0: rows 0, 2 of a 5 × 7 ramp, columns 0, 2, 4; channel 1 the same + 35.
        assert_eq!(v, [0., 2., 4., 14., 16., 18., 35., 37., 39., 49., 51., 53.]);
    }

    /// The LPIPS term is zero for identical images, and a gradient reaches the renders but
    /// not the frozen network.
    #[test]
    fn the_lpips_term_trains_the_renders_only() {
        let device = Device::flex().autodiff();
        let net = Lpips::from_model(
            LpipsNet::Vgg,
            LpipsConfig::for_net(LpipsNet::Vgg).init(&device),
        )
        .frozen();
        let image = |seed: f32| {
            Tensor::<4>::from_data(
                TensorData::new(
                    (0..2 * 3 * 40 * 40)
                        .map(|i| (0.5 + 0.4 * ((i as f32) * seed).sin()).clamp(0.0, 1.0))
                        .collect(),
                    [2, 3, 40, 40],
                ),
                &device,
            )
        };
        let same = lpips_loss(&net, image(0.37), image(0.37)).unwrap();
        let same: Vec<f32> = same.into_data().convert::<f32>().try_to_vec().unwrap();
        assert!(same[0].abs() < 1e-6, "{same:?}");
        let pred = image(0.37).require_grad();
        let loss = lpips_loss(&net, pred.clone(), image(0.11)).unwrap();
        let grads = loss.backward();
        let g = pred.grad(&grads).expect("the renders get a gradient");
        let g: Vec<f32> = g.into_data().convert::<f32>().try_to_vec().unwrap();
        assert!(g.iter().any(|v| *v != 0.0) && g.iter().all(|v| v.is_finite()));
        let conv = &net.model().convs[0];
        assert!(conv.weight.grad(&grads).is_none(), "the network is frozen");
    }
}
