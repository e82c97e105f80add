//! Where a training step's sample comes from (`[train] subjects`, design.md §9.5).
//!
//! - [`TrainingSource::Split`]: the training split on disk, in seeded epochs
//!   ([`crate::trainer::schedule`]) — the reference's setting.
//! - [`TrainingSource::Procedural`]: subject `step` of a [`SubjectStream`], a person generated
//!   for this step alone, so the model cannot memorise its training people and must read the
//!   photos.
//!
//! Both are pure functions of `(seed, step)`, which is what makes `--resume` exact and lets the
//! [`crate::prefetch::Prefetcher`] prepare the next step's sample on another thread.

use std::sync::Arc;

use lifegom_data::dataset::{Dataset, Sample, Split};
use lifegom_data::synth::stream::SubjectStream;
use lifegom_model::inputs::SubjectRig;

use crate::config::{ExperimentConfig, TrainingSubjects};
use crate::trainer::{TrainError, sample_for_step};

/// A sample of the run's stream with the body rig of its subject.
#[derive(Debug, Clone)]
pub struct StepSample {
    /// Its index in the stream.
    pub index: u64,
    /// The N inputs and the target.
    pub sample: Sample,
    /// The subject's canonical body, skeleton and skinning.
    pub rig: Arc<SubjectRig>,
}

/// The samples a training run iterates over (module docs).
#[derive(Debug)]
pub enum TrainingSource {
    /// A split on disk and the rig of each of its subjects.
    Split {
        /// The split.
        dataset: Arc<Dataset>,
        /// One rig per subject, in split order.
        rigs: Vec<Arc<SubjectRig>>,
    },
    /// A fresh synthetic subject per step.
    Procedural {
        /// The stream (boxed: it holds the whole body template).
        stream: Box<SubjectStream>,
        /// The template's own rig (topology and vertex count every subject shares).
        template: Arc<SubjectRig>,
    },
}

impl TrainingSource {
    /// The source `cfg` asks for.
    pub fn open(cfg: &ExperimentConfig) -> Result<Self, TrainError> {
        match cfg.train.subjects {
            TrainingSubjects::Split => {
                let dataset = Dataset::open(&cfg.file.data, Split::Train)?;
                Self::from_split(Arc::new(dataset))
            }
            TrainingSubjects::Procedural => {
                let synth = cfg.file.synthetic.as_ref().ok_or_else(|| {
                    TrainError::Source(format!(
                        "{}: [train] subjects = \"procedural\" needs a [synthetic] section",
                        cfg.file.source.display()
                    ))
                })?;
                let stream = SubjectStream::new(synth, &cfg.file.data)?;
                let template = SubjectRig::new("template", &stream.template_body())?;
                Ok(Self::Procedural {
                    stream: Box::new(stream),
                    template: Arc::new(template),
                })
            }
        }
    }

    /// A source over an opened split.
    pub fn from_split(dataset: Arc<Dataset>) -> Result<Self, TrainError> {
        if dataset.is_empty() {
            return Err(TrainError::Source("the training split is empty".into()));
        }
        let rigs = SubjectRig::for_split(&dataset)?
            .into_iter()
            .map(Arc::new)
            .collect();
        Ok(Self::Split { dataset, rigs })
    }

    /// A rig whose topology and vertex count every sample shares (to build the mesh, the
    /// Laplacian and the model).
    pub fn reference_rig(&self) -> &SubjectRig {
        match self {
            Self::Split { rigs, .. } => &rigs[0],
            Self::Procedural { template, .. } => template,
        }
    }

    /// Sample `step` of the stream under `seed` (the step's own sample in a run with one
    /// sample a step).
    pub fn sample(&self, seed: u64, step: u64) -> Result<StepSample, TrainError> {
        match self {
            Self::Split { dataset, rigs } => {
                let sample = sample_for_step(dataset, seed, step)?;
                let rig = dataset
                    .subjects
                    .iter()
                    .position(|s| s.name == sample.subject)
                    .map(|i| rigs[i].clone())
                    .ok_or_else(|| {
                        TrainError::Source(format!(
                            "sample from unknown subject {}",
                            sample.subject
                        ))
                    })?;
                Ok(StepSample {
                    index: step,
                    sample,
                    rig,
                })
            }
            Self::Procedural { stream, .. } => {
                let generated = stream.sample(seed, step)?;
                let rig = SubjectRig::new(&generated.sample.subject, &generated.canonical)?;
                Ok(StepSample {
                    index: step,
                    sample: generated.sample,
                    rig: Arc::new(rig),
                })
            }
        }
    }
}
