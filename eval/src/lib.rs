//! # lifegom-eval
//!
//! Evaluation of LIFe-GoM avatars on THuman-style splits (design.md §10): novel-view renders scored
//! with PSNR, SSIM, LPIPS (alex, vgg) and FID under the THuman/XHuman crop protocol or the
//! AIST++ full-image protocol; comparison sheets; free-view turntables and procedural novel-pose
//! animations; and the accuracy-vs-time sweep (quality against reconstruction and render time
//! over T and subdivision levels, the paper's Tables 4–5).
//!
//! ```no_run
//! use lifegom_eval::metrics::{ImageRef, psnr};
//! # fn main() -> Result<(), lifegom_eval::metrics::MetricsError> {
//! let (pred, gt) = (vec![0.5f32; 8 * 8 * 3], vec![0.25f32; 8 * 8 * 3]);
//! let db = psnr(ImageRef::new(&pred, [8, 8, 3])?, ImageRef::new(&gt, [8, 8, 3])?, 1.0)?;
//! assert!((db - 12.04).abs() < 0.01);
//! # Ok(()) }
//! ```
//!
//! ## Module map
//!
//! - [`metrics`]: host-side PSNR, skimage-compatible SSIM and the THuman 1000×500 foreground
//!   crop (design.md §10.2–§10.4).
//! - [`evaluate`]: reconstruct each validation subject once, render its targets, score them;
//!   the same loop scores the baselines.
//! - [`baselines`]: reconstructions without learning (the template in one colour, projective
//!   texturing).
//! - [`animate`]: free-view orbits; the motions (procedural walk, arm-raise, squat and
//!   pose-sequence files) are `lifegom_render::motion`, re-exported there.
//! - [`per_scene`]: the per-scene optimisation baseline scored after K gradient steps.
//! - [`folders`]: two folders of images scored against each other (`lifegom-metrics`).
//! - [`validation`]: every feedback step's scores on the validation split (training's curves).
//! - [`report`]: CSVs, `summary.json`, `report.md`, the Pareto plot.
//! - [`error`]: the library's one error type.
//! - [`images`], [`plot`]: PNG/GIF writing, sheets, error maps; charts drawn with plotters
//!   (PNG and SVG, an embedded font).
//! - [`perceptual`]: LPIPS v0.1 (AlexNet, VGG16) and pytorch-fid's Inception pool3 features and
//!   Fréchet distance, as Burn modules loading converted weights; [`perceptual_scores`]: how the
//!   evaluation uses them.

pub mod animate;
pub mod baselines;
pub mod capacity;
pub mod error;
pub mod evaluate;
pub mod folders;
pub mod images;
pub mod metrics;
pub mod per_scene;
pub mod perceptual_scores;
pub mod plot;
pub mod report;
pub mod validation;

/// LPIPS, the FID Inception and the Fréchet distance, and their weights (`lifegom-perceptual`).
pub use lifegom_perceptual as perceptual;
