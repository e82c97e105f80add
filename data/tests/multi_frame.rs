//! The multi-frame (AIST++-style) synthetic split, `configs/synthetic-multiframe-tiny.toml`,
//! read back under the AIST++ rules: one camera per training sequence, a pose per frame,
//! validation targets in other poses and views, white backgrounds, and config mistakes that
//! are one error naming the file and field.

use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use lifegom_data::config::ConfigFile;
use lifegom_data::dataset::{Background, Dataset, Protocol, Split};
use lifegom_data::synth::{self, SynthSetting};
use lifegom_render::rng::Rng;

fn config_path() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../configs/synthetic-multiframe-tiny.toml")
}

fn tiny_config() -> ConfigFile {
    ConfigFile::load(&config_path()).unwrap()
}

/// The tiny multi-frame split, generated once per test binary.
fn tiny_split() -> &'static Path {
    static DIR: OnceLock<PathBuf> = OnceLock::new();
    DIR.get_or_init(|| {
        let dir = std::env::temp_dir().join(format!("lifegom-synth-mf-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        let cfg = tiny_config();
        let s = cfg.synthetic.clone().unwrap();
        let summary = synth::generate_split(&s, &cfg.data, &dir, s.seed, &|| {}).unwrap();
        assert_eq!(summary.train, ["d01", "d02"]);
        assert_eq!(summary.val, ["d03_val"]);
        assert_eq!(summary.frames, 2 * 8 + 5 + 2);
        dir
    })
}

#[test]
fn a_multi_frame_split_reads_back_under_the_aistpp_rules() {
    let cfg = tiny_config().with_root(tiny_split());
    let s = cfg.synthetic.as_ref().unwrap();
    assert_eq!(s.setting, SynthSetting::MultiFrame);
    assert_eq!(cfg.data.protocol, Protocol::Aistpp);

    let train = Dataset::open(&cfg.data, Split::Train).unwrap();
    assert_eq!(train.subjects.len(), 2);
    // AIST++ training: every frame is a target once.
    assert_eq!(train.len(), 2 * 8);
    for subject in &train.subjects {
        assert_eq!(subject.frames.len(), 8);
        // One fixed camera ...
        assert!(subject.cameras.iter().all(|c| *c == subject.cameras[0]));
        // ... and a body that moves: poses and headings change from frame to frame.
        let infos = &subject.mesh_infos;
        assert!(infos.windows(2).all(|w| w[0].poses != w[1].poses));
        assert!(infos.iter().any(|i| i.rh != infos[0].rh) || s.max_turn_deg == 0.0);
        // The same person in every frame.
        assert!(
            infos
                .iter()
                .all(|i| i.tpose_joints == subject.canonical.joints)
        );
    }
    // Different people move differently.
    assert_ne!(
        train.subjects[0].mesh_infos[3].poses,
        train.subjects[1].mesh_infos[3].poses
    );
    let mut rng = Rng::new(4);
    let sample = train.sample(3, &mut rng).unwrap();
    assert_eq!(sample.frame_name, "scene_d01_frame_000003");
    assert_eq!(sample.views.len(), 6);
    let frames: Vec<&str> = sample.views.iter().map(|v| v.frame.as_str()).collect();
    assert!(!frames[..5].contains(&"frame_000003"), "{frames:?}");
    // White background, and the body in view without touching the border.
    assert_eq!(train.background, Background::Fixed([255, 255, 255]));
    assert_eq!(sample.bgcolor, [1.0; 3]);
    let [w, h] = cfg.data.img_size.map(|v| v as usize);
    for v in &sample.views {
        assert!(
            v.mask.iter().filter(|&&m| m > 0.5).count() > 100,
            "{}",
            v.frame
        );
        for x in 0..w {
            for y in [0, h - 1] {
                assert_eq!(v.mask[y * w + x], 0.0, "{} row {y}", v.frame);
                let px = &v.rgb[3 * (y * w + x)..3 * (y * w + x) + 3];
                assert!(px.iter().all(|c| (c - 1.0).abs() < 1e-3), "{px:?}");
            }
        }
    }

    let val = Dataset::open(&cfg.data, Split::Val).unwrap();
    assert_eq!((val.subjects.len(), val.len()), (1, 2));
    let subject = &val.subjects[0];
    assert_eq!(subject.name, "d03_val");
    assert_eq!(subject.frames.len(), 7);
    let idx = val.index(1, &mut rng).unwrap();
    assert_eq!((idx.inputs, idx.target), (vec![0, 1, 2, 3, 4], 6));
    // The inputs share the one camera; every target is seen from another one, in a pose no
    // input shows.
    let (inputs, targets) = subject.cameras.split_at(5);
    assert!(inputs.iter().all(|c| *c == inputs[0]));
    assert!(targets.iter().all(|c| *c != inputs[0]));
    for t in &subject.mesh_infos[5..] {
        assert!(subject.mesh_infos[..5].iter().all(|i| i.poses != t.poses));
    }
    assert_eq!(val.sample(0, &mut rng).unwrap().bgcolor, [1.0; 3]);

    // The split files the reader needs, and the free-view meta file.
    let root = tiny_split();
    let list = |f: &str| -> Vec<String> {
        serde_json::from_str(&std::fs::read_to_string(root.join(f)).unwrap()).unwrap()
    };
    assert_eq!(list("train.json"), ["d01", "d02"]);
    assert_eq!(list("val.json"), ["d03_val"]);
    assert!(root.join("view5_trainval_meta.json").is_file());
}

#[test]
fn generation_is_deterministic_per_seed() {
    let cfg = tiny_config();
    let s = cfg.synthetic.clone().unwrap();
    let template = lifegom_render::template::BodyTemplate::load(s.template.path()).unwrap();
    let a = synth::generate_subject(&template, &s, 7, 1, "x", None).unwrap();
    let b = synth::generate_subject(&template, &s, 7, 1, "x", None).unwrap();
    let c = synth::generate_subject(&template, &s, 8, 1, "x", None).unwrap();
    assert_eq!(a.frames.len(), 8);
    for (x, y) in a.frames.iter().zip(&b.frames) {
        assert!(x.rgb == y.rgb && x.mask == y.mask && x.body == y.body);
    }
    assert_ne!(a.frames[0].body, c.frames[0].body);
    // Only some frames: the same frames, rendered alone.
    let some =
        synth::generate_subject_frames(&template, &s, 7, 1, "x", None, Some(&[2, 6])).unwrap();
    assert_eq!(some.frames.len(), 2);
    assert!(some.frames[1].rgb == a.frames[6].rgb && some.frames[1].body == a.frames[6].body);
}

#[test]
fn multi_frame_config_mistakes_name_the_file_and_field() {
    let text = std::fs::read_to_string(config_path()).unwrap();
    for (from, to, needle) in [
        (
            "protocol = \"aistpp\"",
            "protocol = \"thuman_view5\"",
            "synthetic.setting",
        ),
        (
            "sequence_frames = 8",
            "sequence_frames = 5",
            "synthetic.sequence_frames",
        ),
        (
            "val_target_views = 2",
            "val_target_views = 0",
            "synthetic.val_target_views",
        ),
        (
            "max_turn_deg = 180.0",
            "max_turn_deg = -1.0",
            "synthetic.max_turn_deg",
        ),
        (
            "val_split = \"val.json\"",
            "val_split = \"train.json\"",
            "data.val_split",
        ),
        (
            "val_split = \"val.json\"",
            "val_split = \"val.json\"\nval_subjects = [\"d16_val\"]",
            "data.val_subjects",
        ),
        ("setting = \"multi_frame\"", "setting = \"multi\"", "multi"),
    ] {
        assert!(text.contains(from), "{from}");
        let bad = text.replace(from, to);
        let err = ConfigFile::parse(&bad, Path::new("mf.toml"))
            .unwrap_err()
            .to_string();
        assert!(
            err.contains("mf.toml") && err.contains(needle),
            "{needle}: {err}"
        );
    }
    // Listing the subjects the generator writes is fine, and then one split file may serve both.
    let listed = text.replace(
        "val_split = \"val.json\"",
        "val_split = \"train.json\"\nval_subjects = [\"d03_val\"]",
    );
    ConfigFile::parse(&listed, Path::new("mf.toml")).unwrap();
}
