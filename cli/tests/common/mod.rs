//! Shared setup of the command tests: the tiny synthetic split in a fresh folder.

#![allow(dead_code)] // Each test file uses its own subset.

use std::path::PathBuf;

use lifegom_data::config::ConfigFile;
use lifegom_data::synth;

/// A fresh folder `lifegom-<tag>-<pid>` holding the tiny synthetic split (`tweak` may change
/// its `[synthetic]` section first), and the config pointed at it.
pub fn tiny_split(tag: &str, tweak: impl FnOnce(&mut synth::SynthConfig)) -> (PathBuf, ConfigFile) {
    let tmp = std::env::temp_dir().join(format!("lifegom-{tag}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&tmp);
    let config = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../configs/synthetic-tiny.toml");
    let root = tmp.join("data");
    let cfg = ConfigFile::load(&config).unwrap().with_root(&root);
    let mut s = cfg.synthetic.clone().unwrap();
    tweak(&mut s);
    synth::generate_split(&s, &cfg.data, &root, s.seed, &|| {}).unwrap();
    (tmp, cfg)
}
