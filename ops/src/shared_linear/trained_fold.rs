//! The fold of a bias-free layer with a BatchNorm whose `γ`, `β` train, on Burn's CubeCL
//! backend (see [`super`] and [`super::op::SharedLinearOps::trained_fold`]).
//!
//! The layer's weight is stored `[out, in]` (a convolution's `[C_out, C·kh·kw]`) and the folded
//! weight is read `[in, out]` by the shared product, so the fold also transposes. With
//! `s = γ/√(σ²+ε)`:
//!
//! ```text
//! W' = Wᵀ·diag(s)            b' = β − μ·s
//! ```
//!
//! The backward starts from the passes' unscaled parameter gradient `[D; ∂b']`, `D = Xᵀ·G`
//! `[in, out]` over every pass's rows (the `gradient` module, without a scale), and gives in one
//! launch, per output channel `c`:
//!
//! ```text
//! ∂W[c, i] = s_c·D[i, c]      ∂β_c = ∂b'_c      ∂γ_c = (Σ_i W[c, i]·D[i, c] − μ_c·∂b'_c) / √(σ²_c+ε)
//! ```
//!
//! since `y = x·W' + b'` depends on `s_c` through `W'`'s column and through `b'`. `∂β` is `∂b'`
//! itself (the bias row of the formed gradient, no launch). One thread per weight element and one
//! per channel, which loops over the channel's `in` products in order.

use burn::backend::TensorMetadata;
use burn::backend::tensor::FloatTensor;
use burn::tensor::DType;
use burn_cubecl::cubecl;
use burn_cubecl::cubecl::prelude::*;
use burn_cubecl::cubecl::server::Handle;
use burn_cubecl::tensor::CubeTensor;
use burn_cubecl::{CubeBackend, CubeDevice};
use lifegom_render::cube::host::{
    ComputeClient, THREADS_1D, arg, cast_to, count_1d, prepare, tensor_arg, tensor_f32,
};

use super::op::FoldKernels;

/// `γ[c]/√(σ²[c]+ε)`.
#[cube]
fn channel_scale(gamma: &[f32], var: &[f32], c: usize, epsilon: f32) -> f32 {
    gamma[c] / f32::sqrt(var[c] + epsilon)
}

#[cube(launch)]
#[allow(clippy::too_many_arguments)]
fn trained_fold_kernel(
    weight: &[f32],
    gamma: &[f32],
    beta: &[f32],
    mean: &[f32],
    var: &[f32],
    weight_out: &mut [f32],
    bias_out: &mut [f32],
    weights: usize,
    ins: usize,
    outs: usize,
    epsilon: f32,
) {
    let e = ABSOLUTE_POS;
    if e < weights {
        // `e` indexes the folded weight `[in, out]`.
        let (i, c) = (e / outs, e % outs);
        weight_out[e] = weight[c * ins + i] * channel_scale(gamma, var, c, epsilon);
    } else if e < weights + outs {
        let c = e - weights;
        bias_out[c] = beta[c] - mean[c] * channel_scale(gamma, var, c, epsilon);
    }
}

#[cube(launch)]
#[allow(clippy::too_many_arguments)]
fn trained_fold_backward_kernel(
    formed: &[f32],
    formed_bias: &[f32],
    weight: &[f32],
    gamma: &[f32],
    mean: &[f32],
    var: &[f32],
    weight_grad: &mut [f32],
    gamma_grad: &mut [f32],
    weights: usize,
    ins: usize,
    outs: usize,
    epsilon: f32,
) {
    let e = ABSOLUTE_POS;
    if e < weights {
        // `e` indexes the weight `[out, in]` as stored.
        let (c, i) = (e / ins, e % ins);
        weight_grad[e] = formed[i * outs + c] * channel_scale(gamma, var, c, epsilon);
    } else if e < weights + outs {
        let c = e - weights;
        let mut acc = 0.0f32;
        for i in 0..ins {
            acc += weight[c * ins + i] * formed[i * outs + c];
        }
        let bias_grad = formed_bias[c];
        gamma_grad[c] = (acc - mean[c] * bias_grad) / f32::sqrt(var[c] + epsilon);
    }
}

/// The two outputs of a fold's launch, forward or backward: one the weight's size and one per
/// output channel, and the sizes the kernels take (`weights = in·out`, `ins`, `outs`).
struct FoldOutputs {
    client: ComputeClient,
    device: CubeDevice,
    dtype: DType,
    weights: usize,
    ins: usize,
    outs: usize,
    weight: Handle,
    channel: Handle,
}

impl FoldOutputs {
    /// Buffers for a layer whose weight `like` is stored `[out, in]`.
    fn for_weight(like: &CubeTensor) -> Self {
        let shape = like.shape();
        let (outs, ins) = (shape[0], shape[1]);
        let client = like.client.clone();
        Self {
            weight: client.empty(4 * (ins * outs).max(1)),
            channel: client.empty(4 * outs.max(1)),
            device: like.device.clone(),
            dtype: like.dtype(),
            client,
            weights: ins * outs,
            ins,
            outs,
        }
    }

    /// One thread per weight element and one per channel.
    fn units(&self) -> CubeCount {
        count_1d(self.weights + self.outs)
    }

    /// The weight-sized output as `weight_shape` and the per-channel one.
    fn finish(
        self,
        weight_shape: [usize; 2],
    ) -> (FloatTensor<CubeBackend>, FloatTensor<CubeBackend>) {
        let Self {
            client,
            device,
            dtype,
            weight,
            channel,
            outs,
            ..
        } = self;
        (
            cast_to(tensor_f32(&client, &device, weight, &weight_shape), dtype),
            cast_to(tensor_f32(&client, &device, channel, &[outs]), dtype),
        )
    }
}

/// `(Wᵀ·diag(s), β − μ·s)` for `weight` `[out, in]` and `γ`, `β`, `μ`, `σ²` `[out]` (module
/// docs): one launch.
pub(super) fn trained_fold(
    weight: FloatTensor<CubeBackend>,
    gamma: FloatTensor<CubeBackend>,
    beta: FloatTensor<CubeBackend>,
    mean: FloatTensor<CubeBackend>,
    var: FloatTensor<CubeBackend>,
    epsilon: f32,
) -> (FloatTensor<CubeBackend>, FloatTensor<CubeBackend>) {
    let [weight, gamma, beta, mean, var] = [weight, gamma, beta, mean, var].map(prepare);
    let out = FoldOutputs::for_weight(&weight);
    if out.weights + out.outs > 0 {
        trained_fold_kernel::launch(
            &out.client,
            out.units(),
            CubeDim::new_1d(THREADS_1D),
            tensor_arg(&weight),
            tensor_arg(&gamma),
            tensor_arg(&beta),
            tensor_arg(&mean),
            tensor_arg(&var),
            arg(&out.weight, out.weights),
            arg(&out.channel, out.outs),
            out.weights,
            out.ins,
            out.outs,
            epsilon,
        );
    }
    let shape = [out.ins, out.outs];
    out.finish(shape)
}

impl FoldKernels for CubeBackend {
    fn trained_fold_backward(
        formed: FloatTensor<Self>,
        formed_bias: FloatTensor<Self>,
        weight: FloatTensor<Self>,
        gamma: FloatTensor<Self>,
        mean: FloatTensor<Self>,
        var: FloatTensor<Self>,
        epsilon: f32,
    ) -> (FloatTensor<Self>, FloatTensor<Self>) {
        let [formed, formed_bias, weight, gamma, mean, var] =
            [formed, formed_bias, weight, gamma, mean, var].map(prepare);
        let out = FoldOutputs::for_weight(&weight);
        assert!(
            formed.shape().dims::<2>() == [out.ins, out.outs]
                && formed_bias.shape().num_elements() == out.outs,
            "a trained fold's gradient is `∂W'` [in, out] and its bias row [out]"
        );
        if out.weights + out.outs > 0 {
            trained_fold_backward_kernel::launch(
                &out.client,
                out.units(),
                CubeDim::new_1d(THREADS_1D),
                tensor_arg(&formed),
                tensor_arg(&formed_bias),
                tensor_arg(&weight),
                tensor_arg(&gamma),
                tensor_arg(&mean),
                tensor_arg(&var),
                arg(&out.weight, out.weights),
                arg(&out.channel, out.outs),
                out.weights,
                out.ins,
                out.outs,
                epsilon,
            );
        }
        let shape = [out.outs, out.ins];
        out.finish(shape)
    }
}
