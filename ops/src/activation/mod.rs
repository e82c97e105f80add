//! ReLU with one kernel each way on GPU devices when Burn's kernel fusion is off.
//!
//! Burn 0.22.1's CubeCL backend has no ReLU kernel: its default `relu` is a comparison and a
//! masked fill (two launches), and so is `relu_backward`. The model applies ReLU about a hundred
//! times a training step (encoder, Point Transformer, fusion feed-forward, heads), so on a GPU
//! that was about 1,100 of a quickstart step's launches (BENCHMARKS.md, "Kernel launches per
//! training step"). [`relu`] is:
//! - on the CPU backends exactly Burn's `relu` (numerics unchanged);
//! - on CubeCL devices with Burn's kernel fusion on (the default, [`KernelFusion`]) Burn's `relu`
//!   too: fusion merges its two ops into the kernel of the ops around it, where a custom op
//!   would stand between them as a kernel of its own (a quickstart step launched 7,248 kernels
//!   so, 7,841 with the op; BENCHMARKS.md);
//! - on CubeCL devices with fusion off the [`op::ReluOps`] extension: one elementwise kernel
//!   forward and one backward (`cube`), with Burn's semantics to the bit (`x ≤ 0 → 0`, NaN
//!   passes; the backward zeroes the gradient where the output is `≤ 0`).
//!
//! The fusion-off path stays because `tools/gpu-figures.sh` times fusion on against fusion off
//! on a card; the backward kernel serves the shared layers too (`crate::shared_linear`, a ReLU's
//! mask when no `∂x` is wanted).

pub(crate) mod cube;
pub mod op;

use burn::tensor::Tensor;
use lifegom_render::device::{KernelFusion, runs_on_host};

/// What a layer applies after its affine map, inside the op's own launch where the op has one
/// (the encoder's norms, [`crate::channel_norm`]; the shared layers' products,
/// [`crate::shared_linear`]).
///
/// Kernels take it as a compile-time argument and `match` on it (`cube::activate`,
/// `cube::activation_gradient`), and host code matches on it too, never comparing with one
/// variant: a new variant fails to compile until every kernel and op handles it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Activation {
    /// Nothing.
    Identity,
    /// Burn's ReLU, `max(·, 0)` (NaN passes); its gradient passes where the output is positive.
    Relu,
}

/// `max(x, 0)` elementwise, Burn's `relu` (module docs).
pub fn relu<const D: usize>(x: Tensor<D>) -> Tensor<D> {
    if runs_on_host(&x.device()) || KernelFusion::current() == KernelFusion::On {
        return burn::tensor::activation::relu(x);
    }
    relu_op(x)
}

/// The [`op::ReluOps`] extension, whatever the device (CPU backends do not implement it).
fn relu_op<const D: usize>(x: Tensor<D>) -> Tensor<D> {
    Tensor::from_dispatch(<burn::backend::Dispatch as op::ReluOps>::fused_relu(
        x.into_dispatch(),
    ))
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::tensor::{Device, TensorData};
    use lifegom_render::testing::read;

    /// [`relu`] (on GPU devices the op itself, whether or not fusion would route around it)
    /// equals Burn's `relu` computed on Flex, values and gradient, on positive, negative and
    /// zero inputs and a non-contiguous view.
    fn check_matches_burn(device: &Device) {
        let values: Vec<f32> = (0..60)
            .map(|i| (i as f32 - 29.5) * 0.37)
            .chain([0.0, -0.0])
            .collect();
        let n = values.len();
        let weight: Vec<f32> = (0..n).map(|i| (i % 7) as f32 - 3.0).collect();
        let run = |device: &Device, ours: bool| {
            let ad = device.clone().autodiff();
            let x = Tensor::<2>::from_data(TensorData::new(values.clone(), [2, n / 2]), &ad)
                .require_grad();
            // A transposed view: the op must not assume contiguous input.
            let xt = x.clone().transpose();
            let y = if ours && !runs_on_host(device) {
                relu_op(xt)
            } else if ours {
                relu(xt)
            } else {
                burn::tensor::activation::relu(xt)
            };
            let w = Tensor::<2>::from_data(TensorData::new(weight.clone(), [n / 2, 2]), &ad);
            let grads = (y.clone() * w).sum().backward();
            (read(y), read(x.grad(&grads).expect("input gradient")))
        };
        let (want_y, want_g) = run(&Device::flex(), false);
        let (got_y, got_g) = run(device, true);
        assert_eq!(got_y, want_y, "values on {device:?}");
        assert_eq!(got_g, want_g, "gradient on {device:?}");
    }

    lifegom_render::cpu_backend_tests!(relu_matches_burn => check_matches_burn);

    #[test]
    fn relu_matches_burn_wgpu() {
        if let Some(device) = lifegom_render::testing::wgpu_test_device() {
            check_matches_burn(&device);
        }
    }
}
