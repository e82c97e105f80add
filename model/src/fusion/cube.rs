//! The residual LayerNorm `LN(x + r)·γ + β` on Burn's CubeCL backend (design.md §7.4): the same
//! formulas as the CPU slice code (`super::kernels`) in `f32`, in three kernels.
//!
//! - `forward_kernel`: one thread per row computes the row's mean and `1/√(var + ε)` of
//!   `z = x + r` and writes the normalised, scaled and shifted row.
//! - `rows_backward_kernel`: one thread per row recomputes its statistics, writes them for the
//!   next kernel and writes `∂z = rstd·(a − mean(a) − x̂·mean(a·x̂))` with `a = g·γ`.
//! - `columns_backward_kernel`: one thread per channel sums `g·x̂` and `g` over the rows in
//!   order: `∂γ` and `∂β`, with no atomics.
//!
//! Burn's `LayerNorm` composition is about ten launches forward and fifteen backward per call.

use burn::backend::TensorMetadata;
use burn::backend::tensor::FloatTensor;
use burn_cubecl::CubeBackend;
use burn_cubecl::cubecl;
use burn_cubecl::cubecl::prelude::*;
use lifegom_render::cube::host::{
    THREADS_1D, arg, cast_to, count_1d, prepare, tensor_arg, tensor_f32,
};

use super::op::{AddLayerNormOps, LayerNormEpsilon, LayerNormInputs, LayerNormKernels};

/// A row's mean and reciprocal standard deviation.
#[derive(CubeType, Clone, Copy)]
struct RowStats {
    mean: f32,
    rstd: f32,
}

#[cube]
fn row_stats(x: &[f32], r: &[f32], row: usize, d: usize, epsilon: f32) -> RowStats {
    let base = row * d;
    let mut sum = 0.0f32;
    for c in 0..d {
        sum += x[base + c] + r[base + c];
    }
    let mean = sum / f32::cast_from(d);
    let mut deviation = 0.0f32;
    for c in 0..d {
        let centred = x[base + c] + r[base + c] - mean;
        deviation += centred * centred;
    }
    let var = deviation / f32::cast_from(d);
    RowStats {
        mean,
        rstd: 1.0f32 / f32::sqrt(var + epsilon),
    }
}

/// One thread per row.
#[cube(launch)]
#[allow(clippy::too_many_arguments)]
fn forward_kernel(
    x: &[f32],
    r: &[f32],
    gamma: &[f32],
    beta: &[f32],
    out: &mut [f32],
    rows: usize,
    d: usize,
    epsilon: f32,
) {
    let row = ABSOLUTE_POS;
    if row < rows {
        let stats = row_stats(x, r, row, d, epsilon);
        let base = row * d;
        for c in 0..d {
            let z = x[base + c] + r[base + c];
            out[base + c] = (z - stats.mean) * stats.rstd * gamma[c] + beta[c];
        }
    }
}

/// One thread per row: `∂z` and the row's statistics (`stats[2·row]`, `stats[2·row + 1]`).
#[cube(launch)]
#[allow(clippy::too_many_arguments)]
fn rows_backward_kernel(
    x: &[f32],
    r: &[f32],
    gamma: &[f32],
    grad: &[f32],
    dz: &mut [f32],
    stats_out: &mut [f32],
    rows: usize,
    d: usize,
    epsilon: f32,
) {
    let row = ABSOLUTE_POS;
    if row < rows {
        let stats = row_stats(x, r, row, d, epsilon);
        stats_out[2 * row] = stats.mean;
        stats_out[2 * row + 1] = stats.rstd;
        let base = row * d;
        let mut sum_a = 0.0f32;
        let mut sum_ax = 0.0f32;
        for c in 0..d {
            let xhat = (x[base + c] + r[base + c] - stats.mean) * stats.rstd;
            let a = grad[base + c] * gamma[c];
            sum_a += a;
            sum_ax += a * xhat;
        }
        let n = f32::cast_from(d);
        let mean_a = sum_a / n;
        let mean_ax = sum_ax / n;
        for c in 0..d {
            let xhat = (x[base + c] + r[base + c] - stats.mean) * stats.rstd;
            let a = grad[base + c] * gamma[c];
            dz[base + c] = stats.rstd * (a - mean_a - xhat * mean_ax);
        }
    }
}

/// One thread per channel: `∂γ[c] = Σ_rows g·x̂`, `∂β[c] = Σ_rows g`.
#[cube(launch)]
#[allow(clippy::too_many_arguments)]
fn columns_backward_kernel(
    x: &[f32],
    r: &[f32],
    grad: &[f32],
    stats: &[f32],
    dgamma: &mut [f32],
    dbeta: &mut [f32],
    rows: usize,
    d: usize,
) {
    let c = ABSOLUTE_POS;
    if c < d {
        let mut sum_gx = 0.0f32;
        let mut sum_g = 0.0f32;
        for row in 0..rows {
            let i = row * d + c;
            let xhat = (x[i] + r[i] - stats[2 * row]) * stats[2 * row + 1];
            sum_gx += grad[i] * xhat;
            sum_g += grad[i];
        }
        dgamma[c] = sum_gx;
        dbeta[c] = sum_g;
    }
}

fn cube_forward(inputs: LayerNormInputs<CubeBackend>) -> FloatTensor<CubeBackend> {
    let _span = tracing::trace_span!("cube_add_layer_norm").entered();
    let dtype = inputs.x.dtype();
    let shape = inputs.x.shape();
    let d = inputs.gamma.shape().num_elements();
    let len = shape.num_elements();
    let rows = len / d.max(1);
    let (client, device) = (inputs.x.client.clone(), inputs.x.device.clone());
    let x = prepare(inputs.x);
    let r = prepare(inputs.residual);
    let gamma = prepare(inputs.gamma);
    let beta = prepare(inputs.beta);
    let out = client.empty(4 * len.max(1));
    if rows > 0 && d > 0 {
        forward_kernel::launch(
            &client,
            count_1d(rows),
            CubeDim::new_1d(THREADS_1D),
            tensor_arg(&x),
            tensor_arg(&r),
            tensor_arg(&gamma),
            tensor_arg(&beta),
            arg(&out, len),
            rows,
            d,
            inputs.epsilon as f32,
        );
    }
    cast_to(tensor_f32(&client, &device, out, &shape), dtype)
}

fn cube_backward(
    inputs: LayerNormInputs<CubeBackend>,
    grad: FloatTensor<CubeBackend>,
) -> [FloatTensor<CubeBackend>; 3] {
    let _span = tracing::trace_span!("cube_add_layer_norm_backward").entered();
    let (z_dtype, gamma_dtype, beta_dtype) =
        (inputs.x.dtype(), inputs.gamma.dtype(), inputs.beta.dtype());
    let shape = inputs.x.shape();
    let d = inputs.gamma.shape().num_elements();
    let len = shape.num_elements();
    let rows = len / d.max(1);
    let (client, device) = (inputs.x.client.clone(), inputs.x.device.clone());
    let x = prepare(inputs.x);
    let r = prepare(inputs.residual);
    let gamma = prepare(inputs.gamma);
    let grad = prepare(grad);
    let dz = client.empty(4 * len.max(1));
    let stats = client.empty(4 * (2 * rows).max(1));
    let dgamma = client.empty(4 * d.max(1));
    let dbeta = client.empty(4 * d.max(1));
    if rows > 0 && d > 0 {
        rows_backward_kernel::launch(
            &client,
            count_1d(rows),
            CubeDim::new_1d(THREADS_1D),
            tensor_arg(&x),
            tensor_arg(&r),
            tensor_arg(&gamma),
            tensor_arg(&grad),
            arg(&dz, len),
            arg(&stats, 2 * rows),
            rows,
            d,
            inputs.epsilon as f32,
        );
    }
    if d > 0 {
        // With no rows the sums are zero: the kernel's loops run zero times.
        columns_backward_kernel::launch(
            &client,
            count_1d(d),
            CubeDim::new_1d(THREADS_1D),
            tensor_arg(&x),
            tensor_arg(&r),
            tensor_arg(&grad),
            arg(&stats, 2 * rows),
            arg(&dgamma, d),
            arg(&dbeta, d),
            rows,
            d,
        );
    }
    [
        cast_to(tensor_f32(&client, &device, dz, &shape), z_dtype),
        cast_to(tensor_f32(&client, &device, dgamma, &[d]), gamma_dtype),
        cast_to(tensor_f32(&client, &device, dbeta, &[d]), beta_dtype),
    ]
}

impl AddLayerNormOps for CubeBackend {
    fn add_layer_norm(
        x: FloatTensor<Self>,
        residual: FloatTensor<Self>,
        gamma: FloatTensor<Self>,
        beta: FloatTensor<Self>,
        epsilon: LayerNormEpsilon,
    ) -> FloatTensor<Self> {
        cube_forward(LayerNormInputs {
            x,
            residual,
            gamma,
            beta,
            epsilon: epsilon.0,
        })
    }
}

impl LayerNormKernels for CubeBackend {
    fn layer_norm_forward(inputs: LayerNormInputs<Self>) -> FloatTensor<Self> {
        cube_forward(inputs)
    }

    fn layer_norm_backward(
        inputs: LayerNormInputs<Self>,
        grad: FloatTensor<Self>,
    ) -> [FloatTensor<Self>; 3] {
        cube_backward(inputs, grad)
    }
}
