//! What can go wrong reading or running a graph; every error names the graph (its file, or the
//! name it was given) and, where there is one, the operator or tensor.

use std::path::PathBuf;

/// An error of reading or running a TensorFlow Lite graph.
#[derive(Debug, thiserror::Error)]
pub enum TfliteError {
    /// The file cannot be read.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The underlying error.
        source: std::io::Error,
    },
    /// The bytes are not a TensorFlow Lite model this reader can follow.
    #[error("{graph}: not a readable TensorFlow Lite model: {reason}")]
    Format {
        /// The graph.
        graph: String,
        /// What is wrong.
        reason: String,
    },
    /// A tensor whose declaration or data cannot be used.
    #[error("{graph}: tensor {index} `{name}`: {reason}")]
    Tensor {
        /// The graph.
        graph: String,
        /// The tensor's index in the subgraph.
        index: usize,
        /// Its name in the file.
        name: String,
        /// What is wrong.
        reason: String,
    },
    /// An operator this reader does not run, or one whose inputs, options or shapes do not fit.
    #[error("{graph}: operator {index} ({op}): {reason}")]
    Operator {
        /// The graph.
        graph: String,
        /// The operator's position in the subgraph.
        index: usize,
        /// Its name (`CONV_2D`, a custom code, or `BUILTIN_<n>` for one unknown here).
        op: String,
        /// What is wrong.
        reason: String,
    },
    /// Inputs given to [`crate::Graph::run`] that do not fit the graph's inputs.
    #[error("{graph}: input {index}: {reason}")]
    Input {
        /// The graph.
        graph: String,
        /// The input's position.
        index: usize,
        /// What is wrong.
        reason: String,
    },
}

/// Results of this crate.
pub type Result<T> = std::result::Result<T, TfliteError>;
