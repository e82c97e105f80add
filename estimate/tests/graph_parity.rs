//! Parity of the three MediaPipe person graphs, read and run by `lifegom-tflite`, with the
//! reference TensorFlow Lite interpreter, on every backend (ndarray, Flex, wgpu).
//!
//! The graphs are those `lifegom-weights fetch` takes out of the mediapipe 0.10.14 wheel, found
//! in `$LIFEGOM_WEIGHTS`. The references are every output of each graph under ai-edge-litert
//! 2.3.0's interpreter (`tools/make_tflite_fixtures.py`), on the images of
//! `fixtures/mediapipe/` (a photograph and our renders, already at the graphs' input sizes).
//!
//! Each output must agree within 1e-4 in relative L2 norm (‖ours − theirs‖ / ‖theirs‖), and every
//! element within 1e-3 of the output's largest magnitude. The element bound is looser because
//! TensorFlow Lite does not meet a tighter one against itself: its reference kernels
//! (`BUILTIN_REF`, recorded per output by the fixture script) land up to 5.1e-4 of the scale
//! from its XNNPACK result on the landmark model's segmentation logits; float rounding grows
//! through the layers (traced layer by layer on the selfie model: 2.5e-7 after the first
//! convolution, 1.8e-5 after the first global average, no layer jumping) and the deep heads
//! amplify it at a few elements.
//!
//! Without the graphs the tests skip loudly, unless `LIFEGOM_REQUIRE_WEIGHTS` is set (CI sets
//! it after fetching), in which case they fail.

mod common;

use std::path::{Path, PathBuf};

use common::graphs_dir;

use burn::tensor::{Device, Tensor, TensorData};
use lifegom_estimate::graphs::{self, PersonGraph};

/// Relative L2 norm of the difference, per output.
const L2_TOLERANCE: f32 = 1e-4;
/// Largest element difference, as a fraction of the output's largest magnitude.
const MAX_TOLERANCE: f32 = 1e-3;

fn fixture_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/mediapipe")
}

fn graph_key(graph: PersonGraph) -> &'static str {
    match graph {
        PersonGraph::Detector => "detector",
        PersonGraph::Landmarks => "landmarks",
        PersonGraph::Selfie => "selfie",
    }
}

/// The graph's input for fixture image `name`: `[1, 3, S, S]`, scaled as the graph takes it.
fn input(name: &str, graph: PersonGraph, device: &Device) -> Tensor<4> {
    let size = graph.input_size();
    let path = fixture_dir().join(format!("{name}_{size}.png"));
    let rgb = image::open(&path).unwrap().to_rgb8();
    assert_eq!(
        rgb.dimensions(),
        (size as u32, size as u32),
        "{}",
        path.display()
    );
    let (scale, offset) = graph.input_range();
    let values: Vec<f32> = rgb
        .as_raw()
        .iter()
        .map(|&v| f32::from(v) * scale + offset)
        .collect();
    Tensor::<4>::from_data(TensorData::new(values, [1, size, size, 3]), device)
        .permute([0, 3, 1, 2])
}

fn reference() -> serde_json::Value {
    let text = std::fs::read_to_string(fixture_dir().join("reference.json")).unwrap();
    serde_json::from_str(&text).unwrap()
}

fn parity(device: &Device) {
    let Some(dir) = graphs_dir() else { return };
    let index = reference();
    let images: Vec<String> = index["images"]
        .as_object()
        .unwrap()
        .keys()
        .cloned()
        .collect();
    assert!(
        images.iter().any(|n| n == "astronaut"),
        "the photograph is among the fixtures"
    );
    for graph in PersonGraph::ALL {
        let loaded = graphs::load(&dir, graph, device).unwrap();
        for name in &images {
            let start = std::time::Instant::now();
            let outputs = loaded.run(vec![input(name, graph, device)]).unwrap();
            let seconds = start.elapsed().as_secs_f64();
            let reference = lifegom_data::capture::read_npz(
                &fixture_dir().join(format!("{name}_{}.npz", graph_key(graph))),
            )
            .unwrap();
            assert_eq!(outputs.len(), reference.len(), "{graph} on {name}: outputs");
            for output in &outputs {
                let (_, want) = reference
                    .iter()
                    .find(|(k, _)| *k == output.spec.name)
                    .unwrap_or_else(|| panic!("{graph}: no reference for `{}`", output.spec.name));
                assert_eq!(
                    want.shape, output.spec.shape,
                    "{graph} `{}`",
                    output.spec.name
                );
                let want = want.to_f32();
                let got = output.to_vec().unwrap();
                let scale = want.iter().fold(0f32, |m, v| m.max(v.abs())).max(1e-6);
                let spread = &index["images"][name][graph_key(graph)][&output.spec.name]["reference_kernel_spread"];
                let own = |key: &str| {
                    spread[key]
                        .as_f64()
                        .map_or("-".into(), |s| format!("{s:.1e}"))
                };
                let l2 = (got
                    .iter()
                    .zip(&want)
                    .map(|(g, w)| f64::from(g - w).powi(2))
                    .sum::<f64>()
                    / want
                        .iter()
                        .map(|w| f64::from(*w).powi(2))
                        .sum::<f64>()
                        .max(1e-30))
                .sqrt() as f32;
                let (worst, at) = got
                    .iter()
                    .zip(&want)
                    .map(|(g, w)| (g - w).abs())
                    .enumerate()
                    .fold(
                        (0f32, 0),
                        |(m, i), (j, d)| if d > m { (d, j) } else { (m, i) },
                    );
                eprintln!(
                    "{graph} on {name} ({seconds:.2} s): `{}` {:?} worst |diff| {worst:.3e} \
                     = {:.2e} of its scale {scale:.3e}, relative L2 {l2:.2e} (TensorFlow Lite's \
                     own kernels: {} and {})",
                    output.spec.name,
                    output.spec.shape,
                    worst / scale,
                    own("max"),
                    own("l2"),
                );
                assert!(
                    l2 <= L2_TOLERANCE,
                    "{graph} on {name}: `{}` relative L2 {l2}",
                    output.spec.name
                );
                assert!(
                    worst <= MAX_TOLERANCE * scale,
                    "{graph} on {name}: `{}`[{at}] = {} against the interpreter's {} \
                     (scale {scale:.3e})",
                    output.spec.name,
                    got[at],
                    want[at]
                );
            }
        }
    }
}

#[test]
#[allow(deprecated)] // Device::ndarray(): the CI backend.
fn graphs_match_the_interpreter_on_ndarray() {
    parity(&Device::ndarray());
}

#[test]
fn graphs_match_the_interpreter_on_flex() {
    parity(&Device::flex());
}

#[test]
fn graphs_match_the_interpreter_on_wgpu() {
    if let Some(device) = lifegom_render::testing::wgpu_test_device() {
        parity(&device);
    }
}
