//! The reader's operators on small graphs made in code (`lifegom_tflite::testing`): values
//! worked out by hand from TensorFlow Lite's definitions where a layout or padding rule could
//! go wrong (SAME padding's odd zero, half-pixel resizing, depth-to-space's channel order,
//! averages that leave padding out), every operator at once on every backend, and the errors.
//! The parity with TensorFlow Lite itself, on the MediaPipe graphs, is
//! `lifegom-estimate`'s `graph_parity` test.

use burn::tensor::{Device, Tensor, TensorData};
use lifegom_render::testing::{assert_close_to_scale, wgpu_test_device};
use lifegom_tflite::testing::{Data, Options, TestGraph, pattern, small_graph};
use lifegom_tflite::{Graph, TfliteError};

// TensorFlow Lite's operator numbers.
const CONV_2D: i32 = 3;
const AVERAGE_POOL_2D: i32 = 1;
const DEPTH_TO_SPACE: i32 = 5;
const RESIZE_BILINEAR: i32 = 23;
const FULLY_CONNECTED: i32 = 9;

/// Runs a one-input graph on NHWC values; returns the first output in NHWC order.
fn run_nhwc(bytes: &[u8], shape: [usize; 4], values: Vec<f32>, device: &Device) -> Vec<f32> {
    let graph = Graph::from_bytes("test.tflite", bytes, device).unwrap();
    let x = Tensor::<4>::from_data(TensorData::new(values, shape), device).permute([0, 3, 1, 2]);
    graph.run(vec![x]).unwrap()[0].to_vec().unwrap()
}

/// A CONV_2D of a 3 × 3 box of ones, stride 2, SAME, on a `[1, 4, 4, 1]` input, its output
/// declared as `declared` (`[1, 2, 2, 1]` is what it makes).
fn stride_two_box_conv(declared: &[usize]) -> Vec<u8> {
    let mut g = TestGraph::new();
    let x = g.tensor("x", &[1, 4, 4, 1], None);
    let w = g.tensor("w", &[1, 3, 3, 1], Some(Data::F32(vec![1.0; 9])));
    let b = g.tensor("b", &[1], Some(Data::F32(vec![0.0])));
    let y = g.tensor("y", declared, None);
    let conv = Options::Conv {
        same: true,
        stride: 2,
        relu6: false,
    };
    g.op(CONV_2D, &[x, w, b], y, conv);
    g.input(x);
    g.output(y);
    g.finish()
}

fn hand_checked_values(device: &Device) {
    // CONV_2D 3 × 3 of ones, stride 2, SAME on 4 × 4: TensorFlow pads one zero row and column
    // after, none before.
    let ramp: Vec<f32> = (1..=16).map(|v| v as f32).collect();
    let got = run_nhwc(
        &stride_two_box_conv(&[1, 2, 2, 1]),
        [1, 4, 4, 1],
        ramp,
        device,
    );
    assert_eq!(got, [54.0, 45.0, 72.0, 54.0], "SAME padding");

    // RESIZE_BILINEAR 2 → 4 with half-pixel centres: sources at -0.25, 0.25, 0.75, 1.25.
    let mut g = TestGraph::new();
    let x = g.tensor("x", &[1, 1, 2, 1], None);
    let size = g.tensor("size", &[2], Some(Data::I32(vec![1, 4])));
    let y = g.tensor("y", &[1, 1, 4, 1], None);
    g.op(RESIZE_BILINEAR, &[x, size], y, Options::Resize);
    g.input(x);
    g.output(y);
    let got = run_nhwc(&g.finish(), [1, 1, 2, 1], vec![0.0, 1.0], device);
    assert_close_to_scale(&got, &[0.0, 0.25, 0.75, 1.0], 1e-6, "half-pixel resize");

    // DEPTH_TO_SPACE 2 on two pixels of four channels: each pixel's channels become a 2 × 2
    // block, row by row.
    let mut g = TestGraph::new();
    let x = g.tensor("x", &[1, 1, 2, 4], None);
    let y = g.tensor("y", &[1, 2, 4, 1], None);
    g.op(DEPTH_TO_SPACE, &[x], y, Options::DepthToSpace(2));
    g.input(x);
    g.output(y);
    let got = run_nhwc(
        &g.finish(),
        [1, 1, 2, 4],
        (0..8).map(|v| v as f32).collect(),
        device,
    );
    assert_eq!(
        got,
        [0.0, 1.0, 4.0, 5.0, 2.0, 3.0, 6.0, 7.0],
        "depth to space"
    );

    // AVERAGE_POOL_2D 2 × 2 SAME: the padded column and row are left out of the averages.
    let mut g = TestGraph::new();
    let x = g.tensor("x", &[1, 2, 2, 1], None);
    let y = g.tensor("y", &[1, 2, 2, 1], None);
    g.op(
        AVERAGE_POOL_2D,
        &[x],
        y,
        Options::Pool {
            same: true,
            stride: 1,
            filter: 2,
        },
    );
    g.input(x);
    g.output(y);
    let got = run_nhwc(&g.finish(), [1, 2, 2, 1], vec![1.0, 2.0, 3.0, 4.0], device);
    assert_close_to_scale(&got, &[2.5, 3.0, 3.5, 4.0], 1e-6, "average pool");
}

/// Every operator in one graph: it loads, declares what it computes, and gives the same
/// values on this backend as on Flex.
fn every_operator(device: &Device) {
    let bytes = small_graph();
    let graph = Graph::from_bytes("small.tflite", &bytes, device).unwrap();
    let inputs = graph.inputs();
    assert_eq!(inputs.len(), 1);
    assert_eq!(inputs[0].shape, [1, 8, 8, 3]);
    let outputs: Vec<_> = graph.outputs().into_iter().map(|o| o.shape).collect();
    assert_eq!(outputs, [vec![1, 8, 8, 2], vec![1, 16]]);
    let x = pattern(192, 9);
    let run = |device: &Device| {
        let graph = Graph::from_bytes("small.tflite", &bytes, device).unwrap();
        let t = Tensor::<4>::from_data(TensorData::new(x.clone(), [1, 8, 8, 3]), device)
            .permute([0, 3, 1, 2]);
        graph
            .run(vec![t])
            .unwrap()
            .iter()
            .map(|o| o.to_vec().unwrap())
            .collect::<Vec<_>>()
    };
    let got = run(device);
    let want = run(&Device::flex());
    for (k, (g, w)) in got.iter().zip(&want).enumerate() {
        assert!(g.iter().all(|v| v.is_finite()), "output {k} finite");
        assert_close_to_scale(g, w, 1e-5, &format!("output {k} against Flex"));
    }
    // The image output went through LOGISTIC: strictly inside (0, 1), and not constant.
    assert!(got[0].iter().all(|&v| v > 0.0 && v < 1.0));
    assert!(got[0].iter().any(|&v| (v - got[0][0]).abs() > 1e-3));
}

fn errors_name_the_graph_and_operator(device: &Device) {
    let mut g = TestGraph::new();
    let x = g.tensor("x", &[1, 4], None);
    let w = g.tensor("w", &[2, 4], Some(Data::F32(vec![0.0; 8])));
    let y = g.tensor("y", &[1, 2], None);
    g.op(FULLY_CONNECTED, &[x, w], y, Options::None);
    g.input(x);
    g.output(y);
    let err = Graph::from_bytes("fc.tflite", &g.finish(), device).unwrap_err();
    let text = err.to_string();
    assert!(matches!(err, TfliteError::Operator { .. }), "{text}");
    assert!(
        text.contains("fc.tflite") && text.contains("FULLY_CONNECTED"),
        "{text}"
    );

    // A declared shape the operator does not make.
    let text = Graph::from_bytes("conv.tflite", &stride_two_box_conv(&[1, 3, 3, 1]), device)
        .unwrap_err()
        .to_string();
    assert!(
        text.contains("conv.tflite") && text.contains("CONV_2D"),
        "{text}"
    );

    // Inputs of the wrong shape are refused before anything runs.
    let graph = Graph::from_bytes("small.tflite", &small_graph(), device).unwrap();
    let wrong = Tensor::<4>::zeros([1, 3, 8, 7], device);
    let text = graph.run(vec![wrong]).unwrap_err().to_string();
    assert!(
        text.contains("small.tflite") && text.contains("input 0"),
        "{text}"
    );

    // Every cut of a valid file is an error naming it, never a panic.
    let bytes = small_graph();
    for cut in (0..bytes.len()).step_by(97) {
        let err = Graph::from_bytes("cut.tflite", &bytes[..cut], device).unwrap_err();
        assert!(err.to_string().contains("cut.tflite"), "{err}");
    }
}

lifegom_render::cpu_backend_tests!(
    hand_checked_values,
    every_operator,
    errors_name_the_graph_and_operator
);

#[test]
fn on_wgpu() {
    if let Some(device) = wgpu_test_device() {
        hand_checked_values(&device);
        every_operator(&device);
        errors_name_the_graph_and_operator(&device);
    }
}
