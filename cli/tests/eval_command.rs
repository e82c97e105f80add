//! `lifegom-eval` end to end on the tiny synthetic split (tiny network, ndarray, 64 px): every
//! output file is written, LPIPS/FID say plainly that weights are missing, and the numbers in
//! the files agree with each other.

#![allow(deprecated)] // Device::ndarray(): ndarray is the CI backend the project requires (design.md §1.4).

mod common;

use burn::tensor::Device;
use lifegom_cli::eval_run::{EvalOptions, run};
use lifegom_eval::report::WEIGHTS_MISSING;

use common::{eval_options, tiny_split, untrained_tiny_model};

#[test]
fn eval_on_a_tiny_split_writes_every_file() {
    let (tmp, cfg) = tiny_split("eval-cmd", |_| {});

    // An untrained tiny model stands in for a checkpoint: this test is about the files.
    let ckpt = untrained_tiny_model(&tmp, 2, 1);

    let out = tmp.join("out");
    let outcome = run(&EvalOptions {
        sheets: 2,
        freeview_frames: 3,
        motions: lifegom_render::motion::MotionSource::all_procedural(),
        sweep: true,
        sweep_subjects: Some(1),
        baseline: true,
        per_scene: vec![1, 2],
        per_scene_subjects: Some(1),
        feedback_steps: true,
        ..eval_options(&cfg.data, ckpt, out.clone(), &tmp)
    })
    .unwrap();

    for file in [
        "per_view.csv",
        "per_subject.csv",
        "summary.json",
        "report.md",
        "freeview.gif",
        "motion_walk.gif",
        "motion_arm-raise.gif",
        "motion_squat.gif",
        "pareto.png",
        "freeview/frame_0002.png",
    ] {
        assert!(out.join(file).is_file(), "{file} missing");
    }
    let preds = std::fs::read_dir(out.join("preds")).unwrap().count();
    let sheets = std::fs::read_dir(out.join("sheets")).unwrap().count();
    assert_eq!(preds, outcome.summary.views);
    // At most one sheet per subject: the tiny split has one validation subject.
    assert_eq!(sheets, 1);
    // The tiny split has 1 validation subject with 3 targets.
    assert_eq!((outcome.summary.subjects, outcome.summary.views), (1, 3));
    assert!(outcome.summary.psnr.is_finite() && outcome.summary.psnr > 0.0);
    assert!(outcome.summary.recon_ms > 0.0 && outcome.summary.render_ms > 0.0);
    assert_eq!(outcome.summary.lpips_vgg_x1000, None);
    assert_eq!(outcome.summary.fid, None);
    let names: Vec<&str> = outcome.baselines.iter().map(|(n, _)| n.as_str()).collect();
    assert_eq!(names, ["template, one colour", "projective texturing"]);
    assert!(outcome.baselines.iter().all(|(_, b)| b.psnr.is_finite()));
    assert_eq!(outcome.sweep.len(), 15, "T 1..5 × subdivisions 0..2");
    let ks: Vec<usize> = outcome.per_scene.iter().map(|p| p.steps).collect();
    assert_eq!(ks, [1, 2]);
    assert!(
        outcome
            .per_scene
            .iter()
            .all(|p| p.psnr.is_finite() && p.ms > 0.0),
        "{:?}",
        outcome.per_scene
    );
    let gaussians: Vec<usize> = outcome
        .sweep
        .iter()
        .map(|r| r.summary.num_gaussians)
        .collect();
    assert!(
        gaussians[0] < gaussians[5] && gaussians[5] < gaussians[10],
        "{gaussians:?}"
    );

    let report = std::fs::read_to_string(out.join("report.md")).unwrap();
    assert!(report.contains(WEIGHTS_MISSING), "{report}");
    assert!(report.contains("template, one colour") && report.contains("projective texturing"));
    assert!(report.contains("What accuracy costs in time"));
    // Every method scored on the targets has a row of where its error sits.
    assert!(report.contains("## Where the error sits"), "{report}");
    assert!(
        report.contains("| per-scene optimisation, K = 2 |"),
        "{report}"
    );
    assert!(outcome.summary.regions.is_some());
    assert!(outcome.per_scene.iter().all(|p| p.regions.is_some()));
    // Every feedback step of the one reconstruction; its last is the model's own score.
    assert!(
        report.contains("Every feedback step") && report.contains("t = 2"),
        "{report}"
    );
    let summary_json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("summary.json")).unwrap()).unwrap();
    let steps = summary_json["feedback_steps"][0][1].as_array().unwrap();
    assert_eq!(steps.len(), 2);
    let last = steps[1]["psnr"].as_f64().unwrap();
    assert!(
        (last - outcome.summary.psnr).abs() < 1e-3,
        "{last} vs {}",
        outcome.summary.psnr
    );
    let summary: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("summary.json")).unwrap()).unwrap();
    assert!((summary["model"]["psnr"].as_f64().unwrap() - outcome.summary.psnr).abs() < 1e-9);
    assert!(summary["model"]["fid"].is_null());
    let per_view = std::fs::read_to_string(out.join("per_view.csv")).unwrap();
    assert_eq!(per_view.lines().count(), 1 + outcome.summary.views);
}

#[test]
fn feedback_steps_follow_the_iterations_override() {
    let (tmp, cfg) = tiny_split("eval-steps", |_| {});
    // Trained with T = 2, evaluated with T = 3: the shared update weights run a third step.
    let ckpt = untrained_tiny_model(&tmp, 2, 1);
    let out = tmp.join("out");
    let outcome = run(&EvalOptions {
        iterations: Some(3),
        feedback_steps: true,
        ..eval_options(&cfg.data, ckpt, out.clone(), &tmp)
    })
    .unwrap();
    let summary: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("summary.json")).unwrap()).unwrap();
    let steps = summary["feedback_steps"][0][1].as_array().unwrap();
    assert_eq!(steps.len(), 3, "{steps:?}");
    let last = steps[2]["psnr"].as_f64().unwrap();
    assert!(
        (last - outcome.summary.psnr).abs() < 1e-3,
        "{last} vs {}",
        outcome.summary.psnr
    );
}

#[test]
fn crop_size_scales_the_thuman_protocol() {
    use lifegom_eval::evaluate::thuman_crop_size;
    assert_eq!(thuman_crop_size(1024, 1024), [1000, 500]);
    assert_eq!(thuman_crop_size(512, 512), [500, 250]);
    assert_eq!(thuman_crop_size(256, 256), [250, 125]);
    assert_eq!(thuman_crop_size(64, 64), [63, 31]);
    assert_eq!(thuman_crop_size(10, 4), [10, 2]);
}

/// `--refine-steps`: gradient steps after the feed-forward pass fit the source views, so the
/// refined template scores better on the held-out targets than the template it starts from,
/// and its reconstruction time includes the fit.
#[test]
fn test_time_refinement_improves_the_template() {
    use lifegom_data::dataset::{Dataset, Split};
    use lifegom_eval::evaluate::{EvalSettings, Method, evaluate_split, mean_of};

    let (tmp, cfg) = tiny_split("refine", |_| {});
    let dataset = Dataset::open(&cfg.data, Split::Val).unwrap();
    let device = Device::flex();
    let score = |refine_steps| {
        let settings = EvalSettings {
            out: tmp.join("out"),
            subdivide: Some(1),
            iterations: None,
            save_predictions: false,
            sheets: 0,
            max_subjects: None,
            refine_steps,
        };
        let scores = evaluate_split(
            &Method::TemplateBaseline { subdivide: 1 },
            &dataset,
            &settings,
            &device,
        )
        .unwrap();
        // A view's error by region adds up to its MSE, so to its PSNR.
        for v in &scores.views {
            let total = v.regions.expect("the targets have masks").total();
            assert!(
                (-10.0 * total.log10() - v.psnr).abs() < 1e-9,
                "{}: {total} vs {} dB",
                v.frame_name,
                v.psnr
            );
        }
        (
            mean_of(&scores.views, |v| Some(v.psnr)).unwrap(),
            mean_of(&scores.views, |v| Some(v.recon_ms)).unwrap(),
        )
    };
    let (plain, plain_ms) = score(0);
    let (refined, refined_ms) = score(30);
    assert!(
        refined > plain + 0.5,
        "refined {refined:.2} dB vs template {plain:.2} dB"
    );
    assert!(refined_ms > plain_ms, "{refined_ms} ms vs {plain_ms} ms");
    let _ = std::fs::remove_dir_all(&tmp);
}

/// The capacity check on one tiny training subject: fitting 8 ring views lifts the views it
/// never saw above the projective-texturing start, writes the sheet, and a frame past the
/// subject's last is an error naming the subject's folder.
#[test]
fn capacity_check_fits_ring_views_and_scores_held_out_ones() {
    use lifegom_data::dataset::{Dataset, Split};
    use lifegom_eval::capacity::{ViewSplit, fit_one_subject};
    use lifegom_train::fit::FitConfig;
    use lifegom_train::losses::LossWeights;

    let (tmp, cfg) = tiny_split("capacity", |s| (s.train_subjects, s.val_subjects) = (1, 0));
    let mut dataset = Dataset::open(&cfg.data, Split::Train).unwrap();
    dataset.background = cfg.data.test_background;
    let device = Device::flex();
    let mut split = ViewSplit::ring(16, 8, dataset.subjects[0].frames.len());
    split.held_out.truncate(6);
    let run = |split: &ViewSplit| {
        fit_one_subject(
            &dataset,
            0,
            split,
            &[0, 40],
            0,
            &FitConfig::new(),
            &LossWeights::new(),
            &device,
        )
    };
    let result = run(&split).unwrap();
    let [start, fitted] = result.points[..] else {
        panic!("{:?}", result.points)
    };
    assert!(
        fitted.psnr_held_out > start.psnr_held_out + 1.0,
        "{start:?} → {fitted:?}"
    );
    assert!(fitted.psnr_sources > start.psnr_sources + 1.0);
    assert!(fitted.seconds > 0.0 && start.seconds == 0.0);
    assert!(result.sheet.is_some());

    split.held_out.push(999);
    let err = run(&split).err().unwrap().to_string();
    assert!(err.contains("frame 999") && err.contains("0000"), "{err}");
    let _ = std::fs::remove_dir_all(&tmp);
}
