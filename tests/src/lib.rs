//! Shared helpers for lifegom's cross-crate test suites (`tests/tests/*.rs`): seeded random
//! numbers, tiny scenes, and the "finite outputs and finite gradients" check.

#![allow(deprecated)] // Device::ndarray() is deprecated in Burn 0.22; CI tests it on purpose.

use burn::tensor::{Device, Tensor, TensorData};
use lifegom_render::camera::{Camera, Intrinsics};
use lifegom_render::rasterizer::{Gaussians, RasterSettings, Rendered, rasterize};

/// The CPU devices every suite runs on.
pub fn cpu_devices() -> [(&'static str, Device); 2] {
    [("ndarray", Device::ndarray()), ("flex", Device::flex())]
}

pub use lifegom_render::testing::Rng;

/// A camera at `eye` looking at the origin with focal `f` and a centred principal point.
pub fn camera(eye: glam::Vec3, width: u32, height: u32, f: f32) -> Camera {
    let k = Intrinsics {
        fx: f,
        fy: f,
        cx: width as f32 / 2.0,
        cy: height as f32 / 2.0,
    };
    Camera::look_at(eye, glam::Vec3::ZERO, glam::Vec3::Y, k, width, height)
        .expect("valid test camera")
}

/// A `[rows, cols]` tensor from a flat vector.
pub fn tensor2(values: Vec<f32>, cols: usize, device: &Device) -> Tensor<2> {
    let rows = values.len().checked_div(cols).unwrap_or(0);
    Tensor::from_data(TensorData::new(values, [rows, cols]), device)
}

/// Host copy of a tensor.
pub fn read<const D: usize>(t: Tensor<D>) -> Vec<f32> {
    t.into_data().try_into_vec_as::<f32>().expect("f32 data")
}

/// Asserts every value is finite, naming what and where.
pub fn assert_finite(what: &str, values: &[f32]) {
    if let Some(i) = values.iter().position(|v| !v.is_finite()) {
        panic!("{what}: non-finite value {} at {i}", values[i]);
    }
}

/// Renders Gaussians given as host data on `device.autodiff()`, backpropagates a weighted sum
/// of every output channel, and asserts the image and all four input gradients are finite.
/// Returns the image.
pub fn render_finite(
    case: &str,
    device: &Device,
    means: Vec<f32>,
    covariances: Vec<f32>,
    colors: Vec<f32>,
    opacities: Vec<f32>,
    settings: &RasterSettings,
) -> Vec<f32> {
    let ad = device.clone().autodiff();
    let n = opacities.len();
    let g = Gaussians {
        means: tensor2(means, 3, &ad).require_grad(),
        covariances: tensor2(covariances, 6, &ad).require_grad(),
        colors: tensor2(colors, 3, &ad).require_grad(),
        opacities: Tensor::<1>::from_data(TensorData::new(opacities, [n]), &ad).require_grad(),
    };
    let out: Rendered = rasterize(&g, settings).unwrap_or_else(|e| panic!("{case}: {e}"));
    let image = read(out.image.clone());
    assert_finite(&format!("{case}: image"), &image);
    let weights = Tensor::<3>::from_data(
        TensorData::new(
            (0..image.len())
                .map(|i| ((i * 7919) % 13) as f32 / 13.0 - 0.4)
                .collect(),
            out.image.dims(),
        ),
        &ad,
    );
    let grads = (out.image * weights).sum().backward();
    for (name, grad) in [
        ("means", g.means.grad(&grads)),
        ("covariances", g.covariances.grad(&grads)),
        ("colors", g.colors.grad(&grads)),
    ] {
        if let Some(grad) = grad {
            assert_finite(&format!("{case}: d/d{name}"), &read(grad));
        }
    }
    if let Some(grad) = g.opacities.grad(&grads) {
        assert_finite(&format!("{case}: d/dopacities"), &read(grad));
    }
    image
}
