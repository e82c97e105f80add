//! The positional encoding `δ = relu(rel·W₀ + b₀)·W₃ + b₃` ([`super::position_encoding`]) on
//! Burn's CubeCL backend, for `rel` `[m, 3]` (the `m = n·k` neighbour offsets), `W₀` `[3, 3]`,
//! `W₃` `[3, c]` (Burn's `[in, out]` layout), all four read from one parameter vector
//! `p = [W₃, b₃, W₀, b₀]` (`4c + 12`, the order of the weights' gradient sums below). The
//! hidden layer is three wide, so each thread recomputes it from its row's offset instead of
//! reading it from memory.
//!
//! - `position_forward_kernel`, one thread per `(row, ch)`.
//! - `position_backward_kernel`, one cube per chunk of [`ROWS_PER_CHUNK`] rows: each thread does
//!   one row, `∂h = g·W₃ᵀ` through the ReLU (which passes where its input is positive, as
//!   Burn's does), `∂rel = ∂h_pre·W₀ᵀ`, and keeps the row's hidden activations and `∂h_pre` in
//!   shared memory; then the cube sums its chunk's rows for every output element of the
//!   weights' gradient (`W₃`, `b₃`, `W₀`, `b₀` in that order, `4c + 12` in all), one thread per
//!   element, into the pass's partial sums. One launch per pass: the rows' scratch never goes
//!   to memory.
//! - `position_chunk_totals_kernel` adds the chunks of up to four passes up in pass and chunk
//!   order, one thread per element, once for all passes (`super::position_op`). Fixed orders:
//!   the sums are deterministic.

use burn::backend::TensorMetadata;
use burn::backend::tensor::FloatTensor;
use burn_cubecl::CubeBackend;
use burn_cubecl::cubecl;
use burn_cubecl::cubecl::prelude::*;
use lifegom_render::cube::host::{
    THREADS_1D, arg, cast_to, count_1d, count_cubes, prepare, tensor_arg, tensor_f32,
};

use super::position_op::{
    PositionEncodingKernels, PositionEncodingOps, PositionLedger, TOTAL_PARTS,
};

/// Rows each partial sum covers.
pub(super) const ROWS_PER_CHUNK: usize = 256;

/// The pre-activation `rel[row]·W₀[·, r] + b₀[r]` of hidden unit `r`, from `p`.
#[cube]
fn hidden(rel: &[f32], p: &[f32], row: usize, r: usize, c: usize) -> f32 {
    let w0 = 4 * c;
    rel[row * 3] * p[w0 + r]
        + rel[row * 3 + 1] * p[w0 + 3 + r]
        + rel[row * 3 + 2] * p[w0 + 6 + r]
        + p[w0 + 9 + r]
}

#[cube(launch)]
#[allow(clippy::too_many_arguments)]
fn position_forward_kernel(rel: &[f32], p: &[f32], out: &mut [f32], units: usize, c: usize) {
    let unit = ABSOLUTE_POS;
    if unit < units {
        let ch = unit % c;
        let row = unit / c;
        let mut acc = p[3 * c + ch];
        for r in 0..3usize {
            acc += f32::max(hidden(rel, p, row, r, c), 0.0) * p[r * c + ch];
        }
        out[unit] = acc;
    }
}

/// Row `row`'s term of output element `o` (module docs' order); `local` is the row's slot in
/// the chunk's `scratch` (its hidden activations, then its `∂h_pre`).
#[cube]
#[allow(clippy::too_many_arguments)]
fn weight_term(
    rel: &[f32],
    grad: &[f32],
    scratch: &[f32],
    row: usize,
    local: usize,
    o: usize,
    c: usize,
) -> f32 {
    let mut term = 0.0f32;
    if o < 3 * c {
        term = scratch[local * 6 + o / c] * grad[row * c + o % c];
    } else if o < 4 * c {
        term = grad[row * c + o - 3 * c];
    } else if o < 4 * c + 9 {
        let j = o - 4 * c;
        term = rel[row * 3 + j / 3] * scratch[local * 6 + 3 + j % 3];
    } else if o < 4 * c + 12 {
        term = scratch[local * 6 + 3 + o - 4 * c - 9];
    }
    term
}

/// One cube per chunk of [`ROWS_PER_CHUNK`] rows (module docs): each thread first does one
/// row, `∂rel` and the row's hidden activations and `∂h_pre` into shared memory; then the
/// threads sum the chunk's rows for the weights' outputs, one output at a time each.
#[cube(launch)]
#[allow(clippy::too_many_arguments)]
fn position_backward_kernel(
    rel: &[f32],
    p: &[f32],
    grad: &[f32],
    rel_grad: &mut [f32],
    partial: &mut [f32],
    rows: usize,
    chunks: usize,
    outputs: usize,
    c: usize,
) {
    let mut scratch = Shared::<[f32]>::new_slice(ROWS_PER_CHUNK * 6);
    let chunk = CUBE_POS_Y as usize * CUBE_COUNT_X as usize + CUBE_POS_X as usize;
    let local = UNIT_POS_X as usize;
    let start = chunk * ROWS_PER_CHUNK;
    let row = start + local;
    if chunk < chunks && row < rows {
        // ∂h_pre for the three hidden units, kept in the row's last three slots.
        for r in 0..3usize {
            let pre = hidden(rel, p, row, r, c);
            let mut gh = 0.0f32;
            if pre > 0.0 {
                for ch in 0..c {
                    gh += grad[row * c + ch] * p[r * c + ch];
                }
            }
            scratch[local * 6 + r] = f32::max(pre, 0.0);
            scratch[local * 6 + 3 + r] = gh;
        }
        for a in 0..3usize {
            let mut g = 0.0f32;
            for r in 0..3usize {
                g += scratch[local * 6 + 3 + r] * p[4 * c + a * 3 + r];
            }
            rel_grad[row * 3 + a] = g;
        }
    }
    sync_cube();
    if chunk < chunks {
        let end = usize::min(start + ROWS_PER_CHUNK, rows);
        let mut o = local;
        while o < outputs {
            let mut acc = 0.0f32;
            for r in start..end {
                acc += weight_term(rel, grad, &scratch, r, r - start, o, c);
            }
            partial[chunk * outputs + o] = acc;
            o += ROWS_PER_CHUNK;
        }
    }
}

/// The chunks `part[0..chunks)` of one element `o` added in order onto `acc`.
#[cube]
fn add_chunks(part: &[f32], chunks: usize, outputs: usize, o: usize, acc: f32) -> f32 {
    let mut total = acc;
    for chunk in 0..chunks {
        total += part[chunk * outputs + o];
    }
    total
}

#[cube(launch)]
#[allow(clippy::too_many_arguments)]
fn position_chunk_totals_kernel(
    part0: &[f32],
    part1: &[f32],
    part2: &[f32],
    part3: &[f32],
    scale: &[f32],
    totals: &mut [f32],
    w3_grad: &mut [f32],
    b3_grad: &mut [f32],
    w0_grad: &mut [f32],
    b0_grad: &mut [f32],
    chunks0: usize,
    chunks1: usize,
    chunks2: usize,
    chunks3: usize,
    c: usize,
) {
    let outputs = 4 * c + 12;
    let o = ABSOLUTE_POS;
    if o < outputs {
        let mut acc = add_chunks(part0, chunks0, outputs, o, 0.0f32);
        acc = add_chunks(part1, chunks1, outputs, o, acc);
        acc = add_chunks(part2, chunks2, outputs, o, acc);
        acc = add_chunks(part3, chunks3, outputs, o, acc);
        totals[o] = acc;
        // The folded W₀ and b₀ carry the BatchNorm's scale per output column: ∂W₀ = ∂W₀'·s.
        if o < 3 * c {
            w3_grad[o] = acc;
        } else if o < 4 * c {
            b3_grad[o - 3 * c] = acc;
        } else if o < 4 * c + 9 {
            let j = o - 4 * c;
            w0_grad[j] = acc * scale[j % 3];
        } else {
            let r = o - 4 * c - 9;
            b0_grad[r] = acc * scale[r];
        }
    }
}

/// `p = [W₃, b₃, W₀·diag(s), b₀·s + t]`, one thread per element.
#[cube(launch)]
#[allow(clippy::too_many_arguments)]
fn position_weights_kernel(
    w3: &[f32],
    b3: &[f32],
    w0: &[f32],
    b0: &[f32],
    scale: &[f32],
    shift: &[f32],
    p: &mut [f32],
    c: usize,
) {
    let o = ABSOLUTE_POS;
    if o < 4 * c + 12 {
        if o < 3 * c {
            p[o] = w3[o];
        } else if o < 4 * c {
            p[o] = b3[o - 3 * c];
        } else if o < 4 * c + 9 {
            let j = o - 4 * c;
            p[o] = w0[j] * scale[j % 3];
        } else {
            let r = o - 4 * c - 9;
            p[o] = b0[r] * scale[r] + shift[r];
        }
    }
}

impl PositionEncodingOps for CubeBackend {
    fn position_weights(
        w3: FloatTensor<Self>,
        b3: FloatTensor<Self>,
        w0: FloatTensor<Self>,
        b0: FloatTensor<Self>,
        scale: FloatTensor<Self>,
        shift: FloatTensor<Self>,
        _ledger: PositionLedger,
    ) -> FloatTensor<Self> {
        let dtype = w3.dtype();
        let c = w3.shape()[1];
        let outputs = 4 * c + 12;
        let (client, device) = (w3.client.clone(), w3.device.clone());
        let [w3, b3, w0, b0, scale, shift] = [w3, b3, w0, b0, scale, shift].map(prepare);
        let p = client.empty(4 * outputs);
        position_weights_kernel::launch(
            &client,
            count_1d(outputs),
            CubeDim::new_1d(THREADS_1D),
            tensor_arg(&w3),
            tensor_arg(&b3),
            tensor_arg(&w0),
            tensor_arg(&b0),
            tensor_arg(&scale),
            tensor_arg(&shift),
            arg(&p, outputs),
            c,
        );
        cast_to(tensor_f32(&client, &device, p, &[outputs]), dtype)
    }

    fn position_encoding(
        rel: FloatTensor<Self>,
        weights: FloatTensor<Self>,
        _ledger: PositionLedger,
    ) -> FloatTensor<Self> {
        let _span = tracing::trace_span!("cube_position_encoding").entered();
        let dtype = rel.dtype();
        let mut shape = rel.shape().to_vec();
        let c = channels(&weights);
        let rows: usize = shape[..shape.len() - 1].iter().product();
        *shape.last_mut().expect("rel has a last axis") = c;
        let (client, device) = (rel.client.clone(), rel.device.clone());
        let [rel, p] = [rel, weights].map(prepare);
        let units = rows * c;
        let out = client.empty(4 * units.max(1));
        if units > 0 {
            position_forward_kernel::launch(
                &client,
                count_1d(units),
                CubeDim::new_1d(THREADS_1D),
                tensor_arg(&rel),
                tensor_arg(&p),
                arg(&out, units),
                units,
                c,
            );
        }
        cast_to(tensor_f32(&client, &device, out, &shape), dtype)
    }
}

/// `c` of a parameter vector `[4c + 12]`.
fn channels(weights: &FloatTensor<CubeBackend>) -> usize {
    (weights.shape()[0] - 12) / 4
}

impl PositionEncodingKernels for CubeBackend {
    fn position_encoding_backward(
        rel: FloatTensor<Self>,
        weights: FloatTensor<Self>,
        grad: FloatTensor<Self>,
    ) -> (FloatTensor<Self>, FloatTensor<Self>) {
        let _span = tracing::trace_span!("cube_position_encoding_backward").entered();
        let dtype = rel.dtype();
        let rel_shape = rel.shape().to_vec();
        let c = channels(&weights);
        let rows: usize = rel_shape[..rel_shape.len() - 1].iter().product();
        let (client, device) = (rel.client.clone(), rel.device.clone());
        let [rel, p, grad] = [rel, weights, grad].map(prepare);
        let rel_grad = client.empty(4 * (rows * 3).max(1));
        let outputs = 4 * c + 12;
        let chunks = rows.div_ceil(ROWS_PER_CHUNK).max(1);
        let partial = client.empty(4 * chunks * outputs);
        // With no rows the partial sums are all empty: the kernel writes zeros.
        position_backward_kernel::launch(
            &client,
            count_cubes(chunks),
            CubeDim::new_1d(ROWS_PER_CHUNK as u32),
            tensor_arg(&rel),
            tensor_arg(&p),
            tensor_arg(&grad),
            arg(&rel_grad, rows * 3),
            arg(&partial, chunks * outputs),
            rows,
            chunks,
            outputs,
            c,
        );
        (
            cast_to(tensor_f32(&client, &device, rel_grad, &rel_shape), dtype),
            tensor_f32(&client, &device, partial, &[chunks * outputs]),
        )
    }

    fn position_weight_totals(
        partials: Vec<FloatTensor<Self>>,
        scale: FloatTensor<Self>,
        c: usize,
    ) -> (FloatTensor<Self>, [FloatTensor<Self>; 4]) {
        assert!(
            !partials.is_empty() && partials.len() <= TOTAL_PARTS,
            "1 to {TOTAL_PARTS} passes' partial sums"
        );
        let outputs = 4 * c + 12;
        let dtype = scale.dtype();
        let (client, device) = (partials[0].client.clone(), partials[0].device.clone());
        let parts: Vec<_> = partials.into_iter().map(prepare).collect();
        let scale = prepare(scale);
        let chunks: Vec<usize> = (0..TOTAL_PARTS)
            .map(|i| parts.get(i).map_or(0, |p| p.shape()[0] / outputs))
            .collect();
        // Unused parts are bound to the first one and read zero chunks of it.
        let part = |i: usize| tensor_arg(parts.get(i).unwrap_or(&parts[0]));
        let totals = client.empty(4 * outputs);
        let lens = [3 * c, c, 9, 3];
        let grads = lens.map(|len| client.empty(4 * len.max(1)));
        position_chunk_totals_kernel::launch(
            &client,
            count_1d(outputs),
            CubeDim::new_1d(THREADS_1D),
            part(0),
            part(1),
            part(2),
            part(3),
            tensor_arg(&scale),
            arg(&totals, outputs),
            arg(&grads[0], lens[0].max(1)),
            arg(&grads[1], lens[1].max(1)),
            arg(&grads[2], 9),
            arg(&grads[3], 3),
            chunks[0],
            chunks[1],
            chunks[2],
            chunks[3],
            c,
        );
        let shapes: [&[usize]; 4] = [&[3, c], &[c], &[3, 3], &[3]];
        let mut i = 0;
        let grads = grads.map(|h| {
            let t = cast_to(tensor_f32(&client, &device, h, shapes[i]), dtype);
            i += 1;
            t
        });
        (tensor_f32(&client, &device, totals, &[outputs]), grads)
    }
}
