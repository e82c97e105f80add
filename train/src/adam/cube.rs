//! The fused Adam step on Burn's CubeCL backend: one thread per parameter element reads the
//! parameter, its gradient and both moments and writes all three back, in the order of Burn's
//! op-by-op update (`m·β₁ + g·(1 − β₁)`, `v·β₂ + g²·(1 − β₂)`, `p − (m·c / (√v + ε'))·lr`).
//! A thread whose gradient is NaN or infinite also stores 1 into the one-element `watch`
//! buffer, which the op hands back as its fourth output: every writer stores the same value, so
//! the race between them is harmless, and a finite gradient writes nothing.

use burn::backend::TensorMetadata;
use burn::backend::tensor::FloatTensor;
use burn_cubecl::CubeBackend;
use burn_cubecl::cubecl;
use burn_cubecl::cubecl::prelude::*;
use lifegom_render::cube::host::{
    THREADS_1D, arg, cast_to, count_1d, prepare, tensor_arg, tensor_f32,
};

use super::op::{AdamScalars, AdamStepOps, MomentInputs};

/// One thread per element. With `first` (≠ 0) the moments' inputs are not read: they start at
/// zero ([`MomentInputs::Zero`]).
#[cube(launch)]
#[allow(clippy::too_many_arguments)]
fn adam_step_kernel(
    param: &[f32],
    grad: &[f32],
    moment_1: &[f32],
    moment_2: &[f32],
    param_out: &mut [f32],
    moment_1_out: &mut [f32],
    moment_2_out: &mut [f32],
    watch: &mut [f32],
    units: usize,
    first: u32,
    beta_1: f32,
    one_minus_beta_1: f32,
    beta_2: f32,
    one_minus_beta_2: f32,
    moment_factor: f32,
    epsilon: f32,
    lr: f32,
) {
    let i = ABSOLUTE_POS;
    if i < units {
        let g = grad[i];
        if f32::is_nan(g) || f32::is_inf(g) {
            watch[0] = 1.0;
        }
        let mut m = g * one_minus_beta_1;
        let mut v = (g * g) * one_minus_beta_2;
        if first == 0 {
            // Float addition commutes: the same sums as Burn's `m·β₁ + g·(1 − β₁)`.
            m += moment_1[i] * beta_1;
            v += moment_2[i] * beta_2;
        }
        moment_1_out[i] = m;
        moment_2_out[i] = v;
        let update = (m * moment_factor) / (f32::sqrt(v) + epsilon);
        param_out[i] = param[i] - update * lr;
    }
}

impl AdamStepOps for CubeBackend {
    fn adam_step(
        param: FloatTensor<Self>,
        grad: FloatTensor<Self>,
        moment_1: FloatTensor<Self>,
        moment_2: FloatTensor<Self>,
        watch: FloatTensor<Self>,
        inputs: MomentInputs,
        s: AdamScalars,
    ) -> (
        FloatTensor<Self>,
        FloatTensor<Self>,
        FloatTensor<Self>,
        FloatTensor<Self>,
    ) {
        let dtype = param.dtype();
        let shape = param.shape();
        let n = shape.num_elements();
        let (client, device) = (param.client.clone(), param.device.clone());
        let param = prepare(param);
        let grad = prepare(grad);
        let (first, moment_1, moment_2) = match inputs {
            MomentInputs::Zero => (1u32, grad.clone(), grad.clone()),
            MomentInputs::Given => (0u32, prepare(moment_1), prepare(moment_2)),
        };
        let watch = prepare(watch);
        let outputs = [(); 3].map(|()| client.empty(4 * n.max(1)));
        if n > 0 {
            adam_step_kernel::launch(
                &client,
                count_1d(n),
                CubeDim::new_1d(THREADS_1D),
                tensor_arg(&param),
                tensor_arg(&grad),
                tensor_arg(&moment_1),
                tensor_arg(&moment_2),
                arg(&outputs[0], n),
                arg(&outputs[1], n),
                arg(&outputs[2], n),
                tensor_arg(&watch),
                n,
                first,
                s.beta_1,
                s.one_minus_beta_1,
                s.beta_2,
                s.one_minus_beta_2,
                s.moment_factor,
                s.epsilon,
                s.lr,
            );
        }
        let [p, m, v] = outputs.map(|h| cast_to(tensor_f32(&client, &device, h, &shape), dtype));
        (p, m, v, watch)
    }
}
