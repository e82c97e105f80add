//! The fold of a layer with the frozen BatchNorm after it on Burn's CubeCL backend, in one
//! launch (see [`super`]): one thread per element of the weight `[in, out]` and one per output
//! channel. Each computes its channel's `s = γ/√(σ²+ε)` itself (a few flops, where a separate
//! launch for `s` would cost more); the channel threads also write `s` and the folded bias
//! `b·s + t`, `t = β − μ·s`. The order of the float operations is that of the composed ops
//! (`crate::norm_folds`), so both give the same values.

use burn::backend::TensorMetadata;
use burn::backend::tensor::FloatTensor;
use burn_cubecl::CubeBackend;
use burn_cubecl::cubecl;
use burn_cubecl::cubecl::prelude::*;
use lifegom_render::cube::host::{
    THREADS_1D, arg, cast_to, count_1d, prepare, tensor_arg, tensor_f32,
};

use super::op::{FoldBias, Ledger, SharedLinearOps};
use crate::activation::Activation;
use crate::handoff::Handoff;

/// `γ[c]/√(σ²[c]+ε)`.
#[cube]
pub(super) fn channel_scale(gamma: &[f32], var: &[f32], c: usize, epsilon: f32) -> f32 {
    gamma[c] / f32::sqrt(var[c] + epsilon)
}

#[cube(launch)]
#[allow(clippy::too_many_arguments)]
fn fold_kernel(
    weight: &[f32],
    bias: &[f32],
    gamma: &[f32],
    beta: &[f32],
    mean: &[f32],
    var: &[f32],
    weight_out: &mut [f32],
    bias_out: &mut [f32],
    scale_out: &mut [f32],
    weights: usize,
    out: usize,
    has_bias: u32,
    epsilon: f32,
) {
    let e = ABSOLUTE_POS;
    if e < weights {
        weight_out[e] = weight[e] * channel_scale(gamma, var, e % out, epsilon);
    } else if e < weights + out {
        let c = e - weights;
        let s = channel_scale(gamma, var, c, epsilon);
        let shift = beta[c] - mean[c] * s;
        scale_out[c] = s;
        if has_bias != 0 {
            bias_out[c] = bias[c] * s + shift;
        } else {
            bias_out[c] = shift;
        }
    }
}

impl SharedLinearOps for CubeBackend {
    fn shared_linear(
        x: FloatTensor<Self>,
        weight: FloatTensor<Self>,
        bias: FloatTensor<Self>,
        _ledger: Ledger,
        activation: Activation,
        _handoff: Handoff,
    ) -> FloatTensor<Self> {
        super::product::affine(x, weight, bias, None, activation)
    }

    fn shared_linear_residual(
        x: FloatTensor<Self>,
        weight: FloatTensor<Self>,
        bias: FloatTensor<Self>,
        residual: FloatTensor<Self>,
        _ledger: Ledger,
        _handoff: Handoff,
    ) -> FloatTensor<Self> {
        super::product::affine(x, weight, bias, Some(residual), Activation::Relu)
    }

    fn trained_fold(
        weight: FloatTensor<Self>,
        gamma: FloatTensor<Self>,
        beta: FloatTensor<Self>,
        mean: FloatTensor<Self>,
        var: FloatTensor<Self>,
        epsilon: f32,
        _ledger: Ledger,
    ) -> (FloatTensor<Self>, FloatTensor<Self>) {
        super::trained_fold::trained_fold(weight, gamma, beta, mean, var, epsilon)
    }

    fn shared_fold(
        weight: FloatTensor<Self>,
        bias: FloatTensor<Self>,
        gamma: FloatTensor<Self>,
        beta: FloatTensor<Self>,
        mean: FloatTensor<Self>,
        var: FloatTensor<Self>,
        kind: FoldBias,
        epsilon: f32,
        _ledger: Ledger,
    ) -> (FloatTensor<Self>, FloatTensor<Self>, FloatTensor<Self>) {
        let dtype = weight.dtype();
        let shape = weight.shape();
        let (d_in, d_out) = (shape[0], shape[1]);
        let (client, device) = (weight.client.clone(), weight.device.clone());
        let [weight, bias, gamma, beta, mean, var] =
            [weight, bias, gamma, beta, mean, var].map(prepare);
        let weights = d_in * d_out;
        let weight_out = client.empty(4 * weights.max(1));
        let [bias_out, scale_out] = [(); 2].map(|()| client.empty(4 * d_out.max(1)));
        let units = weights + d_out;
        if units > 0 {
            fold_kernel::launch(
                &client,
                count_1d(units),
                CubeDim::new_1d(THREADS_1D),
                tensor_arg(&weight),
                tensor_arg(&bias),
                tensor_arg(&gamma),
                tensor_arg(&beta),
                tensor_arg(&mean),
                tensor_arg(&var),
                arg(&weight_out, weights),
                arg(&bias_out, d_out),
                arg(&scale_out, d_out),
                weights,
                d_out,
                u32::from(kind == FoldBias::Given),
                epsilon,
            );
        }
        let vector = |h| cast_to(tensor_f32(&client, &device, h, &[d_out]), dtype);
        (
            cast_to(
                tensor_f32(&client, &device, weight_out, &[d_in, d_out]),
                dtype,
            ),
            vector(bias_out),
            vector(scale_out),
        )
    }
}
