//! A full disk while the commands write, and kills at random moments: a write fails with an
//! error naming the file, and the previous file stays whole. The disk fills by a file-size limit
//! (`ulimit -f`, with SIGXFSZ ignored so that a write past it fails with EFBIG instead of killing
//! the process): what a full filesystem does to a writer, without mounting one (no root needed).

mod common;

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

use common::{first_val_subject, tiny_split, untrained_tiny_model};

/// Runs `exe args` with files limited to `limit_kib` KiB (`None`: unlimited).
fn run(exe: &str, args: &[&str], limit_kib: Option<u64>) -> Output {
    let limit = limit_kib.map_or("unlimited".to_string(), |k| k.to_string());
    Command::new("bash")
        .arg("-c")
        .arg(format!(
            r#"trap "" XFSZ; ulimit -f {limit}; exec "$0" "$@""#
        ))
        .arg(exe)
        .args(args)
        .env("RUST_LOG", "warn")
        .output()
        .expect("running bash")
}

fn stderr(out: &Output) -> String {
    String::from_utf8_lossy(&out.stderr).into_owned()
}

fn config() -> String {
    let config = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../configs/synthetic-tiny.toml");
    config.to_str().unwrap().to_string()
}

/// The folder's files (recursively) and their bytes.
fn snapshot(dir: &Path) -> Vec<(PathBuf, Vec<u8>)> {
    let mut files = Vec::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        for entry in std::fs::read_dir(&d).unwrap() {
            let path = entry.unwrap().path();
            if path.is_dir() {
                stack.push(path);
            } else {
                let bytes = std::fs::read(&path).unwrap();
                files.push((path, bytes));
            }
        }
    }
    files.sort();
    files
}

fn assert_no_temporaries(dir: &Path) {
    for (path, _) in snapshot(dir) {
        let name = path.file_name().unwrap().to_string_lossy().into_owned();
        assert!(
            !name.starts_with(".lifegom-"),
            "a temporary was left: {}",
            path.display()
        );
    }
}

/// Training: a checkpoint that cannot be written stops the run with an error naming it; the
/// previous checkpoint is whole, the logs hold only whole lines, and `--resume` goes on.
#[test]
fn a_full_disk_during_training_loses_nothing() {
    let (tmp, cfg) = tiny_split("disk-train", |_| {});
    let root = cfg.data.root.to_str().unwrap().to_string();
    let out = tmp.join("run");
    let out_s = out.to_str().unwrap();
    let exe = env!("CARGO_BIN_EXE_lifegom-train");
    let cfg_path = config();
    let args = |steps: &'static str, resume: bool| {
        let mut a = vec![
            "--config", &cfg_path, "--device", "ndarray", "--data", &root, "--out", out_s,
            "--steps", steps,
        ];
        if resume {
            a.push("--resume");
        }
        a
    };
    let first = run(exe, &args("1", false), None);
    assert!(first.status.success(), "{}", stderr(&first));
    let checkpoint = out.join("checkpoints/latest.lgck");
    let before = std::fs::read(&checkpoint).unwrap();
    assert!(
        before.len() > 256 * 1024,
        "the checkpoint must exceed the limit"
    );

    let full = run(exe, &args("2", true), Some(256));
    let msg = stderr(&full);
    assert!(
        !full.status.success(),
        "a run on a full disk succeeded:\n{msg}"
    );
    assert!(msg.contains("File too large"), "{msg}");
    assert!(msg.contains(out_s), "the error names the file:\n{msg}");
    eprintln!("the training run's error: {msg}");
    assert_eq!(
        std::fs::read(&checkpoint).unwrap(),
        before,
        "the old checkpoint changed"
    );
    assert_no_temporaries(&out);

    let again = run(exe, &args("2", true), None);
    assert!(again.status.success(), "{}", stderr(&again));
    let log = std::fs::read_to_string(out.join("metrics.jsonl")).unwrap();
    let steps: Vec<u64> = log
        .lines()
        .map(|l| {
            let v: serde_json::Value = serde_json::from_str(l).expect("whole lines only");
            v["step"].as_u64().unwrap()
        })
        .collect();
    assert_eq!(steps, [1, 2], "{log}");
    std::fs::remove_dir_all(&tmp).ok();
}

/// Reconstruction: exports (`.lgom`, `.ply`, `.glb`), images and the report that cannot be
/// written are an error naming the file; the previous run's files stay whole.
#[test]
fn a_full_disk_during_export_leaves_the_previous_files() {
    let (tmp, cfg) = tiny_split("disk-export", |s| {
        (s.train_subjects, s.val_subjects) = (0, 1);
    });
    let subject = first_val_subject(&cfg);
    let model = untrained_tiny_model(&tmp, 1, 0);
    let out = tmp.join("out");
    let exe = env!("CARGO_BIN_EXE_lifegom-reconstruct");
    let cfg_path = config();
    let args = [
        subject.to_str().unwrap(),
        "--model",
        model.to_str().unwrap(),
        "--config",
        &cfg_path,
        "--device",
        "ndarray",
        "--turntable",
        "4",
        "--out",
        out.to_str().unwrap(),
    ];
    let first = run(exe, &args, None);
    assert!(first.status.success(), "{}", stderr(&first));
    let before = snapshot(&out);
    let largest = before.iter().map(|(_, b)| b.len()).max().unwrap();
    assert!(largest > 16 * 1024, "some output must exceed the limit");

    let full = run(exe, &args, Some(16));
    let msg = stderr(&full);
    assert!(
        !full.status.success(),
        "an export on a full disk succeeded:\n{msg}"
    );
    assert!(msg.contains("File too large"), "{msg}");
    assert!(
        msg.contains(out.to_str().unwrap()),
        "the error names the file:\n{msg}"
    );
    eprintln!("the export's error: {msg}");
    let after = snapshot(&out);
    assert_eq!(after.len(), before.len(), "files appeared or vanished");
    for ((path, old), (_, new)) in before.iter().zip(&after) {
        assert!(old == new, "{} changed", path.display());
    }
    std::fs::remove_dir_all(&tmp).ok();
}

/// Runs `exe args` twice into the same output folder, the second time on a "full disk" of
/// `limit_kib` KiB: the second run fails with an error naming a file of `out`, and every file of
/// the first run is still there, byte for byte, with no temporary left beside it.
fn second_run_on_a_full_disk_changes_nothing(exe: &str, args: &[&str], out: &Path, limit_kib: u64) {
    let first = run(exe, args, None);
    assert!(first.status.success(), "{}", stderr(&first));
    let before = snapshot(out);
    let largest = before.iter().map(|(_, b)| b.len()).max().unwrap();
    assert!(
        largest as u64 > limit_kib * 1024,
        "some output must exceed the limit"
    );
    let full = run(exe, args, Some(limit_kib));
    let msg = stderr(&full);
    assert!(
        !full.status.success(),
        "a run on a full disk succeeded:\n{msg}"
    );
    assert!(msg.contains("File too large"), "{msg}");
    assert!(
        msg.contains(out.to_str().unwrap()),
        "the error names the file:\n{msg}"
    );
    eprintln!("{}: {msg}", Path::new(exe).file_name().unwrap().display());
    let after = snapshot(out);
    assert_eq!(
        after.iter().map(|(p, _)| p).collect::<Vec<_>>(),
        before.iter().map(|(p, _)| p).collect::<Vec<_>>(),
        "files appeared or vanished"
    );
    for ((path, old), (_, new)) in before.iter().zip(&after) {
        assert!(old == new, "{} changed", path.display());
    }
    assert_no_temporaries(out);
}

/// Data generation: regenerating a split on a full disk leaves the old split whole (images,
/// masks, pickles, split lists).
#[test]
fn a_full_disk_during_data_generation_leaves_the_previous_split() {
    let tmp = std::env::temp_dir().join(format!("lifegom-disk-synth-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&tmp);
    let out = tmp.join("data");
    let cfg_path = config();
    second_run_on_a_full_disk_changes_nothing(
        env!("CARGO_BIN_EXE_lifegom-synth"),
        &["--config", &cfg_path, "--out", out.to_str().unwrap()],
        &out,
        8,
    );
    std::fs::remove_dir_all(&tmp).ok();
}

/// Evaluation: a report that cannot be written is an error, and the previous report, tables,
/// predictions and sheets stay whole.
#[test]
fn a_full_disk_during_evaluation_leaves_the_previous_report() {
    let (tmp, cfg) = tiny_split("disk-eval", |s| {
        (s.train_subjects, s.val_subjects) = (0, 1);
    });
    let model = untrained_tiny_model(&tmp, 1, 0);
    let out = tmp.join("eval");
    let cfg_path = config();
    second_run_on_a_full_disk_changes_nothing(
        env!("CARGO_BIN_EXE_lifegom-eval"),
        &[
            "--config",
            &cfg_path,
            "--data",
            cfg.data.root.to_str().unwrap(),
            "--checkpoint",
            model.to_str().unwrap(),
            "--device",
            "ndarray",
            "--sheets",
            "1",
            "--out",
            out.to_str().unwrap(),
        ],
        &out,
        1,
    );
    std::fs::remove_dir_all(&tmp).ok();
}

/// Kills: `kill -9` at seeded random moments of a run that writes a checkpoint every step;
/// after each, `--resume` starts from a whole checkpoint and the log has only whole lines, its
/// steps counting up from 1 without a gap or a repeat.
#[test]
fn kills_at_random_moments_lose_nothing() {
    let (tmp, cfg) = tiny_split("disk-kill", |_| {});
    let root = cfg.data.root.to_str().unwrap().to_string();
    let text = std::fs::read_to_string(config())
        .unwrap()
        .replace("checkpoint_every = 50", "checkpoint_every = 1")
        .replace("snapshot_every = 50", "snapshot_every = 1");
    let cfg_path = tmp.join("every-step.toml");
    std::fs::write(&cfg_path, text).unwrap();
    let out = tmp.join("run");
    let exe = env!("CARGO_BIN_EXE_lifegom-train");
    let mut rng = lifegom_render::rng::Rng::new(7);
    let kills = 6;
    for kill in 0..kills {
        let mut cmd = Command::new(exe);
        cmd.arg("--config")
            .arg(&cfg_path)
            .args(["--device", "ndarray", "--data", &root, "--out"])
            .arg(&out)
            .env("RUST_LOG", "warn")
            .stdout(std::process::Stdio::null())
            .stderr(std::process::Stdio::null());
        if kill > 0 {
            cmd.arg("--resume");
        }
        let mut child = cmd.spawn().unwrap();
        // Long enough to pass start-up and write some checkpoints, short of the 200 steps.
        let wait_ms = 3000 + (rng.uniform() * 4000.0) as u64;
        std::thread::sleep(std::time::Duration::from_millis(wait_ms));
        child.kill().unwrap(); // SIGKILL
        child.wait().unwrap();
        let checkpoint = out.join("checkpoints/latest.lgck");
        if checkpoint.exists() {
            #[allow(deprecated)] // Device::ndarray(): the CI backend (design.md §1.4).
            let device = burn::tensor::Device::ndarray();
            lifegom_model::trained::load(&checkpoint, &device)
                .unwrap_or_else(|e| panic!("kill {kill}: the checkpoint is damaged: {e}"));
        }
    }
    // A last resume runs one step past the checkpoint and stops cleanly.
    let checkpoint = out.join("checkpoints/latest.lgck");
    #[allow(deprecated)]
    let device = burn::tensor::Device::ndarray();
    let step = lifegom_model::trained::load(&checkpoint, &device)
        .unwrap()
        .header
        .meta["step"]
        .as_u64()
        .unwrap();
    assert!(step >= 2, "the runs got past start-up (step {step})");
    let next = (step + 1).to_string();
    let resumed = run(
        exe,
        &[
            "--config",
            cfg_path.to_str().unwrap(),
            "--device",
            "ndarray",
            "--data",
            &root,
            "--out",
            out.to_str().unwrap(),
            "--steps",
            &next,
            "--resume",
        ],
        None,
    );
    assert!(resumed.status.success(), "{}", stderr(&resumed));
    let log = std::fs::read_to_string(out.join("metrics.jsonl")).unwrap();
    let steps: Vec<u64> = log
        .lines()
        .map(|l| {
            let v: serde_json::Value =
                serde_json::from_str(l).unwrap_or_else(|e| panic!("torn line `{l}`: {e}"));
            v["step"].as_u64().unwrap()
        })
        .collect();
    assert_eq!(steps, (1..=step + 1).collect::<Vec<_>>(), "{log}");
    assert_no_temporaries(&out);
    eprintln!("{kills} kills; resumed at step {step}, finished at {next}");
    std::fs::remove_dir_all(&tmp).ok();
}
