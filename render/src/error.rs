//! One error type for the render crate.
//!
//! Every variant names *what* was wrong (the file, the tensor, the field) and *where* (an index
//! when there is one), so a user sees one clear line instead of a panic deep inside a kernel.

use std::path::PathBuf;

/// Errors raised at the render crate's API boundaries.
#[derive(Debug, thiserror::Error)]
pub enum RenderError {
    /// A camera that cannot project: non-positive focal length, zero image size, a non-finite
    /// entry, or an extrinsic rotation that is not a rotation.
    #[error("invalid camera: field `{field}`: {reason}")]
    InvalidCamera {
        /// The camera field at fault (`fx`, `cam_from_world`, `width`, ...).
        field: &'static str,
        /// What is wrong with it.
        reason: String,
    },
    /// A tensor whose shape does not match the API contract.
    #[error("shape mismatch for `{tensor}`: expected {expected}, got {got:?}")]
    Shape {
        /// Which input.
        tensor: &'static str,
        /// The contract, in words (`[N, 3]`).
        expected: String,
        /// The shape received.
        got: Vec<usize>,
    },
    /// A NaN or infinite value where only finite values make sense.
    #[error("non-finite value in `{tensor}` at flat index {index}")]
    NonFinite {
        /// Which input.
        tensor: &'static str,
        /// First offending element, as a flat index into the tensor.
        index: usize,
    },
    /// An input that is finite but outside the domain (a face index past the vertex count, ...).
    #[error("invalid `{what}`: {reason}")]
    InvalidInput {
        /// Which input.
        what: &'static str,
        /// What is wrong with it.
        reason: String,
    },
    /// A body template that cannot be read or is inconsistent.
    #[error("body template {path}: field `{field}`: {reason}")]
    Template {
        /// The file.
        path: PathBuf,
        /// The glTF field at fault (`skins[0].inverseBindMatrices`, `extras.joint_parents`, ...).
        field: String,
        /// What is wrong with it.
        reason: String,
    },
    /// A pose-sequence (motion) file that cannot be read or does not fit its rig.
    #[error("motion file {path}: field `{field}`: {reason}")]
    Motion {
        /// The file (or `<walk>` for a procedural motion).
        path: PathBuf,
        /// The field at fault (`fps`, `frames[12][40]`, `joint_names[3]`, ...).
        field: String,
        /// What is wrong with it.
        reason: String,
    },
    /// Tensor values could not be read back to the host.
    #[error(transparent)]
    Readback(#[from] crate::readback::ReadbackError),
    /// An I/O failure, with the file it concerns.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The underlying error.
        source: std::io::Error,
    },
}

/// Result alias for the render crate.
pub type Result<T, E = RenderError> = std::result::Result<T, E>;

/// Returns the first non-finite element of `values`, as a [`RenderError::NonFinite`].
pub fn check_finite(tensor: &'static str, values: &[f32]) -> Result<()> {
    match values.iter().position(|v| !v.is_finite()) {
        Some(index) => Err(RenderError::NonFinite { tensor, index }),
        None => Ok(()),
    }
}
