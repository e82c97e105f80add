//! Gathers by index whose backward is parallel and correct on CubeCL devices (design.md §5.7).
//!
//! The backward of `Tensor::select` is a `select_assign` with `Add`. Burn 0.22.1's CubeCL kernel
//! for it runs one thread per element *across* the gathered axis, each walking every index in
//! order: gathering 117,792 rows of 144 features is 144 threads of 117,792 serial steps, which
//! made the backward of a GPU training step take most of its time. It also mis-sums from 65,536
//! indices (a test in `tests/tests/backend_parity.rs` gathers 70,000 rows on wgpu). The model
//! gathers rows by index in many places (face corners, feature samples, neighbours), so every
//! differentiable gather goes through [`select_rows`]:
//!
//! - on the CPU backends it is exactly `Tensor::select`, whose backward is correct and fast
//!   there: their numerics do not change by a bit;
//! - on CubeCL devices it is the [`op::RowGatherOps`] extension: the same forward kernel, and a
//!   scatter-add backward with one thread per gradient element and float atomic adds
//!   (`cube` module).

pub(crate) mod cube;
pub mod op;

use burn::tensor::{Int, Tensor};

use crate::device::runs_on_host;

/// `tensor.select(dim, indices)`: the same values and gradients, with a parallel backward on
/// CubeCL devices (module docs).
pub fn select_rows<const D: usize>(
    tensor: Tensor<D>,
    dim: usize,
    indices: Tensor<1, Int>,
) -> Tensor<D> {
    if runs_on_host(&tensor.device()) {
        return tensor.select(dim, indices);
    }
    Tensor::from_dispatch(<burn::backend::Dispatch as op::RowGatherOps>::gather_rows(
        tensor.into_dispatch(),
        dim,
        indices.into_dispatch(),
    ))
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::tensor::{Device, TensorData};

    use crate::testing::{Rng, read, wgpu_test_device};

    /// Values and the source's gradient of `select_rows` against `Tensor::select` computed on
    /// Flex, for a gather along `dim` of a `[3, 5, 4]` source (every axis position: outer,
    /// middle, last), with repeated indices and rows never gathered.
    fn check_gather_matches_select(device: &Device) {
        let shape = [3usize, 5, 4];
        let mut rng = Rng::new(7);
        let values: Vec<f32> = (0..60).map(|_| rng.range_f32(-1.0, 1.0)).collect();
        for dim in 0..3 {
            let rows = shape[dim] as i64;
            let index: Vec<i64> = [0, rows - 1, 1, 1, rows - 1, 0, 1].to_vec();
            let n = index.len();
            let mut out_shape = shape;
            out_shape[dim] = n;
            let weight: Vec<f32> = (0..out_shape.iter().product::<usize>())
                .map(|_| rng.range_f32(-1.0, 1.0))
                .collect();
            let run = |device: &Device, fused: bool| {
                let ad = device.clone().autodiff();
                let x = Tensor::<3>::from_data(TensorData::new(values.clone(), shape), &ad)
                    .require_grad();
                let idx = Tensor::<1, Int>::from_data(TensorData::new(index.clone(), [n]), &ad);
                let w = Tensor::<3>::from_data(TensorData::new(weight.clone(), out_shape), &ad);
                let y = if fused {
                    select_rows(x.clone(), dim, idx)
                } else {
                    x.clone().select(dim, idx)
                };
                let grads = (y.clone() * w).sum().backward();
                (read(y), read(x.grad(&grads).expect("source gradient")))
            };
            let (want_y, want_g) = run(&Device::flex(), false);
            let (got_y, got_g) = run(device, true);
            assert_eq!(got_y, want_y, "values, dim {dim}, on {device:?}");
            for (k, (a, b)) in got_g.iter().zip(&want_g).enumerate() {
                assert!(
                    (a - b).abs() <= 1e-6,
                    "gradient element {k}, dim {dim}, on {device:?}: {a} vs {b}"
                );
            }
        }
    }

    crate::cpu_backend_tests!(gather_matches_select => check_gather_matches_select);

    /// The CubeCL path (the op and its scatter-add backward), on wgpu; with the float atomics
    /// emulated too.
    #[test]
    fn gather_matches_select_wgpu() {
        let Some(device) = wgpu_test_device() else {
            return;
        };
        assert!(!runs_on_host(&device));
        check_gather_matches_select(&device);
        crate::rasterizer::force_emulated_float_atomics(true);
        let result = std::panic::catch_unwind(|| check_gather_matches_select(&device));
        crate::rasterizer::force_emulated_float_atomics(false);
        if let Err(panic) = result {
            std::panic::resume_unwind(panic);
        }
    }
}
