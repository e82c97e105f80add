//! Errors of the model crate: each wraps the failing stage's own error, so the message names
//! the input at fault.

use crate::encoder::EncoderError;
use lifegom_ops::sampling::SamplingError;
use lifegom_render::RenderError;

/// Errors raised by the reconstructor.
#[derive(Debug, thiserror::Error)]
pub enum ModelError {
    /// Geometry, skinning, visibility or rendering failed.
    #[error(transparent)]
    Render(#[from] RenderError),
    /// Projection or feature sampling failed.
    #[error(transparent)]
    Sampling(#[from] SamplingError),
    /// The image encoder failed (weights file, width).
    #[error(transparent)]
    Encoder(#[from] EncoderError),
    /// Tensor values could not be read back to the host.
    #[error(transparent)]
    Readback(#[from] lifegom_render::readback::ReadbackError),
    /// Inputs that do not fit together.
    #[error("invalid `{what}`: {reason}")]
    InvalidInput {
        /// Which input.
        what: &'static str,
        /// What is wrong with it.
        reason: String,
    },
}

/// Result alias for the model crate.
pub type Result<T, E = ModelError> = std::result::Result<T, E>;
