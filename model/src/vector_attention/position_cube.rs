//! The positional encoding `δ = relu(rel·W₀ + b₀)·W₃ + b₃` ([`super::position_encoding`]) on
//! Burn's CubeCL backend, for `rel` `[m, 3]` (the `m = n·k` neighbour offsets), `W₀` `[3, 3]`,
//! `W₃` `[3, c]` (Burn's `[in, out]` layout). The hidden layer is three wide, so each thread
//! recomputes it from its row's offset instead of reading it from memory.
//!
//! - `position_forward_kernel`, one thread per `(row, ch)`.
//! - `position_backward_rows_kernel`, one thread per row: `∂h = g·W₃ᵀ` through the ReLU (which
//!   passes where its input is positive, as Burn's does), `∂rel = ∂h_pre·W₀ᵀ`, and the row's
//!   hidden activations and `∂h_pre` into a scratch buffer `[m, 6]` for the weights' sums.
//! - The weights' gradients are sums over all `m` rows: `position_partial_sums_kernel` sums
//!   [`ROWS_PER_CHUNK`] rows for every output element (`W₃`, `b₃`, `W₀`, `b₀` in that order,
//!   `4c + 12` in all), one thread per chunk and element; `position_chunk_totals_kernel` adds
//!   the chunks up in chunk order, one thread per element. Fixed orders: the sums are
//!   deterministic.

use burn::backend::TensorMetadata;
use burn::backend::tensor::FloatTensor;
use burn_cubecl::CubeBackend;
use burn_cubecl::cubecl;
use burn_cubecl::cubecl::prelude::*;
use lifegom_render::cube::host::{
    THREADS_1D, arg, cast_to, count_1d, prepare, tensor_arg, tensor_f32,
};

use super::position_op::{PositionEncodingKernels, PositionEncodingOps};

/// Rows each partial sum covers.
const ROWS_PER_CHUNK: usize = 256;

/// `relu(rel[row]·W₀[·, r] + b₀[r])` and its pre-activation.
#[cube]
fn hidden(rel: &[f32], w0: &[f32], b0: &[f32], row: usize, r: usize) -> f32 {
    rel[row * 3] * w0[r] + rel[row * 3 + 1] * w0[3 + r] + rel[row * 3 + 2] * w0[6 + r] + b0[r]
}

#[cube(launch)]
#[allow(clippy::too_many_arguments)]
fn position_forward_kernel(
    rel: &[f32],
    w0: &[f32],
    b0: &[f32],
    w3: &[f32],
    b3: &[f32],
    out: &mut [f32],
    units: usize,
    c: usize,
) {
    let unit = ABSOLUTE_POS;
    if unit < units {
        let ch = unit % c;
        let row = unit / c;
        let mut acc = b3[ch];
        for r in 0..3usize {
            acc += f32::max(hidden(rel, w0, b0, row, r), 0.0) * w3[r * c + ch];
        }
        out[unit] = acc;
    }
}

#[cube(launch)]
#[allow(clippy::too_many_arguments)]
fn position_backward_rows_kernel(
    rel: &[f32],
    w0: &[f32],
    b0: &[f32],
    w3: &[f32],
    grad: &[f32],
    rel_grad: &mut [f32],
    scratch: &mut [f32],
    rows: usize,
    c: usize,
) {
    let row = ABSOLUTE_POS;
    if row < rows {
        // ∂h_pre for the three hidden units, kept in the scratch row's last three slots.
        for r in 0..3usize {
            let pre = hidden(rel, w0, b0, row, r);
            let mut gh = 0.0f32;
            if pre > 0.0 {
                for ch in 0..c {
                    gh += grad[row * c + ch] * w3[r * c + ch];
                }
            }
            scratch[row * 6 + r] = f32::max(pre, 0.0);
            scratch[row * 6 + 3 + r] = gh;
        }
        for a in 0..3usize {
            let mut g = 0.0f32;
            for r in 0..3usize {
                g += scratch[row * 6 + 3 + r] * w0[a * 3 + r];
            }
            rel_grad[row * 3 + a] = g;
        }
    }
}

/// Row `row`'s term of output element `o` (module docs' order).
#[cube]
fn weight_term(rel: &[f32], grad: &[f32], scratch: &[f32], row: usize, o: usize, c: usize) -> f32 {
    let mut term = 0.0f32;
    if o < 3 * c {
        term = scratch[row * 6 + o / c] * grad[row * c + o % c];
    } else if o < 4 * c {
        term = grad[row * c + o - 3 * c];
    } else if o < 4 * c + 9 {
        let j = o - 4 * c;
        term = rel[row * 3 + j / 3] * scratch[row * 6 + 3 + j % 3];
    } else if o < 4 * c + 12 {
        term = scratch[row * 6 + 3 + o - 4 * c - 9];
    }
    term
}

#[cube(launch)]
#[allow(clippy::too_many_arguments)]
fn position_partial_sums_kernel(
    rel: &[f32],
    grad: &[f32],
    scratch: &[f32],
    partial: &mut [f32],
    units: usize,
    rows: usize,
    rows_per_chunk: usize,
    outputs: usize,
    c: usize,
) {
    let unit = ABSOLUTE_POS;
    if unit < units {
        let o = unit % outputs;
        let chunk = unit / outputs;
        let start = chunk * rows_per_chunk;
        let end = usize::min(start + rows_per_chunk, rows);
        let mut acc = 0.0f32;
        for row in start..end {
            acc += weight_term(rel, grad, scratch, row, o, c);
        }
        partial[unit] = acc;
    }
}

#[cube(launch)]
#[allow(clippy::too_many_arguments)]
fn position_chunk_totals_kernel(
    partial: &[f32],
    w3_grad: &mut [f32],
    b3_grad: &mut [f32],
    w0_grad: &mut [f32],
    b0_grad: &mut [f32],
    chunks: usize,
    outputs: usize,
    c: usize,
) {
    let o = ABSOLUTE_POS;
    if o < outputs {
        let mut acc = 0.0f32;
        for chunk in 0..chunks {
            acc += partial[chunk * outputs + o];
        }
        if o < 3 * c {
            w3_grad[o] = acc;
        } else if o < 4 * c {
            b3_grad[o - 3 * c] = acc;
        } else if o < 4 * c + 9 {
            w0_grad[o - 4 * c] = acc;
        } else {
            b0_grad[o - 4 * c - 9] = acc;
        }
    }
}

impl PositionEncodingOps for CubeBackend {
    fn position_encoding(
        rel: FloatTensor<Self>,
        w0: FloatTensor<Self>,
        b0: FloatTensor<Self>,
        w3: FloatTensor<Self>,
        b3: FloatTensor<Self>,
    ) -> FloatTensor<Self> {
        let _span = tracing::trace_span!("cube_position_encoding").entered();
        let dtype = rel.dtype();
        let mut shape = rel.shape().to_vec();
        let c = w3.shape()[1];
        let rows: usize = shape[..shape.len() - 1].iter().product();
        *shape.last_mut().expect("rel has a last axis") = c;
        let (client, device) = (rel.client.clone(), rel.device.clone());
        let [rel, w0, b0, w3, b3] = [rel, w0, b0, w3, b3].map(prepare);
        let units = rows * c;
        let out = client.empty(4 * units.max(1));
        if units > 0 {
            position_forward_kernel::launch(
                &client,
                count_1d(units),
                CubeDim::new_1d(THREADS_1D),
                tensor_arg(&rel),
                tensor_arg(&w0),
                tensor_arg(&b0),
                tensor_arg(&w3),
                tensor_arg(&b3),
                arg(&out, units),
                units,
                c,
            );
        }
        cast_to(tensor_f32(&client, &device, out, &shape), dtype)
    }
}

impl PositionEncodingKernels for CubeBackend {
    fn position_encoding_backward(
        rel: FloatTensor<Self>,
        w0: FloatTensor<Self>,
        b0: FloatTensor<Self>,
        w3: FloatTensor<Self>,
        grad: FloatTensor<Self>,
    ) -> [FloatTensor<Self>; 5] {
        let _span = tracing::trace_span!("cube_position_encoding_backward").entered();
        let dtypes = [&rel, &w0, &b0, &w3].map(|t| t.dtype());
        let rel_shape = rel.shape().to_vec();
        let c = w3.shape()[1];
        let rows: usize = rel_shape[..rel_shape.len() - 1].iter().product();
        let (client, device) = (rel.client.clone(), rel.device.clone());
        let [rel, w0, b0, w3, grad] = [rel, w0, b0, w3, grad].map(prepare);
        let rel_grad = client.empty(4 * (rows * 3).max(1));
        let scratch = client.empty(4 * (rows * 6).max(1));
        let outputs = 4 * c + 12;
        let chunks = rows.div_ceil(ROWS_PER_CHUNK).max(1);
        let partial = client.empty(4 * chunks * outputs);
        let grads = [3 * c, c, 9, 3].map(|len| client.empty(4 * len.max(1)));
        if rows > 0 {
            position_backward_rows_kernel::launch(
                &client,
                count_1d(rows),
                CubeDim::new_1d(THREADS_1D),
                tensor_arg(&rel),
                tensor_arg(&w0),
                tensor_arg(&b0),
                tensor_arg(&w3),
                tensor_arg(&grad),
                arg(&rel_grad, rows * 3),
                arg(&scratch, rows * 6),
                rows,
                c,
            );
        }
        // With no rows the partial sums are all empty: the first kernel writes zeros.
        position_partial_sums_kernel::launch(
            &client,
            count_1d(chunks * outputs),
            CubeDim::new_1d(THREADS_1D),
            tensor_arg(&rel),
            tensor_arg(&grad),
            arg(&scratch, rows * 6),
            arg(&partial, chunks * outputs),
            chunks * outputs,
            rows,
            ROWS_PER_CHUNK,
            outputs,
            c,
        );
        position_chunk_totals_kernel::launch(
            &client,
            count_1d(outputs),
            CubeDim::new_1d(THREADS_1D),
            arg(&partial, chunks * outputs),
            arg(&grads[0], 3 * c),
            arg(&grads[1], c),
            arg(&grads[2], 9),
            arg(&grads[3], 3),
            chunks,
            outputs,
            c,
        );
        let [w3_grad, b3_grad, w0_grad, b0_grad] = grads;
        [
            cast_to(
                tensor_f32(&client, &device, rel_grad, &rel_shape),
                dtypes[0],
            ),
            cast_to(tensor_f32(&client, &device, w0_grad, &[3, 3]), dtypes[1]),
            cast_to(tensor_f32(&client, &device, b0_grad, &[3]), dtypes[2]),
            cast_to(tensor_f32(&client, &device, w3_grad, &[3, c]), dtypes[3]),
            cast_to(tensor_f32(&client, &device, b3_grad, &[c]), dtypes[3]),
        ]
    }
}
