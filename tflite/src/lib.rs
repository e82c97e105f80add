//! A TensorFlow Lite reader that runs what it reads on Burn.
//!
//! [`Graph::read`] takes a `.tflite` file (a FlatBuffer, read through code generated from our
//! declaration of the format, `schema/tflite.fbs`), makes every constant f32 and dense once
//! (f16 weights, CSR-sparse kernels behind `DENSIFY`), converts NHWC to Burn's NCHW once, and
//! checks each operator's shapes against the file before anything runs; [`Graph::run`] then
//! runs the operators as Burn tensor ops, on whichever device the graph was read onto (Flex,
//! ndarray, wgpu). The operators are those of MediaPipe's person graphs (pose detector, pose
//! landmarks, selfie segmentation): `CONV_2D`, `DEPTHWISE_CONV_2D`, MediaPipe's custom
//! `Convolution2DTransposeBias`, `MAX_POOL_2D`, `AVERAGE_POOL_2D`, `ADD`, `MUL`,
//! `CONCATENATION`, `RESHAPE`, `PAD`, `RESIZE_BILINEAR`, `DEPTH_TO_SPACE`, `LOGISTIC`, `RELU`,
//! `RELU6`, `TANH`, `HARD_SWISH`, and `DEQUANTIZE` / `DENSIFY` on constants. Anything else is
//! an error naming the operator and the graph.

mod error;
mod file;
mod graph;
mod op;
mod sparse;
#[doc(hidden)]
pub mod testing;

#[allow(
    dead_code,
    missing_docs,
    unreachable_pub,
    clippy::all,
    clippy::pedantic,
    clippy::undocumented_unsafe_blocks,
    clippy::semicolon_if_nothing_returned,
    clippy::explicit_iter_loop,
    clippy::manual_let_else,
    clippy::redundant_else,
    clippy::inefficient_to_string
)]
#[rustfmt::skip]
mod schema;

pub use error::{Result, TfliteError};
pub use graph::{Graph, Output, TensorSpec};
