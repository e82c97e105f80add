//! One error type for the evaluation library: each variant wraps the failing stage's own
//! error, so the message names the input at fault (a file, a frame, a tensor).

use std::path::PathBuf;

/// Errors raised while evaluating a split or writing its report.
#[derive(Debug, thiserror::Error)]
pub enum EvalError {
    /// Reading the split failed.
    #[error(transparent)]
    Data(#[from] lifegom_data::error::DataError),
    /// The model failed (bad inputs, rendering).
    #[error(transparent)]
    Model(#[from] lifegom_model::error::ModelError),
    /// Geometry or rendering failed.
    #[error(transparent)]
    Render(#[from] lifegom_render::RenderError),
    /// Tensor values could not be read back.
    #[error(transparent)]
    Readback(#[from] lifegom_render::readback::ReadbackError),
    /// A metric got inputs it cannot score.
    #[error(transparent)]
    Metrics(#[from] crate::metrics::MetricsError),
    /// Writing or converting an image failed.
    #[error(transparent)]
    Image(#[from] crate::images::ImageError),
    /// LPIPS or FID failed.
    #[error(transparent)]
    Perceptual(#[from] crate::perceptual::PerceptualError),
    /// Per-scene optimisation failed.
    #[error(transparent)]
    Fit(#[from] lifegom_train::trainer::TrainError),
    /// An input file or folder that cannot be scored (unpaired, differently sized, empty).
    #[error("{path}: {reason}")]
    Input {
        /// The file or folder.
        path: PathBuf,
        /// What is wrong.
        reason: String,
    },
    /// A file could not be written.
    #[error("writing {path}: {reason}")]
    Write {
        /// The file.
        path: PathBuf,
        /// The cause.
        reason: String,
    },
    /// The request does not fit the data (a subject or frame out of range).
    #[error("{0}")]
    Invalid(String),
    /// Reconstructing one frame's avatar failed.
    #[error("reconstructing {frame}: {source}")]
    Frame {
        /// `scene_<subject>_<frame>`.
        frame: String,
        /// The cause.
        source: Box<EvalError>,
    },
}

impl EvalError {
    /// A [`EvalError::Write`] for `path`.
    pub fn write(path: &std::path::Path, reason: impl std::fmt::Display) -> Self {
        Self::Write {
            path: path.to_path_buf(),
            reason: reason.to_string(),
        }
    }
}
