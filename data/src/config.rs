//! Experiment config files (`configs/*.toml`): this crate reads the `[data]` section and, for
//! the synthetic generator, `[synthetic]`. Other sections (`[model]`, `[train]`, ...) belong to
//! other crates and are ignored here, so one file describes a whole experiment.
//!
//! Data paths are relative to the working directory; [`ConfigFile::with_root`] overrides the
//! dataset root from the command line.

use std::path::{Path, PathBuf};

use serde::Deserialize;

use crate::dataset::DataConfig;
use crate::error::{DataError, Location, Result};
use crate::synth::SynthConfig;

/// The sections of a config file this crate reads.
#[derive(Debug, Clone, PartialEq, Deserialize)]
pub struct ConfigFile {
    /// `[data]`.
    pub data: DataConfig,
    /// `[synthetic]`, only in synthetic-data configs.
    #[serde(default)]
    pub synthetic: Option<SynthConfig>,
    /// Where it was read from (for messages).
    #[serde(skip)]
    pub source: PathBuf,
}

impl ConfigFile {
    /// Reads and validates a config file.
    pub fn load(path: &Path) -> Result<Self> {
        let text =
            std::fs::read_to_string(path).map_err(|e| DataError::io(Location::file(path), e))?;
        Self::parse(&text, path)
    }

    /// Parses config text; `source` names it in errors.
    pub fn parse(text: &str, source: &Path) -> Result<Self> {
        let mut cfg: Self = toml::from_str(text).map_err(|e| DataError::Config {
            location: Box::new(Location::file(source)),
            reason: e.to_string(),
        })?;
        cfg.source = source.to_path_buf();
        cfg.data.validate(source)?;
        if let Some(s) = &cfg.synthetic {
            s.validate(&cfg.data, source)?;
        }
        Ok(cfg)
    }

    /// The same config with the dataset root replaced (a command-line override).
    pub fn with_root(mut self, root: impl Into<PathBuf>) -> Self {
        self.data.root = root.into();
        self
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::dataset::{Background, Protocol};
    use crate::kinematics::KinematicTree;

    fn configs_dir() -> PathBuf {
        PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../configs")
    }

    #[test]
    fn every_shipped_config_parses() {
        let mut n = 0;
        for entry in std::fs::read_dir(configs_dir()).unwrap() {
            let path = entry.unwrap().path();
            if path.extension().is_some_and(|e| e == "toml") {
                ConfigFile::load(&path).unwrap_or_else(|e| panic!("{e}"));
                n += 1;
            }
        }
        assert!(n >= 6, "{n} configs");
        let v3 = ConfigFile::load(&configs_dir().join("thuman2.0-view3.toml")).unwrap();
        assert_eq!(v3.data.protocol, Protocol::ThumanView3);
        assert_eq!(v3.data.kinematic_tree, KinematicTree::Smplx);
        assert_eq!(v3.data.img_size, [1024, 1024]);
        assert_eq!(v3.data.train_background, Background::Random);
        assert_eq!(v3.data.test_background, Background::Fixed([0, 0, 0]));
        let a = ConfigFile::load(&configs_dir().join("aistpp-view5.toml")).unwrap();
        assert_eq!((a.data.n_input_frames, a.data.img_size), (5, [960, 540]));
        assert_eq!(a.data.kinematic_tree, KinematicTree::Smpl);
        assert_eq!(a.with_root("/x").data.root, PathBuf::from("/x"));
    }

    #[test]
    fn bad_configs_name_the_file_and_key() {
        let text = std::fs::read_to_string(configs_dir().join("synthetic-tiny.toml")).unwrap();
        let bad = text.replace("img_size = [64, 64]", "img_size = [0, 64]");
        let e = ConfigFile::parse(&bad, Path::new("tiny.toml"))
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("tiny.toml") && e.contains("data.img_size"),
            "{e}"
        );
        // Sizes are checked before anything is allocated.
        let huge = text.replace("img_size = [64, 64]", "img_size = [100000, 64]");
        let e = ConfigFile::parse(&huge, Path::new("tiny.toml"))
            .unwrap_err()
            .to_string();
        for part in ["tiny.toml", "data.img_size", "at most 8192", "[100000, 64]"] {
            assert!(e.contains(part), "`{e}` lacks `{part}`");
        }
        let huge = text.replace("image_size = 64", "image_size = 100000");
        let e = ConfigFile::parse(&huge, Path::new("tiny.toml"))
            .unwrap_err()
            .to_string();
        for part in ["synthetic.image_size", "at most 8192", "100000"] {
            assert!(e.contains(part), "`{e}` lacks `{part}`");
        }
        let e = ConfigFile::parse("[data]\nroot = 3\n", Path::new("x.toml"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("x.toml"), "{e}");
    }
}
