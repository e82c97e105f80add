//! The official code's checkpoints in the commands, end to end: `lifegom-eval`,
//! `lifegom-reconstruct` and `lifegom-train --init` run from a checkpoint written by real
//! `torch.save` in the official structure (`{iter, network, optimizer}`;
//! `tests/fixtures/official/demo-v2.pth`, made from demo model v2 by
//! `tools/official-fixture/make_official_pth.py`) and must give exactly what the same weights
//! give as a `.lgck` (`assets/demo/v2/demo.lgck`). A file that does not fit the config's network
//! is one error naming the key and both shapes.

mod common;

use std::path::{Path, PathBuf};
use std::process::Command;

use lifegom_data::kinematics::KinematicTree;

use common::{first_val_subject, tiny_split};

fn repo(path: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("..")
        .join(path)
}

fn official_fixture() -> PathBuf {
    repo("tests/fixtures/official/demo-v2.pth")
}

fn demo_lgck() -> PathBuf {
    repo("assets/demo/v2/demo.lgck")
}

/// The tiny split (64 px, 3 inputs), and a config for it whose `[model]` is the demo model's
/// network (tiny preset, T = 3, one subdivision at test), so that the official file, which
/// carries no config, is run exactly as the `.lgck` runs.
fn setup(tag: &str) -> (PathBuf, PathBuf) {
    let (tmp, _) = tiny_split(tag, |s| {
        (s.train_subjects, s.val_subjects) = (2, 1);
    });
    let text = std::fs::read_to_string(repo("configs/synthetic-tiny.toml")).unwrap();
    assert!(text.contains("iterations = 2\n"), "the tiny config changed");
    let config = tmp.join("config.toml");
    std::fs::write(
        &config,
        text.replace("iterations = 2\n", "iterations = 3\n"),
    )
    .unwrap();
    (tmp, config)
}

/// Runs a binary of this package; returns its stdout, or panics with its stderr.
fn run_ok(bin: &str, args: &[&str]) -> String {
    let out = command(bin, args);
    assert!(
        out.status.success(),
        "{bin} {args:?} failed:\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8(out.stdout).unwrap()
}

fn command(bin: &str, args: &[&str]) -> std::process::Output {
    Command::new(bin).args(args).output().unwrap()
}

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

#[test]
fn eval_and_reconstruct_from_an_official_pth_equal_the_same_weights_as_lgck() {
    let (tmp, config) = setup("official-e2e");
    let data = tmp.join("data");

    // `lifegom-eval`: the same scores, to the last digit.
    let mut scores = Vec::new();
    for (name, model) in [("lgck", demo_lgck()), ("pth", official_fixture())] {
        let out = tmp.join(format!("eval-{name}"));
        let stdout = run_ok(
            env!("CARGO_BIN_EXE_lifegom-eval"),
            &[
                "--config",
                s(&config),
                "--data",
                s(&data),
                "--checkpoint",
                s(&model),
                "--out",
                s(&out),
                "--device",
                "ndarray",
                "--sheets",
                "0",
            ],
        );
        let json: serde_json::Value = serde_json::from_str(stdout.trim()).unwrap();
        let report = std::fs::read_to_string(out.join("report.md")).unwrap();
        if name == "pth" {
            assert!(report.contains("official PyTorch checkpoint"), "{report}");
        }
        scores.push(json["model"].clone());
    }
    assert!(scores[0]["psnr"].as_f64().unwrap() > 10.0, "{}", scores[0]);
    for key in ["psnr", "ssim", "views"] {
        assert_eq!(scores[0][key], scores[1][key], "{key}: {scores:?}");
    }

    // `lifegom-reconstruct`: the same avatar, byte for byte.
    let subject = first_val_subject(
        &lifegom_data::config::ConfigFile::load(&config)
            .unwrap()
            .with_root(&data),
    );
    lifegom_data::format::Subject::load(&subject, KinematicTree::Stored).unwrap();
    let mut avatars = Vec::new();
    for (name, model) in [("lgck", demo_lgck()), ("pth", official_fixture())] {
        let out = tmp.join(format!("recon-{name}"));
        run_ok(
            env!("CARGO_BIN_EXE_lifegom-reconstruct"),
            &[
                s(&subject),
                "--model",
                s(&model),
                "--config",
                s(&config),
                "--out",
                s(&out),
                "--device",
                "ndarray",
                "--turntable",
                "0",
            ],
        );
        avatars.push(std::fs::read(out.join("avatar.lgom")).unwrap());
    }
    assert!(avatars[0].len() > 1000);
    assert!(avatars[0] == avatars[1], "the two avatars differ");
    let _ = std::fs::remove_dir_all(&tmp);
}

#[test]
fn a_network_mismatch_is_one_error_naming_the_key_and_both_shapes() {
    let (tmp, config) = setup("official-mismatch");
    let text = std::fs::read_to_string(&config).unwrap();
    let cpu = tmp.join("cpu.toml");
    std::fs::write(&cpu, text.replace("preset = \"tiny\"", "preset = \"cpu\"")).unwrap();
    let out = command(
        env!("CARGO_BIN_EXE_lifegom-eval"),
        &[
            "--config",
            s(&cpu),
            "--data",
            s(&tmp.join("data")),
            "--checkpoint",
            s(&official_fixture()),
            "--out",
            s(&tmp.join("eval")),
            "--device",
            "ndarray",
        ],
    );
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("demo-v2.pth"), "{err}");
    assert!(
        err.contains(
            "`img_encoder.encoder.0.weight`: model needs [16, 3, 7, 7], file has [8, 3, 7, 7]"
        ),
        "{err}"
    );
    assert!(
        err.contains("preset = \"tiny\"` network for 3 input views"),
        "{err}"
    );
    assert!(!err.contains("panicked"), "{err}");
    let _ = std::fs::remove_dir_all(&tmp);
}

/// Fine-tuning: one step from `--init` with the official file equals one step from `--init`
/// with the same weights as a `.lgck`, and both start from those weights with a fresh
/// optimizer (step 1 after one step).
#[test]
fn one_step_from_init_is_the_same_from_pth_and_lgck() {
    let (tmp, config) = setup("official-init");
    let mut weights = Vec::new();
    for (name, model) in [("lgck", demo_lgck()), ("pth", official_fixture())] {
        let out = tmp.join(format!("train-{name}"));
        run_ok(
            env!("CARGO_BIN_EXE_lifegom-train"),
            &[
                "--config",
                s(&config),
                "--data",
                s(&tmp.join("data")),
                "--init",
                s(&model),
                "--steps",
                "1",
                "--out",
                s(&out),
                "--device",
                "ndarray",
            ],
        );
        #[allow(deprecated)] // Device::ndarray(): the CI backend (design.md §1.4).
        let device = burn::tensor::Device::ndarray();
        let loaded =
            lifegom_model::trained::load(&out.join("checkpoints/latest.lgck"), &device).unwrap();
        assert_eq!(loaded.header.meta["step"], 1, "{name}");
        weights.push(all_values(&loaded.model));
    }
    #[allow(deprecated)]
    let device = burn::tensor::Device::ndarray();
    let start = all_values(
        &lifegom_model::trained::load(&demo_lgck(), &device)
            .unwrap()
            .model,
    );
    assert!(
        weights[0] == weights[1],
        "one step from the .pth differs from one from the .lgck"
    );
    assert!(weights[0] != start, "the step changed nothing");
    // One Adam step moves each weight by at most about the learning rate: the run started from
    // the demo weights, not from a fresh initialisation.
    let largest = start
        .iter()
        .flatten()
        .zip(weights[0].iter().flatten())
        .map(|(a, b)| (a - b).abs())
        .fold(0.0f32, f32::max);
    assert!(largest < 1e-2, "largest change {largest}");
    let _ = std::fs::remove_dir_all(&tmp);
}

fn all_values(model: &lifegom_model::reconstructor::Reconstructor) -> Vec<Vec<f32>> {
    use burn::store::ModuleSnapshot;
    model
        .collect(None, None, true)
        .iter()
        .map(|t| {
            burn::store::bridge::to_data(t)
                .unwrap()
                .convert::<f32>()
                .try_to_vec::<f32>()
                .unwrap()
        })
        .collect()
}

/// `lifegom-train --export` takes an official file as its input (with `--config` for the
/// network) and writes the official state dict when asked for `.safetensors`: both round trips
/// keep every weight.
#[test]
fn export_converts_between_official_and_lifegom_files() {
    let tmp = std::env::temp_dir().join(format!("lifegom-official-export-{}", std::process::id()));
    std::fs::create_dir_all(&tmp).unwrap();
    let (lgck, safetensors) = (tmp.join("from-pth.lgck"), tmp.join("demo.safetensors"));
    let config = repo("configs/demo-v2.toml");
    let export = |from: &Path, to: &Path, config: Option<&Path>| {
        let mut args = vec!["--export", s(to), "--from", s(from), "--device", "ndarray"];
        if let Some(c) = config {
            args.extend(["--config", s(c)]);
        }
        command(env!("CARGO_BIN_EXE_lifegom-train"), &args)
    };
    // Without a config an official file has no network to go into: one clear error.
    let out = export(&official_fixture(), &lgck, None);
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("demo-v2.pth") && err.contains("--config"),
        "{err}"
    );
    for (from, to, config) in [
        (official_fixture(), &lgck, Some(config.as_path())),
        (demo_lgck(), &safetensors, None),
    ] {
        let out = export(&from, to, config);
        assert!(
            out.status.success(),
            "{}",
            String::from_utf8_lossy(&out.stderr)
        );
    }
    #[allow(deprecated)] // Device::ndarray(): the CI backend (design.md §1.4).
    let device = burn::tensor::Device::ndarray();
    let demo = lifegom_model::trained::load(&demo_lgck(), &device).unwrap();
    let back = lifegom_model::trained::load(&lgck, &device).unwrap();
    let st = lifegom_model::trained::load_any(&safetensors, &demo.config, &device).unwrap();
    let start = all_values(&demo.model);
    assert!(
        all_values(&back.model) == start,
        ".pth → .lgck changed weights"
    );
    assert!(
        all_values(&st.model) == start,
        ".lgck → .safetensors changed weights"
    );
    let _ = std::fs::remove_dir_all(&tmp);
}
