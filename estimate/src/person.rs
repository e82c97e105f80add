//! The person in one photo: detector, crop, landmark model; its mask is the landmark model's
//! (the better of the two graphs against true masks, design.md §8.12).

use std::path::{Path, PathBuf};

use burn::tensor::Device;
use lifegom_tflite::{Graph, TfliteError};

use crate::detector::{self, Detection};
use crate::graphs::{self, GraphsError, PersonGraph};
use crate::landmarks::{self, Pose};

/// Errors of estimating the person in a photo; each names the photo.
#[derive(Debug, thiserror::Error)]
pub enum PersonError {
    /// The photo cannot be read as an image.
    #[error("{path}: not a readable image: {reason}")]
    Image {
        /// The photo.
        path: PathBuf,
        /// The decoder's message.
        reason: String,
    },
    /// The detector finds nobody, or the landmark model sees no person in the crop.
    #[error(
        "{path}: no person found ({reason}); a photo needs one person, whole or nearly, not \
         too small in the frame"
    )]
    NoPerson {
        /// The photo.
        path: PathBuf,
        /// Which stage gave up, with its score.
        reason: String,
    },
    /// Loading the graphs.
    #[error(transparent)]
    Graphs(#[from] GraphsError),
    /// Running a graph.
    #[error("{path}: {source}")]
    Graph {
        /// The photo.
        path: PathBuf,
        /// The reader's error.
        source: TfliteError,
    },
}

/// The two graphs the pipeline runs, loaded once.
#[derive(Debug, Clone)]
pub struct PersonGraphs {
    detector: Graph,
    landmarks: Graph,
    device: Device,
}

/// The person found in a photo.
#[derive(Debug, Clone)]
pub struct Person {
    /// The detection the crop came from.
    pub detection: Detection,
    /// Landmarks, mask and crop.
    pub pose: Pose,
}

impl PersonGraphs {
    /// Loads the detector and the landmark model from the weights folder `dir`.
    pub fn load(dir: &Path, device: &Device) -> Result<Self, GraphsError> {
        Ok(Self {
            detector: graphs::load(dir, PersonGraph::Detector, device)?,
            landmarks: graphs::load(dir, PersonGraph::Landmarks, device)?,
            device: device.clone(),
        })
    }

    /// The person in the `width × height` RGB photo `rgb`; `path` names it in errors.
    pub fn estimate(
        &self,
        path: &Path,
        rgb: &[u8],
        width: usize,
        height: usize,
    ) -> Result<Person, PersonError> {
        let graph_err = |source| PersonError::Graph {
            path: path.to_path_buf(),
            source,
        };
        let found = detector::detect(&self.detector, rgb, width, height, &self.device)
            .map_err(graph_err)?;
        let Some(detection) = found.first().copied() else {
            return Err(PersonError::NoPerson {
                path: path.to_path_buf(),
                reason: format!(
                    "the detector scores no region above {}",
                    detector::MIN_SCORE
                ),
            });
        };
        let roi = landmarks::roi_from_detection(&detection, width, height);
        let pose = landmarks::landmarks(&self.landmarks, rgb, width, height, &roi, &self.device)
            .map_err(graph_err)?
            .ok_or_else(|| PersonError::NoPerson {
                path: path.to_path_buf(),
                reason: format!(
                    "the detector's region scores {:.2}, but the landmark model sees no person \
                     in it",
                    detection.score
                ),
            })?;
        Ok(Person { detection, pose })
    }

    /// [`PersonGraphs::estimate`] on the photo file at `path` (PNG or JPEG, any size).
    pub fn estimate_file(&self, path: &Path) -> Result<(image::RgbImage, Person), PersonError> {
        let rgb = image::open(path)
            .map_err(|e| PersonError::Image {
                path: path.to_path_buf(),
                reason: e.to_string(),
            })?
            .to_rgb8();
        let (w, h) = (rgb.width() as usize, rgb.height() as usize);
        let person = self.estimate(path, rgb.as_raw(), w, h)?;
        Ok((rgb, person))
    }
}
