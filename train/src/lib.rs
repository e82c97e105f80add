//! # lifegom-train
//!
//! The training command for LIFe-GoM (spec §6): Adam on the reconstructor with the RGB, mask,
//! SSIM and Laplacian losses, supervised on every feedback step's source renders and target view.
//!
//! Not implemented yet: this crate is the home of the `lifegom-train` binary (issue "Train and
//! eval commands"). It builds so the workspace layout is in place.
//!
//! ## Module map
//!
//! - [`losses`]: the losses of spec §6.2 (L1, mask L1, Gaussian-window SSIM, uniform mesh
//!   Laplacian) and the [`losses::LossWeights`] that combine them.

pub mod losses;
