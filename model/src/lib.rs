//! # lifegom-model
//!
//! The LIFe-GoM reconstructor (spec §5): from N source images with masks, cameras and body
//! poses, predict a canonical T-pose Gaussians-on-Mesh, refined by T steps of learned feedback
//! that compare re-renders of the current avatar with the inputs.
//!
//! | module | concept |
//! |---|---|
//! | [`fusion`] | multi-source fusion: self-attention over views, cross-attention with a per-vertex query |
//!
//! Model code has no backend generic: modules take a `burn::tensor::Device` and run on ndarray,
//! Flex (and wgpu once the GPU kernels land), with `.autodiff()` for training.

pub mod avatar;
pub mod encoder;
pub mod error;
pub mod feedback;
pub mod fusion;
pub mod heads;
pub mod knn;
pub mod point_transformer;
pub mod sampling;
