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
//!
//! # Official checkpoints
//!
//! [`load_any`] also takes the official code's weights: a `torch.save` file (zip or legacy
//! pickle, the state dict bare or under `network`) or a `.safetensors` file, told apart from a
//! `.lgck` by its first bytes. Such a file holds weights only, so the network is the one the
//! caller's experiment config describes (`[model]` and the number of input views); its shapes
//! are checked against the file's, tensor by tensor, and a mismatch is one error naming the key
//! and both shapes, with the preset the file does match when it matches one
//! ([`crate::checkpoint`] has the key map).

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
    /// An official checkpoint that cannot be imported (the error names the file and the key).
    #[error("{import}{hint}")]
    Official {
        /// The importer's error (its text is this error's; not repeated as a cause).
        import: Box<crate::checkpoint::CheckpointError>,
        /// What the file's shapes do describe, when that helps (empty otherwise).
        hint: String,
    },
    /// The model was trained for another body template: its per-vertex embedding has one row
    /// per vertex of that template.
    #[error(
        "{path}: `{key}` has shape {file:?}, one row per vertex of the body template the model \
         was trained with, but this template has {template_vertices} low-res vertices (needs \
         {needed:?}); use the template the model was trained on (the demo model: the low-res Anny \
         template)"
    )]
    Template {
        /// The file.
        path: PathBuf,
        /// The embedding's key as the file names it.
        key: &'static str,
        /// Its shape in the file.
        file: Vec<usize>,
        /// The shape this template needs.
        needed: Vec<usize>,
        /// Low-res vertices of the template.
        template_vertices: usize,
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

/// Where a loaded model's weights came from.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ModelFileKind {
    /// A lifegom trained-model file (`.lgck`).
    Lifegom,
    /// An official LIFe-GoM checkpoint, in this container format.
    Official(crate::weights_file::WeightsFormat),
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
    /// What kind of file it was.
    pub kind: ModelFileKind,
}

impl TrainedModel {
    /// One phrase for reports: `step 7000` for a lifegom model, `official PyTorch checkpoint`
    /// for an imported one.
    pub fn provenance(&self) -> String {
        match self.kind {
            ModelFileKind::Official(format) => format!("official {format} checkpoint"),
            ModelFileKind::Lifegom => match self.header.meta["step"].as_u64() {
                Some(step) => format!("step {step}"),
                None => "step unknown".into(),
            },
        }
    }

    /// Checks that the model's per-vertex embedding fits a template of `template_vertices`
    /// low-res vertices; `path` is the file the model came from.
    pub fn check_template(
        &self,
        path: &Path,
        template_vertices: usize,
    ) -> Result<(), TrainedError> {
        let [rows, width] = self.model.vertex_embed.dims();
        if rows == template_vertices {
            return Ok(());
        }
        Err(TrainedError::Template {
            path: path.to_path_buf(),
            key: match self.kind {
                ModelFileKind::Lifegom => "vertex_embed",
                ModelFileKind::Official(_) => crate::checkpoint::VERTEX_EMBED_KEY,
            },
            file: vec![rows, width],
            needed: vec![template_vertices, width],
            template_vertices,
        })
    }

    /// Whether this model's network has the architecture of `config` (what the weights'
    /// shapes depend on; feedback steps, subdivisions and dropout may differ).
    pub fn same_architecture(&self, config: &ReconstructorConfig) -> bool {
        architecture(&self.config) == architecture(config)
    }
}

/// The parts of a config the weights' shapes depend on, as JSON (the config types derive no
/// equality).
fn architecture(config: &ReconstructorConfig) -> serde_json::Value {
    serde_json::json!({
        "encoder": serde_json::from_str::<serde_json::Value>(&config.encoder.to_string()).ok(),
        "point_transformer":
            serde_json::from_str::<serde_json::Value>(&config.point_transformer.to_string()).ok(),
        "num_views": config.num_views,
        "n_heads": config.n_heads,
    })
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
        kind: ModelFileKind::Lifegom,
    })
}

/// Whether the file at `path` is a lifegom trained-model file (by its magic, not its name).
pub fn is_lifegom_file(path: &Path) -> Result<bool, TrainedError> {
    use std::io::Read;
    let mut head = Vec::with_capacity(MAGIC.len());
    std::fs::File::open(path)
        .and_then(|f| f.take(MAGIC.len() as u64).read_to_end(&mut head))
        .map_err(io(path))?;
    Ok(head == MAGIC)
}

/// Loads a `.lgck` ([`load`]) or an official checkpoint (module docs), told apart by content.
/// `official` is the network an official file's weights are loaded into (the experiment's
/// `[model]` for its number of views); a `.lgck` carries its own config and ignores it.
pub fn load_any(
    path: &Path,
    official: &ReconstructorConfig,
    device: &Device,
) -> Result<TrainedModel, TrainedError> {
    if is_lifegom_file(path)? {
        return load(path, device);
    }
    let _span = tracing::info_span!("import_official", path = %path.display()).entered();
    let official_err =
        |e: crate::checkpoint::CheckpointError, hint: String| TrainedError::Official {
            import: Box::new(e),
            hint,
        };
    let shapes = crate::checkpoint::read_official_shapes(path)
        .map_err(|e| official_err(e, String::new()))?;
    // The embedding has one row per vertex of the template the weights were trained with; the
    // caller checks that against its template ([`TrainedModel::check_template`]).
    let Some(&[rows, _]) = shapes
        .get(crate::checkpoint::VERTEX_EMBED_KEY)
        .map(Vec::as_slice)
    else {
        return Err(official_err(
            crate::checkpoint::CheckpointError::Missing {
                path: path.to_path_buf(),
                keys: vec![crate::checkpoint::VERTEX_EMBED_KEY.into()],
            },
            String::new(),
        ));
    };
    let model = official
        .init(rows, device)
        .map_err(|e| TrainedError::Model {
            path: path.to_path_buf(),
            source: Box::new(e),
        })?;
    let (model, report) =
        crate::checkpoint::load_official_checkpoint(model, path).map_err(|e| {
            let hint = match &e {
                crate::checkpoint::CheckpointError::Shape { .. }
                | crate::checkpoint::CheckpointError::Missing { .. }
                | crate::checkpoint::CheckpointError::Unexpected { .. } => {
                    described_preset_hint(&shapes, rows, official, device)
                }
                _ => String::new(),
            };
            official_err(e, hint)
        })?;
    let header = TrainedHeader {
        config: serde_json::from_str(&official.to_string()).map_err(|e| TrainedError::Format {
            path: path.to_path_buf(),
            reason: format!("config: {e}"),
        })?,
        num_vertices: rows,
        meta: serde_json::json!({
            "source": "official LIFe-GoM checkpoint",
            "file": path.display().to_string(),
            "format": report.format.to_string(),
            "tensors": report.applied.len(),
        }),
    };
    Ok(TrainedModel {
        model,
        config: official.clone(),
        header,
        payload: Vec::new(),
        kind: ModelFileKind::Official(report.format),
    })
}

/// A preset's constructor, taking the number of views.
type PresetFn = fn(usize) -> ReconstructorConfig;

/// The presets a state dict is compared with when it does not fit the asked network.
const PRESETS: [(&str, PresetFn); 3] = [
    ("paper", ReconstructorConfig::paper),
    ("cpu", ReconstructorConfig::cpu),
    ("tiny", ReconstructorConfig::tiny),
];

/// Views a described preset is looked for with.
const MAX_DESCRIBED_VIEWS: usize = 8;

/// `"; the file holds the `[model] preset = "tiny"` network for 3 views"` when the file's
/// shapes are exactly one preset's, else empty. Parameters are drawn lazily, so building the
/// candidates allocates no weights.
fn described_preset_hint(
    shapes: &std::collections::BTreeMap<String, Vec<usize>>,
    rows: usize,
    asked: &ReconstructorConfig,
    device: &Device,
) -> String {
    for (name, preset) in PRESETS {
        for views in 1..=MAX_DESCRIBED_VIEWS {
            let Ok(model) = preset(views).init(rows, device) else {
                continue;
            };
            let Ok(names) = crate::checkpoint::official_key_names(&model) else {
                continue;
            };
            let fits = names
                .iter()
                .all(|t| shapes.get(&t.key).is_some_and(|s| *s == t.shape))
                && shapes
                    .keys()
                    .filter(|k| !crate::checkpoint::is_ignorable_buffer(k))
                    .count()
                    == names.len();
            if fits {
                return format!(
                    "; the file holds the `[model] preset = \"{name}\"` network for {views} input \
                     views (`[data] n_input_frames = {views}`), not the config's network ({} views)",
                    asked.num_views
                );
            }
        }
    }
    "; the file matches none of the presets (paper, cpu, tiny) for 1 to 8 views".into()
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

    /// The same weights as a `.lgck` and as an official-format SafeTensors file load into the
    /// same network; a file that does not fit the asked network is one error naming a key, both
    /// shapes and the preset the file does hold; a template of another size is refused.
    #[test]
    fn official_files_load_like_lifegom_files_and_mismatches_name_key_and_shapes() {
        let device = Device::ndarray();
        let config = ReconstructorConfig::tiny(3).with_iterations(2);
        let model = config.init(23, &device).unwrap();
        let lgck = tmp("same.lgck");
        save(&lgck, &model, &config, serde_json::json!({"step": 3}), &[]).unwrap();
        let official = tmp("same.safetensors");
        crate::checkpoint::save_official_safetensors(&model, &official).unwrap();

        let a = load_any(&lgck, &ReconstructorConfig::paper(3), &device).unwrap();
        let b = load_any(&official, &config, &device).unwrap();
        assert_eq!(a.kind, ModelFileKind::Lifegom);
        assert_eq!(
            b.kind,
            ModelFileKind::Official(crate::weights_file::WeightsFormat::SafeTensors)
        );
        assert_eq!(b.header.num_vertices, 23);
        assert!(a.same_architecture(&b.config));
        assert_eq!(a.provenance(), "step 3");
        assert_eq!(b.provenance(), "official SafeTensors checkpoint");
        let values = |m: &Reconstructor| -> Vec<Vec<f32>> {
            use burn::store::ModuleSnapshot;
            m.collect(None, None, true)
                .iter()
                .map(|t| {
                    let data = burn::store::bridge::to_data(t).unwrap();
                    data.convert::<f32>().to_vec().unwrap()
                })
                .collect()
        };
        let (va, vb) = (values(&a.model), values(&b.model));
        assert_eq!(va.len(), vb.len());
        assert!(va == vb, "every tensor equal");

        // Asked for 2 views: the heads' input widths differ.
        let err = load_any(&official, &ReconstructorConfig::tiny(2), &device)
            .unwrap_err()
            .to_string();
        assert!(err.contains("same.safetensors"), "{err}");
        assert!(
            err.contains("`reconstructor.so3_update_layer.0.weight`: model needs [32, 312], file has [32, 456]"),
            "{err}"
        );
        assert!(
            err.contains("preset = \"tiny\"` network for 3 input"),
            "{err}"
        );

        let err = b.check_template(&official, 1229).unwrap_err().to_string();
        assert!(
            err.contains("`reconstructor.vertex_embed` has shape [23, "),
            "{err}"
        );
        assert!(err.contains("needs [1229, "), "{err}");
        assert!(a.check_template(&lgck, 23).is_ok());
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
