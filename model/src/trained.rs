//! Trained-model files (`.lgck`): the network's weights, the config that builds it, and an
//! opaque payload for whoever wrote the file (the trainer stores its optimizer state there).
//!
//! One file, written atomically: the bytes go to a temporary file in the same directory, are
//! flushed to disk, and then renamed over the destination, so a crash or Ctrl-C mid-write leaves
//! the previous checkpoint intact and never a half-written one.
//!
//! Layout (little endian):
//!
//! ```text
//! b"LGOMCKPT" | u32 version (1) | u64 n | header JSON (n bytes)
//!             | u64 m | model weights, Burn burnpack (m bytes)
//!             | u64 k | payload (k bytes)
//! ```
//!
//! The header holds the [`ReconstructorConfig`], the low-res vertex count (the vertex embedding
//! has one row per template vertex) and free-form metadata. Burnpack keeps parameter ids, so an
//! optimizer state saved alongside resumes against the same parameters.

use std::path::{Path, PathBuf};

use burn::module::Module;
use burn::store::ModuleRecord;
use burn::tensor::{Bytes, Device};
use lifegom_render::atomic_file::write_atomic;
use serde::{Deserialize, Serialize};

use crate::reconstructor::{Reconstructor, ReconstructorConfig};

const MAGIC: &[u8; 8] = b"LGOMCKPT";
const VERSION: u32 = 1;

/// Errors reading or writing a trained-model file; each names the file.
#[derive(Debug, thiserror::Error)]
pub enum TrainedError {
    /// Filesystem error.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The cause.
        source: std::io::Error,
    },
    /// The file is not a trained-model file or is damaged.
    #[error("{path}: not a valid lifegom checkpoint: {reason}")]
    Format {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        reason: String,
    },
    /// The weights do not fit the network the header describes.
    #[error("{path}: weights do not fit the model: {reason}")]
    Weights {
        /// The file.
        path: PathBuf,
        /// Burn's explanation.
        reason: String,
    },
    /// The config in the header cannot build a network.
    #[error("{path}: {source}")]
    Model {
        /// The file.
        path: PathBuf,
        /// The cause.
        source: Box<crate::error::ModelError>,
    },
}

/// The JSON header of a trained-model file.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct TrainedHeader {
    /// The network's config, as `ReconstructorConfig`'s JSON.
    pub config: serde_json::Value,
    /// Rows of the vertex embedding (template vertices).
    pub num_vertices: usize,
    /// Free-form metadata (training step, experiment name, ...).
    pub meta: serde_json::Value,
}

/// A loaded trained-model file.
#[derive(Debug)]
pub struct TrainedModel {
    /// The network, on the device it was loaded to.
    pub model: Reconstructor,
    /// The config it was built from.
    pub config: ReconstructorConfig,
    /// The header as stored.
    pub header: TrainedHeader,
    /// The writer's payload (empty when none).
    pub payload: Vec<u8>,
}

fn io(path: &Path) -> impl FnOnce(std::io::Error) -> TrainedError + '_ {
    move |source| TrainedError::Io {
        path: path.to_path_buf(),
        source,
    }
}

/// Serialises a model, its config and a payload into the file format (module docs).
pub fn encode(
    model: &Reconstructor,
    config: &ReconstructorConfig,
    meta: serde_json::Value,
    payload: &[u8],
) -> Result<Vec<u8>, String> {
    let header = TrainedHeader {
        config: serde_json::from_str(&config.to_string()).map_err(|e| e.to_string())?,
        num_vertices: model.vertex_embed.dims()[0],
        meta,
    };
    let header = serde_json::to_vec(&header).map_err(|e| e.to_string())?;
    let weights = model
        .clone()
        .into_record()
        .into_bytes()
        .map_err(|e| format!("serialising weights: {e}"))?;
    let mut out = Vec::with_capacity(header.len() + weights.len() + payload.len() + 40);
    out.extend_from_slice(MAGIC);
    out.extend_from_slice(&VERSION.to_le_bytes());
    for part in [&header[..], &weights[..], payload] {
        out.extend_from_slice(&(part.len() as u64).to_le_bytes());
        out.extend_from_slice(part);
    }
    Ok(out)
}

/// Saves a model atomically.
pub fn save(
    path: &Path,
    model: &Reconstructor,
    config: &ReconstructorConfig,
    meta: serde_json::Value,
    payload: &[u8],
) -> Result<(), TrainedError> {
    let bytes = encode(model, config, meta, payload).map_err(|reason| TrainedError::Format {
        path: path.to_path_buf(),
        reason,
    })?;
    write_atomic(path, &bytes).map_err(io(path))
}

/// The three sections of a file, unparsed.
fn split(bytes: &[u8]) -> Result<[&[u8]; 3], String> {
    if bytes.len() < 12 || &bytes[..8] != MAGIC {
        return Err("missing the LGOMCKPT magic".into());
    }
    let version = u32::from_le_bytes(bytes[8..12].try_into().unwrap_or_default());
    if version != VERSION {
        return Err(format!("version {version}, this build reads {VERSION}"));
    }
    let mut rest = &bytes[12..];
    let mut parts = [&[][..]; 3];
    for (i, name) in ["header", "weights", "payload"].iter().enumerate() {
        if rest.len() < 8 {
            return Err(format!("truncated before the {name} length"));
        }
        let n = u64::from_le_bytes(rest[..8].try_into().unwrap_or_default());
        rest = &rest[8..];
        if (rest.len() as u64) < n {
            return Err(format!(
                "truncated {name}: {n} bytes announced, {} present",
                rest.len()
            ));
        }
        parts[i] = &rest[..n as usize];
        rest = &rest[n as usize..];
    }
    if !rest.is_empty() {
        return Err(format!("{} trailing bytes", rest.len()));
    }
    Ok(parts)
}

/// Reads only the header (cheap: no weights are built).
pub fn read_header(path: &Path) -> Result<TrainedHeader, TrainedError> {
    let bytes = std::fs::read(path).map_err(io(path))?;
    let format = |reason: String| TrainedError::Format {
        path: path.to_path_buf(),
        reason,
    };
    let [header, _, _] = split(&bytes).map_err(format)?;
    serde_json::from_slice(header).map_err(|e| format(format!("header: {e}")))
}

/// Loads a model file onto `device`.
pub fn load(path: &Path, device: &Device) -> Result<TrainedModel, TrainedError> {
    let bytes = std::fs::read(path).map_err(io(path))?;
    let format = |reason: String| TrainedError::Format {
        path: path.to_path_buf(),
        reason,
    };
    let [header, weights, payload] = split(&bytes).map_err(format)?;
    let header: TrainedHeader =
        serde_json::from_slice(header).map_err(|e| format(format!("header: {e}")))?;
    let config: ReconstructorConfig = serde_json::from_value(header.config.clone())
        .map_err(|e| format(format!("header config: {e}")))?;
    let model = config
        .init(header.num_vertices, device)
        .map_err(|e| TrainedError::Model {
            path: path.to_path_buf(),
            source: Box::new(e),
        })?;
    let record = ModuleRecord::from_bytes(Bytes::from_bytes_vec(weights.to_vec()))
        .map_err(|e| format(format!("weights: {e}")))?;
    let model = model
        .try_load_record(record)
        .map_err(|e| TrainedError::Weights {
            path: path.to_path_buf(),
            reason: e.to_string(),
        })?;
    Ok(TrainedModel {
        model,
        config,
        header,
        payload: payload.to_vec(),
    })
}

#[cfg(test)]
mod tests {
    #![allow(deprecated)]
    use super::*;

    use lifegom_render::testing::read;

    fn tmp(name: &str) -> PathBuf {
        let dir = std::env::temp_dir().join(format!("lifegom-trained-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        dir.join(name)
    }

    #[test]
    fn round_trip_keeps_weights_config_and_payload() {
        let device = Device::ndarray();
        let config = ReconstructorConfig::tiny(2).with_iterations(2);
        let model = config.init(17, &device).unwrap();
        let path = tmp("model.lgck");
        save(
            &path,
            &model,
            &config,
            serde_json::json!({"step": 7}),
            b"optimizer",
        )
        .unwrap();
        let loaded = load(&path, &device).unwrap();
        assert_eq!(loaded.payload, b"optimizer");
        assert_eq!(loaded.header.meta["step"], 7);
        assert_eq!(loaded.config.iterations, 2);
        assert_eq!(
            read(loaded.model.vertex_embed.val()),
            read(model.vertex_embed.val())
        );
        assert_eq!(read_header(&path).unwrap().num_vertices, 17);
    }

    /// The demo model the README's main job loads: inference-only (no optimizer payload),
    /// within the size the repository allows, built for the low-res template, and its weights
    /// fit the network its header describes.
    #[test]
    fn the_shipped_demo_model_loads() {
        let path = PathBuf::from(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/../assets/demo/demo.lgck"
        ));
        let size = std::fs::metadata(&path).unwrap().len();
        assert!(size <= 25 << 20, "{size} bytes");
        let loaded = load(&path, &Device::ndarray()).unwrap();
        assert!(loaded.payload.is_empty());
        let template = lifegom_render::template::BodyTemplate::load(
            lifegom_render::template::lowres_template_path(),
        )
        .unwrap();
        assert_eq!(loaded.header.num_vertices, template.num_vertices());
        assert_eq!(loaded.config.iterations, 3);
        assert!(loaded.header.meta["step"].as_u64().unwrap() > 0);
    }

    #[test]
    fn damaged_files_are_errors_naming_the_file() {
        let device = Device::ndarray();
        let config = ReconstructorConfig::tiny(1).with_iterations(1);
        let model = config.init(5, &device).unwrap();
        let bytes = encode(&model, &config, serde_json::Value::Null, &[]).unwrap();
        let cases: [(&str, Vec<u8>); 4] = [
            ("empty", vec![]),
            ("magic", b"NOTACKPT00000000".to_vec()),
            ("truncated", bytes[..bytes.len() / 2].to_vec()),
            ("trailing", [bytes.clone(), vec![0]].concat()),
        ];
        for (name, data) in cases {
            let path = tmp(&format!("{name}.lgck"));
            std::fs::write(&path, data).unwrap();
            let err = load(&path, &device).unwrap_err().to_string();
            assert!(err.contains(&path.display().to_string()), "{name}: {err}");
        }
        let missing = tmp("missing.lgck");
        let err = load(&missing, &device).unwrap_err().to_string();
        assert!(err.contains("missing.lgck"), "{err}");
    }
}
