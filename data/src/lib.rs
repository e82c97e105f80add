//! # lifegom-data
//!
//! Reads the official LIFe-GoM processed datasets natively and generates synthetic
//! THuman-style splits in exactly that format.
//!
//! | module | concept |
//! |---|---|
//! | [`pickle`] | a Rust pickle VM (numpy arrays, protocols 2–5) and a pickle writer |
//! | [`error`] | one error type naming file / subject / frame / field |
//! | [`kinematics`] | SMPL (24) and SMPL-X (55) parent tables |

pub mod config;
pub mod dataset;
pub mod error;
pub mod format;
pub mod kinematics;
pub mod pickle;
pub mod preprocess;
pub mod rng;
pub mod synth;

pub use error::{DataError, Location, Result};
