//! # lifegom-eval
//!
//! The evaluation command for THuman-style splits (spec §7): novel-view and novel-pose
//! renders, PSNR, SSIM, LPIPS-style and FID metrics.
//!
//! Not implemented yet: this crate is the home of the `lifegom-eval` binary (issue "Train and
//! eval commands"). It builds so the workspace layout is in place.
//!
//! ## Module map
//!
//! - [`metrics`]: host-side PSNR, skimage-compatible SSIM and the THuman 1000×500 foreground
//!   crop (spec §7.2–§7.3).
//! - [`perceptual`]: LPIPS v0.1 (AlexNet, VGG16) and pytorch-fid's Inception pool3 features
//!   and Fréchet distance, as Burn modules loading converted weights.

pub mod metrics;
pub mod perceptual;
