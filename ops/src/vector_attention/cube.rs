//! The vector-attention aggregation on Burn's CubeCL backend: one thread per point and weight
//! channel `(i, j)` in both kernels.
//!
//! - `aggregate_forward_kernel`: the softmax over the `k` neighbours, shifted by their maximum as Burn's
//!   `softmax` is (`exp(w − max) / Σ exp(w − max)`), then for each of the `S` value channels
//!   sharing weight channel `j` the weighted sum of the neighbours' values.
//! - `aggregate_backward_kernel`: recomputes the softmax `p`, then writes `∂v[i, κ, s, j] = p_κ·g[i, s, j]`
//!   and the softmax's backward `∂w[i, κ, j] = p_κ·(a_κ − Σ_λ p_λ·a_λ)` with
//!   `a_κ = Σ_s g[i, s, j]·v[i, κ, s, j]`. Each thread owns its outputs: no atomics.

use burn::backend::TensorMetadata;
use burn::backend::tensor::FloatTensor;
use burn_cubecl::CubeBackend;
use burn_cubecl::cubecl;
use burn_cubecl::cubecl::prelude::*;
use lifegom_render::cube::host::{
    THREADS_1D, arg, cast_to, count_1d, prepare, tensor_arg, tensor_f32,
};

use super::op::{VectorAttentionKernels, VectorAttentionOps};

/// The maximum over the neighbours of logit channel `j` of point `i`, and the softmax's sum.
#[derive(CubeType, Clone, Copy)]
pub(super) struct SoftmaxScale {
    pub(super) max: f32,
    pub(super) sum: f32,
}

#[cube]
pub(super) fn softmax_scale(
    logits: &[f32],
    i: usize,
    j: usize,
    k: usize,
    cs: usize,
) -> SoftmaxScale {
    let base = i * k * cs + j;
    let mut max = logits[base];
    for kk in 1..k {
        max = f32::max(max, logits[base + kk * cs]);
    }
    let mut sum = 0.0f32;
    for kk in 0..k {
        sum += f32::exp(logits[base + kk * cs] - max);
    }
    SoftmaxScale { max, sum }
}

/// `softmax_κ(w[i, ·, j])[κ]` given the neighbours' `scale`.
#[cube]
pub(super) fn probability(
    logits: &[f32],
    scale: &SoftmaxScale,
    i: usize,
    kk: usize,
    j: usize,
    k: usize,
    cs: usize,
) -> f32 {
    f32::exp(logits[(i * k + kk) * cs + j] - scale.max) / scale.sum
}

/// `v[i, κ, s, j]` at its flat index.
#[cube]
fn value_index(i: usize, kk: usize, si: usize, j: usize, k: usize, s: usize, cs: usize) -> usize {
    ((i * k + kk) * s + si) * cs + j
}

/// One thread per `(i, j)`: writes `out[i, s, j]` for every `s`.
#[cube(launch)]
fn aggregate_forward_kernel(
    values: &[f32],
    logits: &[f32],
    out: &mut [f32],
    units: usize,
    k: usize,
    s: usize,
    cs: usize,
) {
    let unit = ABSOLUTE_POS;
    if unit < units {
        let j = unit % cs;
        let i = unit / cs;
        let scale = softmax_scale(logits, i, j, k, cs);
        for si in 0..s {
            let mut acc = 0.0f32;
            for kk in 0..k {
                let p = probability(logits, &scale, i, kk, j, k, cs);
                acc += p * values[value_index(i, kk, si, j, k, s, cs)];
            }
            out[(i * s + si) * cs + j] = acc;
        }
    }
}

/// `a_κ = Σ_s g[i, s, j]·v[i, κ, s, j]`.
#[cube]
#[allow(clippy::too_many_arguments)]
fn weighted_value(
    values: &[f32],
    grad: &[f32],
    i: usize,
    kk: usize,
    j: usize,
    k: usize,
    s: usize,
    cs: usize,
) -> f32 {
    let mut a = 0.0f32;
    for si in 0..s {
        a += grad[(i * s + si) * cs + j] * values[value_index(i, kk, si, j, k, s, cs)];
    }
    a
}

/// One thread per `(i, j)`: writes `∂v[i, ·, ·, j]` and `∂w[i, ·, j]`.
#[cube(launch)]
#[allow(clippy::too_many_arguments)]
fn aggregate_backward_kernel(
    values: &[f32],
    logits: &[f32],
    grad: &[f32],
    values_grad: &mut [f32],
    logits_grad: &mut [f32],
    units: usize,
    k: usize,
    s: usize,
    cs: usize,
) {
    let unit = ABSOLUTE_POS;
    if unit < units {
        let j = unit % cs;
        let i = unit / cs;
        let scale = softmax_scale(logits, i, j, k, cs);
        // Σ_λ p_λ·a_λ, the softmax backward's shared term.
        let mut dot = 0.0f32;
        for kk in 0..k {
            let p = probability(logits, &scale, i, kk, j, k, cs);
            for si in 0..s {
                let v = value_index(i, kk, si, j, k, s, cs);
                values_grad[v] = p * grad[(i * s + si) * cs + j];
            }
            dot += p * weighted_value(values, grad, i, kk, j, k, s, cs);
        }
        for kk in 0..k {
            let p = probability(logits, &scale, i, kk, j, k, cs);
            let a = weighted_value(values, grad, i, kk, j, k, s, cs);
            logits_grad[(i * k + kk) * cs + j] = p * (a - dot);
        }
    }
}

/// `[n, k, S, C/S]` → `(n, k, S, C/S)`.
fn dims4(values: &burn_cubecl::tensor::CubeTensor) -> (usize, usize, usize, usize) {
    let shape = values.shape();
    (shape[0], shape[1], shape[2], shape[3])
}

impl VectorAttentionOps for CubeBackend {
    fn attention_aggregate(
        values: FloatTensor<Self>,
        logits: FloatTensor<Self>,
    ) -> FloatTensor<Self> {
        let _span = tracing::trace_span!("cube_attention_aggregate").entered();
        let dtype = values.dtype();
        let (n, k, s, cs) = dims4(&values);
        let (client, device) = (values.client.clone(), values.device.clone());
        let values = prepare(values);
        let logits = prepare(logits);
        let len = n * s * cs;
        let out = client.empty(4 * len.max(1));
        let units = n * cs;
        if units > 0 && k > 0 {
            aggregate_forward_kernel::launch(
                &client,
                count_1d(units),
                CubeDim::new_1d(THREADS_1D),
                tensor_arg(&values),
                tensor_arg(&logits),
                arg(&out, len),
                units,
                k,
                s,
                cs,
            );
        }
        cast_to(tensor_f32(&client, &device, out, &[n, s, cs]), dtype)
    }
}

impl VectorAttentionKernels for CubeBackend {
    fn attention_aggregate_backward(
        values: FloatTensor<Self>,
        logits: FloatTensor<Self>,
        grad: FloatTensor<Self>,
    ) -> (FloatTensor<Self>, FloatTensor<Self>) {
        let _span = tracing::trace_span!("cube_attention_aggregate_backward").entered();
        let (values_dtype, logits_dtype) = (values.dtype(), logits.dtype());
        let (n, k, s, cs) = dims4(&values);
        let (client, device) = (values.client.clone(), values.device.clone());
        let values = prepare(values);
        let logits = prepare(logits);
        let grad = prepare(grad);
        let (values_len, logits_len) = (n * k * s * cs, n * k * cs);
        let values_grad = client.empty(4 * values_len.max(1));
        let logits_grad = client.empty(4 * logits_len.max(1));
        let units = n * cs;
        if units > 0 && k > 0 {
            aggregate_backward_kernel::launch(
                &client,
                count_1d(units),
                CubeDim::new_1d(THREADS_1D),
                tensor_arg(&values),
                tensor_arg(&logits),
                tensor_arg(&grad),
                arg(&values_grad, values_len),
                arg(&logits_grad, logits_len),
                units,
                k,
                s,
                cs,
            );
        }
        (
            cast_to(
                tensor_f32(&client, &device, values_grad, &[n, k, s, cs]),
                values_dtype,
            ),
            cast_to(
                tensor_f32(&client, &device, logits_grad, &[n, k, cs]),
                logits_dtype,
            ),
        )
    }
}
