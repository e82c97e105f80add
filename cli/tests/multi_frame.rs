//! The multi-frame setting end to end (`configs/synthetic-multiframe-tiny.toml`): generate an
//! AIST++-style split, train a few steps with the real training entry point (AIST++ losses,
//! SSIM standing in for LPIPS), evaluate with the real evaluation entry point under the AIST++
//! protocol (full images over white), and animate the avatar with a procedural motion and a
//! pose-sequence file.

#![allow(deprecated)] // Device::ndarray(): ndarray is the CI backend the project requires (design.md §1.4).

mod common;

use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::AtomicBool;

use burn::tensor::Device;
use lifegom_cli::eval_run::{EvalOptions, run};
use lifegom_cli::reconstruct_run::Capture;
use lifegom_cli::train_run::{RunOptions, StopReason, train};
use lifegom_data::dataset::{Dataset, Protocol, Split};
use lifegom_data::synth;
use lifegom_eval::images::Image;
use lifegom_render::motion::{JointRoles, Motion, MotionSource, PoseSequence};
use lifegom_render::rng::Rng;
use lifegom_train::config::ExperimentConfig;

#[test]
fn multi_frame_split_trains_and_evaluates_under_the_aistpp_protocol() {
    let tmp = std::env::temp_dir().join(format!("lifegom-multi-frame-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&tmp);
    let config =
        PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../configs/synthetic-multiframe-tiny.toml");
    let root = tmp.join("data");
    let cfg = ExperimentConfig::load(&config).unwrap().with_root(&root);
    assert_eq!(cfg.file.data.protocol, Protocol::Aistpp);
    let s = cfg.file.synthetic.clone().unwrap();
    synth::generate_split(&s, &cfg.file.data, &root, s.seed, &|| {}).unwrap();
    // Its validation people are frames of one camera: `lifegom-reconstruct` picks the
    // multi-frame model for them.
    let person = common::first_val_subject(&cfg.file);
    let person =
        lifegom_data::format::Subject::load(&person, cfg.file.data.kinematic_tree).unwrap();
    assert_eq!(Capture::of(&person), Capture::OneCamera);

    // Train: the AIST++ weights (no mask term) with 1 - SSIM at the LPIPS weight.
    let run_dir = tmp.join("run");
    let summary = train(
        &cfg,
        &RunOptions {
            out: run_dir.clone(),
            resume: false,
            init: None,
            max_minutes: None,
            steps: Some(3),
            device: Device::ndarray(),
            progress: false,
        },
        Arc::new(AtomicBool::new(false)),
    )
    .unwrap();
    assert_eq!((summary.step, summary.stop), (3, StopReason::Finished));
    assert!(summary.checkpoint.is_file());
    let lines: Vec<serde_json::Value> = std::fs::read_to_string(run_dir.join("metrics.jsonl"))
        .unwrap()
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    assert_eq!(lines.len(), 3);
    for line in &lines {
        for term in ["total", "rgb", "ssim", "laplacian", "psnr_target"] {
            assert!(line[term].as_f64().unwrap().is_finite(), "{term}: {line}");
        }
        // The sample is a frame of a training sequence; mask weight 0, no LPIPS term.
        assert!(line["sample"].as_str().unwrap().starts_with("scene_d0"));
        assert!(
            line.get("mask").is_none() && line.get("lpips").is_none(),
            "{line}"
        );
    }

    // Motions: a procedural one, a file, an SMPL file (retargeted to the Anny rig), and a file
    // for a rig nothing maps to (skipped, not fatal).
    let roles = JointRoles::for_rig(104).unwrap();
    let file = tmp.join("motions").join("wave.json");
    PoseSequence::from_motion(Motion::ArmRaise, &roles, 104, 3, 10.0)
        .save(&file)
        .unwrap();
    let smpl = tmp.join("motions").join("smpl.json");
    let smpl_roles = JointRoles::for_rig(24).unwrap();
    PoseSequence::from_motion(Motion::Squat, &smpl_roles, 24, 2, 10.0)
        .save(&smpl)
        .unwrap();
    let wrong_rig = tmp.join("motions").join("odd.json");
    PoseSequence {
        source: wrong_rig.clone(),
        fps: 10.0,
        joint_names: None,
        poses: vec![lifegom_render::skeleton::BodyPose::rest(30); 2],
        root_translations: None,
    }
    .save(&wrong_rig)
    .unwrap();
    let motions: Vec<MotionSource> = [
        "walk",
        file.to_str().unwrap(),
        smpl.to_str().unwrap(),
        wrong_rig.to_str().unwrap(),
    ]
    .iter()
    .map(|m| m.parse().unwrap())
    .collect();

    let out = tmp.join("eval");
    let outcome = run(&EvalOptions {
        official_network: cfg.reconstructor(),
        sheets: 1,
        freeview_frames: 2,
        motions,
        sweep_subjects: Some(1),
        baseline: true,
        ..common::eval_options(
            &cfg.file.data,
            summary.checkpoint.clone(),
            out.clone(),
            &tmp,
        )
    })
    .unwrap();
    // One validation sequence: frames 0-4 are the inputs, its 2 targets are scored.
    assert_eq!((outcome.summary.subjects, outcome.summary.views), (1, 2));
    assert!(outcome.summary.psnr.is_finite() && outcome.summary.psnr > 0.0);
    assert!(outcome.summary.ssim.is_finite());
    assert!(outcome.baselines.iter().all(|(_, b)| b.psnr.is_finite()));
    for f in [
        "per_view.csv",
        "summary.json",
        "report.md",
        "freeview.gif",
        "motion_walk.gif",
        "motion_wave.gif",
        "motion/walk/poses.json",
        "motion/wave/poses.json",
        "motion/wave/frame_0002.png",
    ] {
        assert!(out.join(f).is_file(), "{f} missing");
    }
    assert!(!out.join("motion/wave/frame_0003.png").exists());
    assert!(
        out.join("motion_smpl.gif").is_file(),
        "an SMPL motion is retargeted to the Anny rig"
    );
    assert!(
        !out.join("motion_odd.gif").exists(),
        "a 30-joint motion on a 104-joint rig"
    );
    // What the evaluation wrote is what it played: the file reads back as the same poses.
    let played = PoseSequence::load(out.join("motion/wave/poses.json")).unwrap();
    assert_eq!(played.poses(), PoseSequence::load(&file).unwrap().poses());
    // A procedural motion is written with the rig's joint names, ready to edit by name.
    let walk = PoseSequence::load(out.join("motion/walk/poses.json")).unwrap();
    let names = walk.joint_names.unwrap();
    assert_eq!(names.len(), 104);
    assert!(names.iter().any(|n| n == "upperarm01.L"));

    // The AIST++ protocol scores the full image over white: the PSNR of a saved prediction
    // against the full, quantised ground truth is the one reported.
    let val = Dataset::open(&cfg.file.data, Split::Val).unwrap();
    assert_eq!(val.background, cfg.file.data.test_background);
    let per_view = std::fs::read_to_string(out.join("per_view.csv")).unwrap();
    let mut rng = Rng::new(0);
    for (i, row) in per_view.lines().skip(1).enumerate() {
        let cols: Vec<&str> = row.split(',').collect();
        let sample = val.sample(i, &mut rng).unwrap();
        assert_eq!(cols[1], sample.frame_name);
        let target = sample.views.last().unwrap();
        let [w, h] = cfg.file.data.img_size.map(|v| v as usize);
        let gt = Image {
            width: w,
            height: h,
            data: target.rgb.clone(),
        }
        .quantized();
        let pred = Image::load(&out.join("preds").join(format!("{}.png", cols[1]))).unwrap();
        assert_eq!((pred.width, pred.height), (w, h));
        let mse = pred
            .data
            .iter()
            .zip(&gt.data)
            .map(|(a, b)| f64::from(a - b).powi(2))
            .sum::<f64>()
            / gt.data.len() as f64;
        let psnr = -10.0 * mse.log10();
        let reported: f64 = cols[2].parse().unwrap();
        assert!((psnr - reported).abs() < 1e-2, "{psnr} vs {reported}");
    }
    let _ = std::fs::remove_dir_all(&tmp);
}
