//! Shared setup of the command tests: the tiny synthetic split in a fresh folder.

#![allow(dead_code)] // Each test file uses its own subset.

use std::path::{Path, PathBuf};

use burn::tensor::Device;
use lifegom_cli::eval_run::EvalOptions;
use lifegom_data::config::ConfigFile;
use lifegom_data::dataset::DataConfig;
use lifegom_data::synth;
use lifegom_model::reconstructor::ReconstructorConfig;
use lifegom_model::trained;

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

/// The first validation person of the split `cfg` names (a subject folder).
pub fn first_val_subject(cfg: &ConfigFile) -> PathBuf {
    let (val_dir, _) = cfg.data.split_paths(lifegom_data::dataset::Split::Val);
    std::fs::read_dir(&val_dir)
        .unwrap()
        .map(|e| e.unwrap().path())
        .find(|p| p.is_dir())
        .unwrap_or_else(|| panic!("no subject folder in {}", val_dir.display()))
}

/// An untrained tiny model for the low-res template (T = `iterations`, tested at `subdivide`
/// levels), saved as `dir/model.lgck`: it stands in for a checkpoint where a test is about
/// files and errors, not accuracy.
pub fn untrained_tiny_model(dir: &Path, iterations: usize, subdivide: u32) -> PathBuf {
    #[allow(deprecated)] // Device::ndarray(): the CI backend (design.md §1.4).
    let device = Device::ndarray();
    let config = ReconstructorConfig::tiny(3)
        .with_iterations(iterations)
        .with_subdivide_test(subdivide);
    let model = config.init(1229, &device).unwrap();
    let path = dir.join("model.lgck");
    trained::save(&path, &model, &config, serde_json::json!({"step": 0}), &[]).unwrap();
    path
}

/// `lifegom-eval`'s options for `checkpoint` on `data` (ndarray, the CI backend), writing to
/// `out`, with every extra output off and no perceptual weights (`tmp/no-weights`): a test
/// turns on what it is about.
pub fn eval_options(
    data: &DataConfig,
    checkpoint: PathBuf,
    out: PathBuf,
    tmp: &Path,
) -> EvalOptions {
    #[allow(deprecated)] // Device::ndarray(): the CI backend (design.md §1.4).
    let device = Device::ndarray();
    EvalOptions {
        data: data.clone(),
        checkpoint,
        official_network: ReconstructorConfig::tiny(2),
        out,
        device,
        subdivide: None,
        iterations: None,
        sheets: 0,
        freeview_frames: 0,
        motions: vec![],
        sweep: false,
        sweep_sizes: vec![],
        sweep_subjects: None,
        baseline: false,
        other_models: vec![],
        per_scene: vec![],
        per_scene_subjects: None,
        max_subjects: None,
        refine_steps: 0,
        weights_dir: tmp.join("no-weights"),
        context: vec!["test".into()],
        feedback_steps: false,
    }
}
