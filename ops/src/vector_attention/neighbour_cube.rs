//! The Point Transformer layer's neighbourhood ops on Burn's CubeCL backend ([`super::relation`]
//! and [`super::aggregate_gathered`]). `qkv` is `[n, 3c]` with the query, key and value of point
//! `i` at columns `0..c`, `c..2c` and `2c..3c`; `neighbours[i·k + κ]` is point `i`'s κ-th
//! neighbour.
//!
//! Forward, one launch each:
//! - `relation_forward_kernel`, one thread per `(i, κ, ch)`:
//!   `relu((k[nbr, ch] − q[i, ch] + δ[i, κ, ch])·scale[ch] + shift[ch])`;
//! - `aggregate_gathered_forward_kernel`, one thread per point and weight channel `(i, j)`: the
//!   softmax over the neighbours (as `vector_attention::cube` computes it) applied to the
//!   gathered values `v[nbr, ch] + δ[i, κ, ch]` of the `S` channels `ch = s·C/S + j`.
//!
//! Backward, two launches each (three for a pair), no zero-fill: a first kernel writes every output it owns
//! (including zeros over the rows of `∂qkv` the scatter adds into), a second adds the
//! neighbours' shares into the key (relation) or value (aggregation) columns of `∂qkv` with
//! float atomic adds ([`lifegom_render::cube::atomic`]), reading them from the `∂δ` the first
//! wrote: the gathered operand and `δ` enter as a sum, so their gradients are equal.
//! - `relation_backward_rows_kernel`, one thread per `(i, ch)`: `∂δ[i, κ, ch] = g·scale·[y > 0]`
//!   for every κ (ReLU passes where its output is positive, as Burn's does), `∂q[i, ch] =
//!   −Σ_κ ∂δ[i, κ, ch]`, zeros over row `i`'s key and value columns.
//! - `aggregate_gathered_backward_rows_kernel`, one thread per `(i, j)`: `∂δ = p_κ·g` (the
//!   value's gradient), the softmax's backward for the logits as in `vector_attention::cube`,
//!   zeros over all of row `i`'s columns of channel `j`.
//! - `scatter_columns_kernel`, one thread per `(i, κ, ch)`: `∂qkv[nbr, offset + ch] += ∂δ[i, κ, ch]`.
//!   For a paired relation and aggregation (`super::neighbour_op`) the relation's launch also
//!   adds the aggregation's `∂δ` into the value columns, which the aggregation's backward then
//!   skips: three launches for the pair instead of four.
//!
//! A neighbour index outside `0..n` gathers zero and receives nothing (the callers build them
//! in range; this only keeps a bad index from reading out of bounds).

use burn::backend::TensorMetadata;
use burn::backend::tensor::{FloatTensor, IntTensor};
use burn_cubecl::CubeBackend;
use burn_cubecl::cubecl;
use burn_cubecl::cubecl::prelude::*;
use burn_cubecl::tensor::CubeTensor;
use lifegom_render::cube::atomic::{AtomicAddF32, use_native_float_atomics};
use lifegom_render::cube::host::{
    THREADS_1D, arg, cast_to, count_1d, prepare, prepare_i32, tensor_arg, tensor_f32,
};

use super::cube::{probability, softmax_scale};
use super::neighbour_op::{
    AggregateEnding, AttentionPair, NeighbourAttentionKernels, NeighbourAttentionOps, ValueScatter,
};

/// The sizes every kernel indexes with.
#[derive(CubeType, CubeLaunch)]
struct Sizes {
    /// Points.
    n: usize,
    /// Neighbours per point.
    k: usize,
    /// Channels of each of q, k, v and δ.
    c: usize,
}

/// `qkv[row, column]` for a neighbour `row` read from the index table, or zero outside `0..n`.
#[cube]
fn gathered(qkv: &[f32], row: i32, column: usize, sizes: &Sizes) -> f32 {
    let mut value = 0.0f32;
    if row >= 0 && (row as usize) < sizes.n {
        value = qkv[row as usize * 3 * sizes.c + column];
    }
    value
}

/// `(k[nbr, ch] − q[i, ch] + δ[i, κ, ch])·scale[ch] + shift[ch]` for the flat `ik = i·k + κ`.
#[cube]
#[allow(clippy::too_many_arguments)]
fn relation_pre(
    qkv: &[f32],
    neighbours: &[i32],
    delta: &[f32],
    scale: &[f32],
    shift: &[f32],
    i: usize,
    ik: usize,
    ch: usize,
    sizes: &Sizes,
) -> f32 {
    let key = gathered(qkv, neighbours[ik], sizes.c + ch, sizes);
    let pre = key - qkv[i * 3 * sizes.c + ch] + delta[ik * sizes.c + ch];
    pre * scale[ch] + shift[ch]
}

#[cube(launch)]
fn relation_forward_kernel(
    qkv: &[f32],
    neighbours: &[i32],
    delta: &[f32],
    scale: &[f32],
    shift: &[f32],
    out: &mut [f32],
    units: usize,
    sizes: &Sizes,
) {
    let unit = ABSOLUTE_POS;
    if unit < units {
        let ch = unit % sizes.c;
        let ik = unit / sizes.c;
        let i = ik / sizes.k;
        let y = relation_pre(qkv, neighbours, delta, scale, shift, i, ik, ch, sizes);
        out[unit] = f32::max(y, 0.0);
    }
}

#[cube(launch)]
#[allow(clippy::too_many_arguments)]
fn relation_backward_rows_kernel(
    qkv: &[f32],
    neighbours: &[i32],
    delta: &[f32],
    scale: &[f32],
    shift: &[f32],
    grad: &[f32],
    qkv_addend: &[f32],
    qkv_grad: &mut [f32],
    delta_grad: &mut [f32],
    units: usize,
    added: u32,
    sizes: &Sizes,
) {
    let unit = ABSOLUTE_POS;
    if unit < units {
        let ch = unit % sizes.c;
        let i = unit / sizes.c;
        let mut query = 0.0f32;
        for kk in 0..sizes.k {
            let ik = i * sizes.k + kk;
            let y = relation_pre(qkv, neighbours, delta, scale, shift, i, ik, ch, sizes);
            let mut g = 0.0f32;
            if y > 0.0 {
                g = grad[ik * sizes.c + ch] * scale[ch];
            }
            delta_grad[ik * sizes.c + ch] = g;
            query -= g;
        }
        let row = i * 3 * sizes.c;
        let mut key = 0.0f32;
        let mut value = 0.0f32;
        if added != 0 {
            query += qkv_addend[row + ch];
            key = qkv_addend[row + sizes.c + ch];
            value = qkv_addend[row + 2 * sizes.c + ch];
        }
        qkv_grad[row + ch] = query;
        qkv_grad[row + sizes.c + ch] = key;
        qkv_grad[row + 2 * sizes.c + ch] = value;
    }
}

/// `v[nbr, ch] + δ[i, κ, ch]` for the flat `ik = i·k + κ`.
#[cube]
fn gathered_value(
    qkv: &[f32],
    neighbours: &[i32],
    delta: &[f32],
    ik: usize,
    ch: usize,
    sizes: &Sizes,
) -> f32 {
    gathered(qkv, neighbours[ik], 2 * sizes.c + ch, sizes) + delta[ik * sizes.c + ch]
}

#[cube(launch)]
#[allow(clippy::too_many_arguments)]
fn aggregate_gathered_forward_kernel(
    qkv: &[f32],
    neighbours: &[i32],
    delta: &[f32],
    logits: &[f32],
    out_scale: &[f32],
    out_shift: &[f32],
    out: &mut [f32],
    units: usize,
    cs: usize,
    sizes: &Sizes,
    #[comptime] normed: bool,
) {
    let unit = ABSOLUTE_POS;
    if unit < units {
        let j = unit % cs;
        let i = unit / cs;
        let k = sizes.k;
        let scale = softmax_scale(logits, i, j, k, cs);
        let s = sizes.c / cs;
        for si in 0..s {
            let ch = si * cs + j;
            let mut acc = 0.0f32;
            for kk in 0..k {
                let ik = i * k + kk;
                let p = probability(logits, &scale, i, kk, j, k, cs);
                acc += p * gathered_value(qkv, neighbours, delta, ik, ch, sizes);
            }
            if normed {
                // The block's frozen BatchNorm, then Burn's ReLU (`v ≤ 0 → 0`).
                acc = acc * out_scale[ch] + out_shift[ch];
                acc = select(acc <= 0.0f32, 0.0f32, acc);
            }
            out[i * sizes.c + ch] = acc;
        }
    }
}

#[cube(launch)]
#[allow(clippy::too_many_arguments)]
fn aggregate_gathered_backward_rows_kernel(
    qkv: &[f32],
    neighbours: &[i32],
    delta: &[f32],
    logits: &[f32],
    grad: &[f32],
    output: &[f32],
    out_scale: &[f32],
    qkv_grad: &mut [f32],
    delta_grad: &mut [f32],
    logits_grad: &mut [f32],
    units: usize,
    cs: usize,
    sizes: &Sizes,
    #[comptime] normed: bool,
) {
    let unit = ABSOLUTE_POS;
    if unit < units {
        let j = unit % cs;
        let i = unit / cs;
        let k = sizes.k;
        let c = sizes.c;
        let s = c / cs;
        let scale = softmax_scale(logits, i, j, k, cs);
        // a_κ = Σ_s g[i, ch]·value[κ, ch] and Σ_λ p_λ·a_λ, the softmax backward's shared term.
        let mut dot = 0.0f32;
        for kk in 0..k {
            let ik = i * k + kk;
            let p = probability(logits, &scale, i, kk, j, k, cs);
            let mut a = 0.0f32;
            for si in 0..s {
                let ch = si * cs + j;
                let mut g = grad[i * c + ch];
                if normed {
                    // Through the ReLU and the BatchNorm's scale.
                    g = select(output[i * c + ch] <= 0.0f32, 0.0f32, g * out_scale[ch]);
                }
                delta_grad[ik * c + ch] = p * g;
                a += g * gathered_value(qkv, neighbours, delta, ik, ch, sizes);
            }
            dot += p * a;
            // Kept until the second loop: the logit gradient needs the finished `dot`.
            logits_grad[ik * cs + j] = a;
        }
        for kk in 0..k {
            let ik = i * k + kk;
            let p = probability(logits, &scale, i, kk, j, k, cs);
            logits_grad[ik * cs + j] = p * (logits_grad[ik * cs + j] - dot);
        }
        let row = i * 3 * c;
        for si in 0..s {
            let ch = si * cs + j;
            qkv_grad[row + ch] = 0.0;
            qkv_grad[row + c + ch] = 0.0;
            qkv_grad[row + 2 * c + ch] = 0.0;
        }
    }
}

/// `qkv_grad[nbr, offset + ch] += delta_grad[i, κ, ch]` for every `(i, κ, ch)`; with `added`,
/// also `delta_out = delta_grad + delta_addend` (the relation's `∂δ` and the paired
/// aggregation's, `super::neighbour_op`) and the values' scatter the aggregation left to it,
/// `qkv_grad[nbr, 2c + ch] += delta_addend[i, κ, ch]` (`ValueScatter::ToRelation`).
#[cube(launch)]
#[allow(clippy::too_many_arguments)]
fn scatter_columns_kernel<A: AtomicAddF32>(
    neighbours: &[i32],
    delta_grad: &[f32],
    delta_addend: &[f32],
    delta_out: &mut [f32],
    qkv_grad: &[Atomic<A>],
    units: usize,
    offset: usize,
    added: u32,
    sizes: &Sizes,
) {
    let unit = ABSOLUTE_POS;
    if unit < units {
        if added != 0 {
            delta_out[unit] = delta_grad[unit] + delta_addend[unit];
        }
        let ch = unit % sizes.c;
        let ik = unit / sizes.c;
        let row = neighbours[ik];
        if row >= 0 && (row as usize) < sizes.n {
            let at = row as usize * 3 * sizes.c;
            A::atomic_add_f32(&qkv_grad[at + offset + ch], delta_grad[unit]);
            if added != 0 {
                A::atomic_add_f32(&qkv_grad[at + 2 * sizes.c + ch], delta_addend[unit]);
            }
        }
    }
}

/// `(n, k, c)` from `qkv` `[n, 3c]` and `delta` `[n, k, c]`.
fn sizes_of(qkv: &CubeTensor, delta: &CubeTensor) -> (usize, usize, usize) {
    let (q, d) = (qkv.shape(), delta.shape());
    (q[0], d[1], d[2])
}

/// Adds `delta_grad` into the columns `offset..offset + c` of `qkv_grad` at each neighbour's row;
/// with `sum = Some((addend, out))` also writes `delta_grad + addend` into `out` and adds
/// `addend` into the values' columns `2c..3c` (the paired aggregation's `∂δ`, which is its
/// values' gradient).
fn scatter_columns(
    client: &lifegom_render::cube::host::ComputeClient,
    neighbours: &CubeTensor,
    delta_grad: &cubecl::server::Handle,
    qkv_grad: &cubecl::server::Handle,
    offset: usize,
    (n, k, c): (usize, usize, usize),
    sum: Option<(&CubeTensor, &cubecl::server::Handle)>,
) {
    let units = n * k * c;
    // Without a sum the kernel writes nothing more: a word of its own stands in for the output
    // (a buffer bound twice, once writable, is not allowed).
    let spare = client.empty(4);
    let sum_args = || match sum {
        Some((addend, out)) => (tensor_arg(addend), arg(out, units), 1u32),
        None => (arg(delta_grad, units), arg(&spare, 1), 0u32),
    };
    macro_rules! launch {
        ($slot:ty) => {{
            let (addend, out, added) = sum_args();
            scatter_columns_kernel::launch::<$slot>(
                client,
                count_1d(units),
                CubeDim::new_1d(THREADS_1D),
                tensor_arg(neighbours),
                arg(delta_grad, units),
                addend,
                out,
                arg(qkv_grad, n * 3 * c),
                units,
                offset,
                added,
                SizesLaunch::new(n, k, c),
            )
        }};
    }
    if use_native_float_atomics(client) {
        launch!(f32);
    } else {
        launch!(u32);
    }
}

impl NeighbourAttentionOps for CubeBackend {
    fn attention_relation(
        qkv: FloatTensor<Self>,
        neighbours: IntTensor<Self>,
        delta: FloatTensor<Self>,
        scale: FloatTensor<Self>,
        shift: FloatTensor<Self>,
        _pair: AttentionPair,
    ) -> FloatTensor<Self> {
        let _span = tracing::trace_span!("cube_attention_relation").entered();
        let dtype = delta.dtype();
        let (client, device) = (delta.client.clone(), delta.device.clone());
        let (qkv, delta) = (prepare(qkv), prepare(delta));
        let (n, k, c) = sizes_of(&qkv, &delta);
        let (scale, shift) = (prepare(scale), prepare(shift));
        let neighbours = prepare_i32(neighbours);
        let units = n * k * c;
        let out = client.empty(4 * units.max(1));
        if units > 0 {
            relation_forward_kernel::launch(
                &client,
                count_1d(units),
                CubeDim::new_1d(THREADS_1D),
                tensor_arg(&qkv),
                tensor_arg(&neighbours),
                tensor_arg(&delta),
                tensor_arg(&scale),
                tensor_arg(&shift),
                arg(&out, units),
                units,
                SizesLaunch::new(n, k, c),
            );
        }
        cast_to(tensor_f32(&client, &device, out, &[n, k, c]), dtype)
    }

    fn attention_aggregate_gathered(
        qkv: FloatTensor<Self>,
        neighbours: IntTensor<Self>,
        delta: FloatTensor<Self>,
        logits: FloatTensor<Self>,
        out_scale: FloatTensor<Self>,
        out_shift: FloatTensor<Self>,
        ending: AggregateEnding,
        _pair: AttentionPair,
    ) -> FloatTensor<Self> {
        let _span = tracing::trace_span!("cube_attention_aggregate_gathered").entered();
        let dtype = delta.dtype();
        let (client, device) = (delta.client.clone(), delta.device.clone());
        let (qkv, delta, logits) = (prepare(qkv), prepare(delta), prepare(logits));
        let normed = ending == AggregateEnding::NormRelu;
        // Without the norm the kernel reads neither: `δ` is bound in their place.
        let (out_scale, out_shift) = if normed {
            (prepare(out_scale), prepare(out_shift))
        } else {
            (delta.clone(), delta.clone())
        };
        let (n, k, c) = sizes_of(&qkv, &delta);
        let cs = logits.shape()[2];
        let neighbours = prepare_i32(neighbours);
        let out = client.empty(4 * (n * c).max(1));
        let units = n * cs;
        if units > 0 && k > 0 {
            aggregate_gathered_forward_kernel::launch(
                &client,
                count_1d(units),
                CubeDim::new_1d(THREADS_1D),
                tensor_arg(&qkv),
                tensor_arg(&neighbours),
                tensor_arg(&delta),
                tensor_arg(&logits),
                tensor_arg(&out_scale),
                tensor_arg(&out_shift),
                arg(&out, n * c),
                units,
                cs,
                SizesLaunch::new(n, k, c),
                normed,
            );
        }
        cast_to(tensor_f32(&client, &device, out, &[n, c]), dtype)
    }
}

impl NeighbourAttentionKernels for CubeBackend {
    fn attention_relation_backward(
        qkv: FloatTensor<Self>,
        neighbours: IntTensor<Self>,
        delta: FloatTensor<Self>,
        scale: FloatTensor<Self>,
        shift: FloatTensor<Self>,
        grad: FloatTensor<Self>,
        addends: Option<(FloatTensor<Self>, FloatTensor<Self>)>,
    ) -> (FloatTensor<Self>, FloatTensor<Self>) {
        let _span = tracing::trace_span!("cube_attention_relation_backward").entered();
        let (qkv_dtype, delta_dtype) = (qkv.dtype(), delta.dtype());
        let (client, device) = (delta.client.clone(), delta.device.clone());
        let (qkv, delta, grad) = (prepare(qkv), prepare(delta), prepare(grad));
        let (n, k, c) = sizes_of(&qkv, &delta);
        let (scale, shift) = (prepare(scale), prepare(shift));
        let neighbours = prepare_i32(neighbours);
        let qkv_grad = client.empty(4 * (n * 3 * c).max(1));
        let delta_grad = client.empty(4 * (n * k * c).max(1));
        let addends = addends.map(|(q, d)| (prepare(q), prepare(d)));
        // With the paired aggregation's gradients the sum of both `∂δ` goes to a buffer of its
        // own: the scatter still reads the relation's alone for the keys.
        let delta_total = addends
            .as_ref()
            .map(|_| client.empty(4 * (n * k * c).max(1)));
        let units = n * c;
        if units > 0 {
            relation_backward_rows_kernel::launch(
                &client,
                count_1d(units),
                CubeDim::new_1d(THREADS_1D),
                tensor_arg(&qkv),
                tensor_arg(&neighbours),
                tensor_arg(&delta),
                tensor_arg(&scale),
                tensor_arg(&shift),
                tensor_arg(&grad),
                addends
                    .as_ref()
                    .map_or_else(|| tensor_arg(&grad), |(q, _)| tensor_arg(q)),
                arg(&qkv_grad, n * 3 * c),
                arg(&delta_grad, n * k * c),
                units,
                u32::from(addends.is_some()),
                SizesLaunch::new(n, k, c),
            );
            if k > 0 {
                let sum = addends
                    .as_ref()
                    .zip(delta_total.as_ref())
                    .map(|((_, d), out)| (d, out));
                scatter_columns(
                    &client,
                    &neighbours,
                    &delta_grad,
                    &qkv_grad,
                    c,
                    (n, k, c),
                    sum,
                );
            }
        }
        let delta_grad = delta_total.unwrap_or(delta_grad);
        (
            cast_to(
                tensor_f32(&client, &device, qkv_grad, &[n, 3 * c]),
                qkv_dtype,
            ),
            cast_to(
                tensor_f32(&client, &device, delta_grad, &[n, k, c]),
                delta_dtype,
            ),
        )
    }

    fn attention_aggregate_gathered_backward(
        qkv: FloatTensor<Self>,
        neighbours: IntTensor<Self>,
        delta: FloatTensor<Self>,
        logits: FloatTensor<Self>,
        grad: FloatTensor<Self>,
        scatter: ValueScatter,
        norm: Option<(FloatTensor<Self>, FloatTensor<Self>)>,
    ) -> (FloatTensor<Self>, FloatTensor<Self>, FloatTensor<Self>) {
        let _span = tracing::trace_span!("cube_attention_aggregate_gathered_backward").entered();
        let dtypes = (qkv.dtype(), delta.dtype(), logits.dtype());
        let (client, device) = (delta.client.clone(), delta.device.clone());
        let (qkv, delta, logits) = (prepare(qkv), prepare(delta), prepare(logits));
        let grad = prepare(grad);
        let normed = norm.is_some();
        // Without the norm the kernel reads neither: the gradient is bound in their place.
        let (output, out_scale) = match norm {
            Some((output, scale)) => (prepare(output), prepare(scale)),
            None => (grad.clone(), grad.clone()),
        };
        let (n, k, c) = sizes_of(&qkv, &delta);
        let cs = logits.shape()[2];
        let neighbours = prepare_i32(neighbours);
        let qkv_grad = client.empty(4 * (n * 3 * c).max(1));
        let delta_grad = client.empty(4 * (n * k * c).max(1));
        let logits_grad = client.empty(4 * (n * k * cs).max(1));
        let units = n * cs;
        if units > 0 && k > 0 {
            aggregate_gathered_backward_rows_kernel::launch(
                &client,
                count_1d(units),
                CubeDim::new_1d(THREADS_1D),
                tensor_arg(&qkv),
                tensor_arg(&neighbours),
                tensor_arg(&delta),
                tensor_arg(&logits),
                tensor_arg(&grad),
                tensor_arg(&output),
                tensor_arg(&out_scale),
                arg(&qkv_grad, n * 3 * c),
                arg(&delta_grad, n * k * c),
                arg(&logits_grad, n * k * cs),
                units,
                cs,
                SizesLaunch::new(n, k, c),
                normed,
            );
            if scatter == ValueScatter::Here {
                scatter_columns(
                    &client,
                    &neighbours,
                    &delta_grad,
                    &qkv_grad,
                    2 * c,
                    (n, k, c),
                    None,
                );
            }
        }
        (
            cast_to(
                tensor_f32(&client, &device, qkv_grad, &[n, 3 * c]),
                dtypes.0,
            ),
            cast_to(
                tensor_f32(&client, &device, delta_grad, &[n, k, c]),
                dtypes.1,
            ),
            cast_to(
                tensor_f32(&client, &device, logits_grad, &[n, k, cs]),
                dtypes.2,
            ),
        )
    }
}
