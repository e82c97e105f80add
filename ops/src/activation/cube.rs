//! ReLU on Burn's CubeCL backend: one thread per element each way; and the [`Activation`] the
//! other ops' kernels end with.

use burn::backend::TensorMetadata;
use burn::backend::tensor::FloatTensor;
use burn_cubecl::CubeBackend;
use burn_cubecl::cubecl;
use burn_cubecl::cubecl::prelude::*;
use lifegom_render::cube::host::{
    THREADS_1D, arg, cast_to, count_1d, prepare, tensor_arg, tensor_f32,
};

use super::Activation;
use super::op::{ReluKernels, ReluOps};

/// `activation(v)`, in a kernel's epilogue. The match is exhaustive: a new [`Activation`] fails
/// to compile here until the kernels know it.
#[cube]
pub(crate) fn activate(v: f32, #[comptime] activation: Activation) -> f32 {
    match activation {
        Activation::Identity => v,
        // Burn's ReLU: `v ≤ 0 → 0`, NaN passes.
        Activation::Relu => select(v <= 0.0f32, 0.0f32, v),
    }
}

/// The gradient `g` of `activation(y)` carried back to `y`, for the activation's input `y`.
#[cube]
pub(crate) fn activation_gradient(y: f32, g: f32, #[comptime] activation: Activation) -> f32 {
    match activation {
        Activation::Identity => g,
        Activation::Relu => select(y <= 0.0f32, 0.0f32, g),
    }
}

/// `x ≤ 0 → 0`, else `x` (NaN passes), as Burn's comparison and masked fill.
#[cube(launch)]
fn relu_forward_kernel(x: &[f32], out: &mut [f32], units: usize) {
    let i = ABSOLUTE_POS;
    if i < units {
        let v = x[i];
        out[i] = select(v <= 0.0f32, 0.0f32, v);
    }
}

/// `output ≤ 0 → 0`, else the gradient.
#[cube(launch)]
fn relu_backward_kernel(output: &[f32], grad: &[f32], out: &mut [f32], units: usize) {
    let i = ABSOLUTE_POS;
    if i < units {
        out[i] = select(output[i] <= 0.0f32, 0.0f32, grad[i]);
    }
}

impl ReluOps for CubeBackend {
    fn fused_relu(x: FloatTensor<Self>) -> FloatTensor<Self> {
        let dtype = x.dtype();
        let shape = x.shape();
        let n = shape.num_elements();
        let (client, device) = (x.client.clone(), x.device.clone());
        let x = prepare(x);
        let out = client.empty(4 * n.max(1));
        if n > 0 {
            relu_forward_kernel::launch(
                &client,
                count_1d(n),
                CubeDim::new_1d(THREADS_1D),
                tensor_arg(&x),
                arg(&out, n),
                n,
            );
        }
        cast_to(tensor_f32(&client, &device, out, &shape), dtype)
    }
}

impl ReluKernels for CubeBackend {
    fn fused_relu_backward(
        output: FloatTensor<Self>,
        grad: FloatTensor<Self>,
    ) -> FloatTensor<Self> {
        let dtype = grad.dtype();
        let shape = grad.shape();
        let n = shape.num_elements();
        let (client, device) = (grad.client.clone(), grad.device.clone());
        let output = prepare(output);
        let grad = prepare(grad);
        let out = client.empty(4 * n.max(1));
        if n > 0 {
            relu_backward_kernel::launch(
                &client,
                count_1d(n),
                CubeDim::new_1d(THREADS_1D),
                tensor_arg(&output),
                tensor_arg(&grad),
                arg(&out, n),
                n,
            );
        }
        cast_to(tensor_f32(&client, &device, out, &shape), dtype)
    }
}
