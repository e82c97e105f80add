//! The three person graphs of MediaPipe, fetched from the Python package registry and read by
//! `lifegom-tflite`.
//!
//! | graph | file | size | input → outputs |
//! |---|---|---|---|
//! | BlazePose detector | `pose_detection.tflite` | 2.96 MB | `[1, 224, 224, 3]` in [-1, 1] → 2254 anchors' boxes and keypoints `[1, 2254, 12]`, scores `[1, 2254, 1]` |
//! | BlazePose landmarks (full) | `pose_landmark_full.tflite` | 6.44 MB | `[1, 256, 256, 3]` in [0, 1] → 39 landmarks × 5 `[1, 195]`, presence `[1, 1]`, segmentation logits `[1, 256, 256, 1]`, heatmaps `[1, 64, 64, 39]`, world landmarks `[1, 117]` |
//! | selfie segmentation | `selfie_segmentation.tflite` | 0.25 MB | `[1, 256, 256, 3]` in [0, 1] → person probability `[1, 256, 256, 1]` |
//!
//! All three come from one file, the `mediapipe` 0.10.14 wheel for CPython 3.11 on
//! manylinux2014 x86-64 (Apache-2.0; the 1.x wheels no longer carry the graphs). The wheel is
//! the same for every machine, since pip is told the platform and Python version; its SHA-256
//! is checked, and so is each graph's as it is taken out and again as it is loaded.

use std::path::{Path, PathBuf};

use burn::tensor::Device;
use lifegom_data::registry::{self, Package, RegistryError};
use lifegom_tflite::{Graph, TfliteError};

/// The mediapipe 0.10.14 wheel that ships the graphs.
pub const MEDIAPIPE: Package = Package {
    requirement: "mediapipe==0.10.14",
    archive: "mediapipe-0.10.14-cp311-cp311-manylinux_2_17_x86_64.manylinux2014_x86_64.whl",
    sha256: "a807328339e7356fda0bb14df12fedbf1d33bdf81649c5f8666b0026b1cc30b4",
    bytes: 35_664_771,
    licence: "Apache-2.0",
    pip_options: &[
        "--only-binary",
        ":all:",
        "--platform",
        "manylinux2014_x86_64",
        "--python-version",
        "311",
    ],
    by_hand: "download mediapipe-0.10.14-cp311-cp311-manylinux_2_17_x86_64.manylinux2014_x86_64.whl \
              from https://pypi.org/project/mediapipe/0.10.14/#files and run `lifegom-weights \
              convert` on it",
};

/// One of the person graphs.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum PersonGraph {
    /// BlazePose's person detector.
    Detector,
    /// BlazePose's landmark model (the full one), with its person segmentation.
    Landmarks,
    /// The selfie segmentation model.
    Selfie,
}

impl PersonGraph {
    /// All three.
    pub const ALL: [PersonGraph; 3] = [
        PersonGraph::Detector,
        PersonGraph::Landmarks,
        PersonGraph::Selfie,
    ];

    /// The file in the weights folder.
    pub fn file_name(self) -> &'static str {
        match self {
            PersonGraph::Detector => "pose_detection.tflite",
            PersonGraph::Landmarks => "pose_landmark_full.tflite",
            PersonGraph::Selfie => "selfie_segmentation.tflite",
        }
    }

    /// Its entry in the wheel.
    pub fn wheel_entry(self) -> &'static str {
        match self {
            PersonGraph::Detector => "mediapipe/modules/pose_detection/pose_detection.tflite",
            PersonGraph::Landmarks => "mediapipe/modules/pose_landmark/pose_landmark_full.tflite",
            PersonGraph::Selfie => {
                "mediapipe/modules/selfie_segmentation/selfie_segmentation.tflite"
            }
        }
    }

    /// Its SHA-256, hex.
    pub fn sha256(self) -> &'static str {
        match self {
            PersonGraph::Detector => {
                "9ba9dd3d42efaaba86b4ff0122b06f29c4122e756b329d89dca1e297fd8f866c"
            }
            PersonGraph::Landmarks => {
                "e9a5c5cb17f736fafd4c2ec1da3b3d331d6edbe8a0d32395855aeb2cdfd64b9f"
            }
            PersonGraph::Selfie => {
                "9ee168ec7c8f2a16c56fe8e1cfbc514974cbbb7e434051b455635f1bd1462f5c"
            }
        }
    }

    /// The side of its square input image.
    pub fn input_size(self) -> usize {
        match self {
            PersonGraph::Detector => 224,
            PersonGraph::Landmarks | PersonGraph::Selfie => 256,
        }
    }

    /// The input's value range as `scale · u8 + offset` (the detector takes [-1, 1], the others
    /// [0, 1], as MediaPipe's graphs feed them).
    pub fn input_range(self) -> (f32, f32) {
        match self {
            PersonGraph::Detector => (1.0 / 127.5, -1.0),
            PersonGraph::Landmarks | PersonGraph::Selfie => (1.0 / 255.0, 0.0),
        }
    }
}

impl std::fmt::Display for PersonGraph {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.file_name())
    }
}

/// Errors of fetching and loading the graphs.
#[derive(Debug, thiserror::Error)]
pub enum GraphsError {
    /// Downloading or opening the wheel.
    #[error(transparent)]
    Registry(#[from] RegistryError),
    /// A graph file that is not the pinned one.
    #[error(
        "{path}: SHA-256 {found}, expected {expected}: not mediapipe 0.10.14's {graph}; run \
         `lifegom-weights fetch` again"
    )]
    Hash {
        /// The file.
        path: PathBuf,
        /// Which graph it should be.
        graph: PersonGraph,
        /// The pinned hash.
        expected: &'static str,
        /// The file's.
        found: String,
    },
    /// A graph not in the weights folder.
    #[error(
        "{path}: missing; `lifegom-weights fetch` downloads it (mediapipe 0.10.14, Apache-2.0, \
         35.7 MB), or {}",
        MEDIAPIPE.by_hand
    )]
    Missing {
        /// Where it should be.
        path: PathBuf,
    },
    /// The reader refused the graph.
    #[error(transparent)]
    Tflite(#[from] TfliteError),
}

/// The graphs missing from `dir`.
pub fn missing(dir: &Path) -> Vec<PersonGraph> {
    PersonGraph::ALL
        .into_iter()
        .filter(|g| !dir.join(g.file_name()).is_file())
        .collect()
}

/// Downloads the wheel with pip (unless every graph is already in `dir`) and takes the missing
/// graphs out of it; returns the files written. `progress` gets one line per step.
pub fn fetch(dir: &Path, progress: &mut dyn FnMut(&str)) -> Result<Vec<PathBuf>, GraphsError> {
    if missing(dir).is_empty() {
        return Ok(Vec::new());
    }
    let pip = registry::find_pip(MEDIAPIPE)?;
    let tmp = tempfile::tempdir().map_err(|source| RegistryError::Io {
        path: std::env::temp_dir(),
        source,
    })?;
    progress(&format!(
        "downloading {} ({:.1} MB, {} licence) with pip …",
        MEDIAPIPE.requirement,
        MEDIAPIPE.bytes as f64 / 1e6,
        MEDIAPIPE.licence
    ));
    let start = std::time::Instant::now();
    let wheel = registry::download(&pip, MEDIAPIPE, tmp.path())?;
    progress(&format!(
        "  {} in {:.1} s, SHA-256 checked",
        MEDIAPIPE.archive,
        start.elapsed().as_secs_f64()
    ));
    extract(&wheel, dir)
}

/// Takes the graphs missing from `dir` out of the mediapipe wheel at `wheel` (one a user
/// brings, or the one [`fetch`] downloaded); returns the files written.
pub fn extract(wheel: &Path, dir: &Path) -> Result<Vec<PathBuf>, GraphsError> {
    registry::check_hash(wheel, MEDIAPIPE)?;
    let mut written = Vec::new();
    for graph in missing(dir) {
        let bytes = registry::read_zip_entry(wheel, graph.wheel_entry())?;
        let path = dir.join(graph.file_name());
        check(&path, graph, &bytes)?;
        lifegom_render::atomic_file::write_atomic(&path, &bytes).map_err(|source| {
            RegistryError::Io {
                path: path.clone(),
                source,
            }
        })?;
        written.push(path);
    }
    Ok(written)
}

/// Reads graph `graph` from `dir` onto `device`, its hash checked.
pub fn load(dir: &Path, graph: PersonGraph, device: &Device) -> Result<Graph, GraphsError> {
    let path = dir.join(graph.file_name());
    let bytes = match std::fs::read(&path) {
        Ok(b) => b,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
            return Err(GraphsError::Missing { path });
        }
        Err(source) => return Err(RegistryError::Io { path, source }.into()),
    };
    check(&path, graph, &bytes)?;
    Ok(Graph::from_bytes(
        &path.display().to_string(),
        &bytes,
        device,
    )?)
}

fn check(path: &Path, graph: PersonGraph, bytes: &[u8]) -> Result<(), GraphsError> {
    let found = registry::sha256(bytes);
    if found != graph.sha256() {
        return Err(GraphsError::Hash {
            path: path.to_path_buf(),
            graph,
            expected: graph.sha256(),
            found,
        });
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_changed_graph_is_refused_by_its_hash() {
        let tmp = tempfile::tempdir().unwrap();
        let dir = tmp.path();
        std::fs::write(
            dir.join(PersonGraph::Selfie.file_name()),
            b"TFL3 not the graph",
        )
        .unwrap();
        let err = load(dir, PersonGraph::Selfie, &Device::flex()).unwrap_err();
        let text = err.to_string();
        assert!(matches!(err, GraphsError::Hash { .. }), "{text}");
        assert!(text.contains("selfie_segmentation.tflite"), "{text}");
        let err = load(dir, PersonGraph::Detector, &Device::flex()).unwrap_err();
        assert!(matches!(err, GraphsError::Missing { .. }), "{err}");
        assert!(err.to_string().contains("lifegom-weights fetch"), "{err}");
    }
}
