//! End-to-end training tests on the tiny synthetic split (tiny network, ndarray, 64 px):
//! the loss goes down on a fixed batch, a resumed run equals an uninterrupted one, Ctrl-C-style
//! stops leave a loadable checkpoint, and bad checkpoints are clear errors.

#![allow(deprecated)] // Device::ndarray(): ndarray is the CI backend the project requires (design.md §1.4).

use std::path::{Path, PathBuf};
use std::sync::atomic::AtomicBool;
use std::sync::{Arc, Mutex, MutexGuard, OnceLock};

use burn::tensor::Device;
use lifegom_cli::train_run::{RunOptions, StopReason, train};
use lifegom_data::config::ConfigFile;
use lifegom_data::dataset::{Dataset, Split};
use lifegom_data::synth;
use lifegom_model::inputs::{SubjectRig, model_inputs};
use lifegom_model::reconstructor::MeshPurpose;
use lifegom_train::config::ExperimentConfig;
use lifegom_train::data_parallel::{BatchLayout, weights_checksum};
use lifegom_train::losses::UniformLaplacian;
use lifegom_train::prefetch::Prefetcher;
use lifegom_train::trainer::{Trainer, sample_for_step};

fn config_path() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../configs/synthetic-tiny.toml")
}

/// The tiny split, generated once per test binary.
fn data_root() -> &'static Path {
    static ROOT: OnceLock<PathBuf> = OnceLock::new();
    ROOT.get_or_init(|| {
        let root = std::env::temp_dir().join(format!("lifegom-train-data-{}", std::process::id()));
        let cfg = ConfigFile::load(&config_path()).unwrap().with_root(&root);
        let s = cfg.synthetic.clone().unwrap();
        synth::generate_split(&s, &cfg.data, &root, s.seed, &|| {}).unwrap();
        root
    })
}

/// Burn's RNG is process-wide and these tests compare seeded runs: one test at a time.
fn serial() -> MutexGuard<'static, ()> {
    static LOCK: Mutex<()> = Mutex::new(());
    LOCK.lock().unwrap_or_else(|e| e.into_inner())
}

fn experiment() -> ExperimentConfig {
    ExperimentConfig::load(&config_path())
        .unwrap()
        .with_root(data_root())
}

fn out_dir(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("lifegom-train-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    dir
}

/// A run of `steps` steps on ndarray into `out`, without progress output.
fn run_options(out: PathBuf, steps: u64, resume: bool) -> RunOptions {
    RunOptions {
        out,
        resume,
        init: None,
        max_minutes: None,
        steps: Some(steps),
        device: Device::ndarray(),
        progress: false,
    }
}

/// A stop flag that is never raised.
fn never() -> Arc<AtomicBool> {
    Arc::new(AtomicBool::new(false))
}

fn total(stats: &lifegom_train::trainer::StepStats) -> f64 {
    stats.losses.iter().find(|(n, _)| n == "total").unwrap().1
}

/// A fresh T = 1 trainer (on ndarray, `train`'s settings) and the inputs of the first sample of
/// the seed-7 schedule, at 64 px.
struct OneSample {
    trainer: Trainer,
    mesh: lifegom_render::gom::GomMesh,
    lap: UniformLaplacian,
    inputs: lifegom_model::inputs::ModelInputs,
}

fn one_sample(train: &lifegom_train::config::TrainSection) -> OneSample {
    let cfg = experiment();
    let data = Dataset::open(&cfg.file.data, Split::Train).unwrap();
    let bodies = SubjectRig::for_split(&data).unwrap();
    let trainer = Trainer::new(
        cfg.reconstructor().with_iterations(1),
        bodies[0].num_vertices(),
        train,
        &Device::ndarray(),
    )
    .unwrap();
    let mesh = trainer
        .config
        .mesh(&bodies[0].topology, MeshPurpose::Training, trainer.device())
        .unwrap();
    let lap = UniformLaplacian::new(&bodies[0].topology.faces, bodies[0].num_vertices()).unwrap();
    let sample = sample_for_step(&data, 7, 0).unwrap();
    let body = bodies.iter().find(|b| b.name == sample.subject).unwrap();
    let inputs = model_inputs(body, &sample, 64, 64, trainer.device()).unwrap();
    OneSample {
        trainer,
        mesh,
        lap,
        inputs,
    }
}

#[test]
fn a_few_steps_lower_the_loss_on_a_fixed_batch() {
    let _serial = serial();
    let mut section = experiment().train;
    section.lr_reconstructor = 1e-3;
    section.lr_encoder = 1e-3;
    let OneSample {
        mut trainer,
        mesh,
        lap,
        inputs,
    } = one_sample(&section);
    let losses: Vec<f64> = (0..6)
        .map(|_| total(&trainer.train_step(&inputs, &mesh, &lap).unwrap()))
        .collect();
    assert!(losses.iter().all(|l| l.is_finite()), "{losses:?}");
    // Every step lowers the loss, and six of them by at least 5 %. (The sample and the dropout
    // masks come from the seeded schedule; with the schedule of version 2 the drop is 9 %.)
    assert!(
        losses.windows(2).all(|w| w[1] < w[0]),
        "each Adam step on one sample should lower its loss: {losses:?}"
    );
    assert!(
        losses[5] < 0.95 * losses[0],
        "6 Adam steps on one sample should lower its loss by 5 %: {losses:?}"
    );
    assert_eq!(trainer.step, 6);
}

fn logged_totals(out: &Path) -> Vec<(u64, f64)> {
    std::fs::read_to_string(out.join("metrics.jsonl"))
        .unwrap()
        .lines()
        .map(|l| {
            let v: serde_json::Value = serde_json::from_str(l).unwrap();
            (v["step"].as_u64().unwrap(), v["total"].as_f64().unwrap())
        })
        .collect()
}

#[test]
fn resume_equals_an_uninterrupted_run() {
    let _serial = serial();
    let cfg = experiment();
    let opts = run_options;

    let straight = out_dir("straight");
    let full = train(&cfg, &opts(straight.clone(), 4, false), never()).unwrap();
    assert_eq!((full.step, full.stop), (4, StopReason::Finished));

    let split = out_dir("split");
    let first = train(&cfg, &opts(split.clone(), 2, false), never()).unwrap();
    assert_eq!(first.step, 2);
    let second = train(&cfg, &opts(split.clone(), 4, true), never()).unwrap();
    assert_eq!((second.step, second.steps_this_run), (4, 2));

    let a = logged_totals(&straight);
    let b = logged_totals(&split);
    assert_eq!(a.len(), 4, "{a:?}");
    assert_eq!(
        a.iter().map(|x| x.0).collect::<Vec<_>>(),
        b.iter().map(|x| x.0).collect::<Vec<_>>()
    );
    for ((step, la), (_, lb)) in a.iter().zip(&b) {
        assert!(
            (la - lb).abs() <= 1e-6 * la.abs().max(1.0),
            "step {step}: uninterrupted {la} vs resumed {lb}"
        );
    }
    assert!(straight.join("snapshots").exists());
    assert!(straight.join("loss_curve.png").exists());
    assert!(straight.join("checkpoints/latest.lgck").exists());
}

/// With validation on, the run keeps the weights of its best validation beside its latest:
/// `checkpoints/best.lgck`, whose header names the step and score, which is the best final-step
/// PSNR in `validation.jsonl`; a resumed run keeps it unless it does better.
#[test]
fn the_best_validated_weights_are_kept() {
    let _serial = serial();
    let mut cfg = experiment();
    cfg.train.validate_every = 1;
    cfg.train.validate_subjects = 1;
    let out = out_dir("best");
    let opts = |steps: u64, resume: bool| run_options(out.clone(), steps, resume);
    let best_of_log = || {
        std::fs::read_to_string(out.join("validation.jsonl"))
            .unwrap()
            .lines()
            .map(|l| {
                let v: serde_json::Value = serde_json::from_str(l).unwrap();
                let psnr = v["psnr"]
                    .as_array()
                    .unwrap()
                    .last()
                    .unwrap()
                    .as_f64()
                    .unwrap();
                (psnr, v["step"].as_u64().unwrap())
            })
            .fold((f64::NEG_INFINITY, 0), |a, b| if b.0 > a.0 { b } else { a })
    };
    let kept = || {
        let header =
            lifegom_model::trained::read_header(&lifegom_cli::train_run::best_checkpoint(&out))
                .expect("checkpoints/best.lgck");
        let v = &header.meta["validation"];
        (v["psnr"].as_f64().unwrap(), v["step"].as_u64().unwrap())
    };
    train(&cfg, &opts(3, false), never()).unwrap();
    assert_eq!(kept(), best_of_log());
    train(&cfg, &opts(5, true), never()).unwrap();
    assert_eq!(kept(), best_of_log());
}

/// A CPU run that resumes starts no GPU stack. burn-optim reads a resumed optimizer state onto
/// Burn's default device, which is the wgpu device when wgpu is compiled in; the binaries make
/// their `--device` the default (`lifegom_cli::make_default_device`). Before that, on a machine
/// with Mesa's Vulkan drivers and no `XDG_RUNTIME_DIR` (CI's), the resumed run printed
/// `error: XDG_RUNTIME_DIR is invalid or not set in the environment.` four times.
#[test]
fn a_cpu_run_that_resumes_prints_no_gpu_errors() {
    let _serial = serial();
    let out = out_dir("cpu-resume");
    let run = |steps: &str, resume: bool| {
        let mut cmd = std::process::Command::new(env!("CARGO_BIN_EXE_lifegom-train"));
        cmd.arg("--config")
            .arg(config_path())
            .args(["--device", "ndarray", "--steps", steps, "--data"])
            .arg(data_root())
            .arg("--out")
            .arg(&out)
            .env_remove("XDG_RUNTIME_DIR")
            .env_remove("BURN_DEVICE");
        if resume {
            cmd.arg("--resume");
        }
        let output = cmd.output().expect("running lifegom-train");
        let stderr = String::from_utf8_lossy(&output.stderr).into_owned();
        assert!(output.status.success(), "lifegom-train failed:\n{stderr}");
        stderr
    };
    run("1", false);
    let stderr = run("2", true);
    assert!(
        !stderr
            .lines()
            .any(|l| l.starts_with("error:") || l.contains("XDG_RUNTIME_DIR")),
        "a resumed CPU run printed errors:\n{stderr}"
    );
}

#[test]
fn a_stop_request_saves_a_checkpoint_and_bad_checkpoints_are_errors() {
    let _serial = serial();
    let cfg = experiment();
    let out = out_dir("stop");
    let stop = Arc::new(AtomicBool::new(true));
    let summary = train(
        &cfg,
        &RunOptions {
            out: out.clone(),
            resume: false,
            init: None,
            max_minutes: None,
            steps: Some(10),
            device: Device::ndarray(),
            progress: false,
        },
        stop,
    )
    .unwrap();
    assert_eq!(summary.stop, StopReason::Interrupted);
    assert_eq!(summary.step, 0);
    let resumed = Trainer::resume(&summary.checkpoint, &cfg.train, &Device::ndarray()).unwrap();
    assert_eq!(resumed.step, 0);

    let bad = out.join("bad.lgck");
    std::fs::write(&bad, b"LGOMCKPT garbage").unwrap();
    let err = Trainer::resume(&bad, &cfg.train, &Device::ndarray())
        .err()
        .unwrap()
        .to_string();
    assert!(err.contains("bad.lgck"), "{err}");
}

/// A batch whose loss is not finite leaves the weights and the step counter alone (design.md
/// §1.6); its samples count as used, and the next batch trains normally.
#[test]
fn a_batch_with_a_non_finite_loss_is_not_applied() {
    let _serial = serial();
    let OneSample {
        mut trainer,
        mesh,
        lap,
        inputs,
    } = one_sample(&experiment().train);
    let mut poisoned = inputs.clone();
    poisoned.target_rgb = poisoned.target_rgb.clone() * f32::NAN;

    let before = weights_checksum(&trainer.model).unwrap();
    let stats = trainer.train_step(&poisoned, &mesh, &lap).unwrap();
    assert!(!stats.applied);
    assert!(
        stats.losses.iter().any(|(_, v)| !v.is_finite()),
        "{:?}",
        stats.losses
    );
    assert_eq!((trainer.step, trainer.samples), (0, 1));
    assert_eq!(weights_checksum(&trainer.model).unwrap(), before);

    let stats = trainer.train_step(&inputs, &mesh, &lap).unwrap();
    assert!(stats.applied);
    assert_eq!((trainer.step, trainer.samples), (1, 2));
    assert_ne!(weights_checksum(&trainer.model).unwrap(), before);
}

#[test]
fn prefetched_samples_follow_the_serial_schedule() {
    let cfg = experiment();
    let data = std::sync::Arc::new(Dataset::open(&cfg.file.data, Split::Train).unwrap());
    let source = lifegom_train::source::TrainingSource::from_split(data.clone()).unwrap();
    let source = std::sync::Arc::new(source);
    let mut prefetch = Prefetcher::new(source.clone(), 7, BatchLayout::alone(3));
    for step in 3..9 {
        let a = prefetch.next_sample().unwrap();
        let b = sample_for_step(&data, 7, step).unwrap();
        assert_eq!(a.index, step);
        assert_eq!(a.sample.frame_name, b.frame_name, "step {step}");
        assert_eq!(a.sample.bgcolor, b.bgcolor, "step {step}");
        assert_eq!(
            a.sample.canonical_vertices, b.canonical_vertices,
            "step {step}"
        );
    }
    // Dropping it mid-stream joins the worker instead of hanging.
    drop(prefetch);
    // Rank 1 of 2 with two samples each: the second pair of every batch of four.
    let layout = BatchLayout {
        first_sample: 3,
        accumulate: 2,
        rank: 1,
        ranks: 2,
    };
    let mut prefetch = Prefetcher::new(source, 7, layout);
    for step in [5, 6, 9, 10] {
        let a = prefetch.next_sample().unwrap();
        let b = sample_for_step(&data, 7, step).unwrap();
        assert_eq!((a.index, a.sample.frame_name), (step, b.frame_name));
    }
}

/// One run, one writer: a second `lifegom-train` on a folder a running one holds stops at once
/// naming the folder and the holder's process id; once the holder is killed with SIGKILL, the
/// folder is free again (the lock is the kernel's, not a marker file).
#[cfg(unix)]
#[test]
fn a_second_process_on_a_run_folder_in_use_stops_at_once() {
    let _serial = serial();
    let out = out_dir("one-writer");
    let train = |steps: &str| {
        let mut cmd = std::process::Command::new(env!("CARGO_BIN_EXE_lifegom-train"));
        cmd.arg("--config")
            .arg(config_path())
            .args(["--device", "ndarray", "--steps", steps, "--data"])
            .arg(data_root())
            .arg("--out")
            .arg(&out);
        cmd
    };
    let mut first = train("100000")
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::null())
        .spawn()
        .expect("starting lifegom-train");
    // The first one holds the folder once its lock file names it.
    let lock = out.join(lifegom_cli::run_lock::LOCK_FILE);
    let deadline = std::time::Instant::now() + std::time::Duration::from_secs(120);
    while std::fs::read_to_string(&lock).map_or(true, |s| s.trim() != first.id().to_string()) {
        assert!(
            std::time::Instant::now() < deadline,
            "the first run never locked its folder"
        );
        std::thread::sleep(std::time::Duration::from_millis(50));
    }
    let started = std::time::Instant::now();
    let second = train("1").output().expect("running lifegom-train");
    let stderr = String::from_utf8_lossy(&second.stderr);
    assert!(!second.status.success(), "the second run ran:\n{stderr}");
    assert!(
        stderr.contains(&out.display().to_string())
            && stderr.contains(&format!("process {}", first.id())),
        "{stderr}"
    );
    assert!(
        started.elapsed().as_secs() < 60,
        "the second run did not stop at once"
    );
    // An export of the run's checkpoint is refused the same way.
    let export = std::process::Command::new(env!("CARGO_BIN_EXE_lifegom-train"))
        .arg("--out")
        .arg(&out)
        .arg("--export")
        .arg(out.join("exported.lgck"))
        .output()
        .expect("running lifegom-train --export");
    assert!(!export.status.success());
    assert!(String::from_utf8_lossy(&export.stderr).contains("in use by process"));
    first.kill().expect("SIGKILL"); // kill -9: no clean-up runs
    first.wait().unwrap();
    let again = train("1").output().expect("running lifegom-train");
    assert!(
        again.status.success(),
        "a killed holder left the folder locked:\n{}",
        String::from_utf8_lossy(&again.stderr)
    );
    let _ = std::fs::remove_dir_all(&out);
}

/// With a held-out set (design.md §8.11) the run validates on it beside the validation split:
/// each `validation.jsonl` line carries its scores per feedback step, its baselines and curve
/// are written, and `best.lgck` is judged by the mean of both sets' final PSNR.
#[test]
fn a_held_out_set_is_validated_beside_the_validation_split() {
    let _serial = serial();
    let root = out_dir("held-out-data");
    let mut cfg = experiment().with_root(&root);
    cfg.file.data.held_out_dir = Some("held_out".into());
    cfg.file.data.held_out_split = Some("held_out.json".into());
    let s = synth::SynthConfig {
        held_out_subjects: 1,
        ..cfg.file.synthetic.clone().unwrap()
    };
    synth::generate_split(&s, &cfg.file.data, &root, s.seed, &|| {}).unwrap();
    cfg.train.validate_every = 1;
    cfg.train.validate_subjects = 1;
    let out = out_dir("held-out");
    train(&cfg, &run_options(out.clone(), 2, false), never()).unwrap();
    let lines: Vec<serde_json::Value> = std::fs::read_to_string(out.join("validation.jsonl"))
        .unwrap()
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    assert_eq!(lines.len(), 2);
    let t = cfg.reconstructor().iterations;
    let finals = |v: &serde_json::Value| {
        let own = v["psnr"].as_array().unwrap();
        let held = v["held_out"]["psnr"].as_array().unwrap();
        assert_eq!((own.len(), held.len()), (t, t), "{v}");
        // Each step's error near the silhouette and inside it, on both sets.
        for key in ["silhouette_mse_x1e4", "inside_mse_x1e4"] {
            for set in [v, &v["held_out"]] {
                let per_t = set[key].as_array().unwrap_or_else(|| panic!("{key}: {v}"));
                assert_eq!(per_t.len(), t, "{v}");
                assert!(per_t.iter().all(|x| x.as_f64().unwrap() >= 0.0), "{v}");
            }
        }
        let last = |a: &[serde_json::Value]| a.last().unwrap().as_f64().unwrap();
        0.5 * (last(own) + last(held))
    };
    let best = lines.iter().map(finals).fold(f64::NEG_INFINITY, f64::max);
    let baselines: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(out.join("validation_baselines_held_out.json")).unwrap(),
    )
    .unwrap();
    for (name, b) in baselines.as_object().unwrap() {
        assert!(
            b["silhouette_mse_x1e4"].as_f64().unwrap() > 0.0,
            "{name}: {b}"
        );
    }
    for file in [
        "validation_baselines_held_out.json",
        "validation_curve_held_out.png",
        "validation_curve.png",
    ] {
        assert!(out.join(file).is_file(), "{file} missing");
    }
    let header =
        lifegom_model::trained::read_header(&lifegom_cli::train_run::best_checkpoint(&out))
            .unwrap();
    assert_eq!(header.meta["validation"]["psnr"].as_f64(), Some(best));
}
