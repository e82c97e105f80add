//! Burn's kernel fusion changes no value: the tiny model's reconstruction (two views, two
//! feedback iterations) and the gradient of its sum at the vertex embedding, on wgpu, with
//! fusion on and with it off (`LIFEGOM_FUSION=off`), agree within 1e-5 of each value's scale.
//!
//! Which fusers exist is fixed once per process, so the test runs itself twice as a child
//! process, once per setting, and compares what the two wrote. It needs a wgpu adapter (lavapipe
//! in CI); without one it says so and passes, unless `LIFEGOM_REQUIRE_WGPU` is set.

mod common;

use std::path::Path;
use std::process::Command;

use common::reconstruct_parts;
use lifegom_model::reconstructor::HostConcurrency;
use lifegom_render::device::{DeviceChoice, KernelFusion};
use lifegom_render::testing::wgpu_test_device;

const CHILD_OUT: &str = "LIFEGOM_FUSION_TEST_OUT";
const TEST_NAME: &str = "fusion_on_and_off_agree";

#[test]
fn fusion_on_and_off_agree() {
    if let Some(out) = std::env::var_os(CHILD_OUT) {
        write_child_values(Path::new(&out));
        return;
    }
    if wgpu_test_device().is_none() {
        return;
    }
    let dir = std::env::temp_dir().join(format!("lifegom-fusion-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let on = run_child(&dir, "on");
    let off = run_child(&dir, "off");
    std::fs::remove_dir_all(&dir).ok();
    assert_eq!(on.len(), off.len());
    for ((name, a), (_, b)) in on.iter().zip(&off) {
        assert_eq!(a.len(), b.len(), "{name}");
        let scale = a
            .iter()
            .fold(0f32, |m, v| m.max(v.abs()))
            .max(f32::MIN_POSITIVE);
        let diff = a.iter().zip(b).fold(0f32, |m, (x, y)| m.max((x - y).abs()));
        eprintln!(
            "{name}: {} values, max |on − off| = {diff:e}, scale {scale:e}",
            a.len()
        );
        assert!(
            a.iter().chain(b).all(|v| v.is_finite()),
            "{name}: non-finite values"
        );
        assert!(
            diff <= 1e-5 * scale,
            "{name}: fusion on and off differ by {diff:e} (scale {scale:e})"
        );
    }
}

/// Runs this test in a child process with `LIFEGOM_FUSION=mode` and reads what it wrote.
fn run_child(dir: &Path, mode: &str) -> Vec<(String, Vec<f32>)> {
    let out = dir.join(format!("{mode}.txt"));
    let status = Command::new(std::env::current_exe().unwrap())
        .args(["--exact", TEST_NAME, "--nocapture", "--test-threads=1"])
        .env("LIFEGOM_FUSION", mode)
        .env(CHILD_OUT, &out)
        .status()
        .unwrap();
    assert!(status.success(), "the child with fusion {mode} failed");
    std::fs::read_to_string(&out)
        .unwrap()
        .lines()
        .map(|line| {
            let (name, values) = line.split_once(' ').unwrap();
            let values = values.split(' ').map(|v| v.parse().unwrap()).collect();
            (name.to_string(), values)
        })
        .collect()
}

/// The child: one reconstruction and its gradient on wgpu, written one part per line (values as
/// exact decimal f32).
fn write_child_values(out: &Path) {
    let mode = std::env::var("LIFEGOM_FUSION").unwrap();
    let device = DeviceChoice::Wgpu.device();
    assert_eq!(
        KernelFusion::current().name(),
        mode,
        "the child runs the requested setting"
    );
    let parts = reconstruct_parts(&device.autodiff(), 5, 2, HostConcurrency::default());
    let text: String = parts
        .iter()
        .map(|(name, values)| {
            let values: Vec<String> = values.iter().map(|v| v.to_string()).collect();
            format!("{name} {}\n", values.join(" "))
        })
        .collect();
    std::fs::write(out, text).unwrap();
}
