//! The Point Transformer layer's vector attention around its weight MLP as two custom ops on the
//! CPU backends (design.md §7.5).
//!
//! For point `i`, neighbour `j` (of `k`) and channel `m` of `c`, the layer computes
//!
//! 1. the **relation** `r_ij = ReLU(s ⊙ (k_j − q_i + δ_ij) + t)`, with `(s, t)` the frozen BN
//!    `linear_w.0` as a per-channel affine map ([`point_relation`]);
//! 2. the weight MLP's Linears on `r` (Burn `Linear`s; not here);
//! 3. the **aggregation** `out_i[g·c_w + m] = Σ_j a_ij[m] · (v_j + δ_ij)[g·c_w + m]` with
//!    `a_i·[m] = softmax_j(w_i·[m])` over the neighbours and the `c_w = c/s_p` attention channels
//!    shared by the `s_p` groups of value channels ([`point_aggregation`]).
//!
//! As tensor ops those are a subtraction, an addition, the BN's multiply and add and a ReLU for
//! (1), and a five-op softmax, an addition, a broadcast multiply and a sum for (3): about a
//! dozen autodiff nodes per layer, each with an intermediate of the layer's `[n, k, c]`, on one
//! core. At the tiny preset's widths (8–64 channels) the Point Transformer is dominated by that
//! per-op cost. Here each is one pass, one rayon task per block of points, and one node.
//!
//! Backwards, with `g` the output gradient:
//!
//! - relation: `h = g·[r > 0]`; `∂k_j = ∂δ_ij = s ⊙ h_ij`, `∂q_i = −Σ_j s ⊙ h_ij`,
//!   `∂s = Σ_ij h_ij ⊙ (k_j − q_i + δ_ij)`, `∂t = Σ_ij h_ij` (per-task partial sums added in task
//!   order, so the result does not depend on the thread count);
//! - aggregation: `∂v_j = ∂δ_ij = a_ij ⊙ g_i` (per group), `∂a_ij[m] = Σ_g g_i[g·c_w + m]·(v_j +
//!   δ_ij)[g·c_w + m]`, `∂w_ij = a_ij ⊙ (∂a_ij − Σ_j' a_ij' ⊙ ∂a_ij')`, recomputing `a`.
//!
//! The gathered keys and values `k_j`, `v_j` come in already gathered (`[n, k, c]`). CubeCL
//! devices, and the tests' reference, keep the tensor-op composition
//! ([`super::PointTransformerLayer`] routes by [`VectorAttentionKernel`]).

// NdArray is deprecated in Burn 0.22 in favour of Flex; ndarray is the CI backend the project
// requires (design.md §1.4).
#![allow(deprecated)]

use burn::backend::TensorMetadata;
use burn::backend::autodiff::checkpoint::base::Checkpointer;
use burn::backend::autodiff::checkpoint::strategy::CheckpointStrategy;
use burn::backend::autodiff::grads::Gradients;
use burn::backend::autodiff::ops::{Backward, Ops};
use burn::backend::tensor::FloatTensor;
use burn::backend::{Autodiff, Backend, Flex, NdArray, backend_extension};
use burn::tensor::{Device, Element, Shape, Tensor};
use bytemuck::Pod;
use rayon::prelude::*;

use crate::fusion::kernels::Real;
use lifegom_render::device::runs_on_host;
use lifegom_render::in_precision;
use lifegom_render::op_backward::{gradient_per_input, record};
use lifegom_render::readback::{HostLend, cpu_float_from};

/// Points per rayon task: the layers have 4 to 1,229 points, so the finest level splits into
/// dozens of tasks and the coarsest runs as one.
const POINTS_PER_TASK: usize = 32;

/// How the PT layer's relation and aggregation are computed.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum VectorAttentionKernel {
    /// The custom ops of this module (CPU backends).
    HostOps,
    /// Burn tensor-op compositions (CubeCL devices; the reference in tests).
    TensorOps,
}

impl VectorAttentionKernel {
    /// The fast choice for `device`.
    pub fn for_device(device: &Device) -> Self {
        if runs_on_host(device) {
            Self::HostOps
        } else {
            Self::TensorOps
        }
    }
}

/// `ReLU(scale ⊙ (keys − query_i + delta) + shift)`: `keys`, `delta` `[n, k, c]`, `query`
/// `[n, c]`, `scale`, `shift` `[c]` → `[n, k, c]`. CPU devices only (callers route).
pub fn point_relation(
    keys: Tensor<3>,
    query: Tensor<2>,
    delta: Tensor<3>,
    scale: Tensor<1>,
    shift: Tensor<1>,
) -> Tensor<3> {
    Tensor::from_dispatch(
        <burn::backend::Dispatch as PointRelationOps>::point_relation(
            keys.into_dispatch(),
            query.into_dispatch(),
            delta.into_dispatch(),
            scale.into_dispatch(),
            shift.into_dispatch(),
        ),
    )
}

/// `Σ_j softmax_j(logits) ⊙ (values + delta)` with the `c/s` logit channels shared by the `s`
/// groups of value channels: `values`, `delta` `[n, k, c]`, `logits` `[n, k, c/s]` → `[n, c]`.
/// CPU devices only (callers route).
pub fn point_aggregation(values: Tensor<3>, delta: Tensor<3>, logits: Tensor<3>) -> Tensor<2> {
    Tensor::from_dispatch(
        <burn::backend::Dispatch as PointAggregationOps>::point_aggregation(
            values.into_dispatch(),
            delta.into_dispatch(),
            logits.into_dispatch(),
        ),
    )
}

/// See [`point_relation`].
#[backend_extension(NdArray, Flex, Autodiff)]
pub trait PointRelationOps: Backend {
    /// The relation of every point to each of its neighbours.
    fn point_relation(
        keys: FloatTensor<Self>,
        query: FloatTensor<Self>,
        delta: FloatTensor<Self>,
        scale: FloatTensor<Self>,
        shift: FloatTensor<Self>,
    ) -> FloatTensor<Self>;
}

/// See [`point_aggregation`].
#[backend_extension(NdArray, Flex, Autodiff)]
pub trait PointAggregationOps: Backend {
    /// The attention-weighted sum over every point's neighbours.
    fn point_aggregation(
        values: FloatTensor<Self>,
        delta: FloatTensor<Self>,
        logits: FloatTensor<Self>,
    ) -> FloatTensor<Self>;
}

/// The relation op's inputs on one backend: what the forward takes and the node keeps.
#[derive(Debug, Clone)]
pub struct RelationInputs<B: Backend> {
    keys: FloatTensor<B>,
    query: FloatTensor<B>,
    delta: FloatTensor<B>,
    scale: FloatTensor<B>,
    shift: FloatTensor<B>,
}

/// The aggregation op's inputs on one backend.
#[derive(Debug, Clone)]
pub struct AggregationInputs<B: Backend> {
    values: FloatTensor<B>,
    delta: FloatTensor<B>,
    logits: FloatTensor<B>,
}

/// What a backend implements so that `Autodiff<B>` can differentiate the ops.
#[doc(hidden)]
pub trait VectorAttentionKernels: Backend {
    /// The relation forward.
    fn relation_forward(inputs: RelationInputs<Self>) -> FloatTensor<Self>;
    /// `[∂keys, ∂query, ∂delta, ∂scale, ∂shift]`.
    fn relation_backward(
        inputs: RelationInputs<Self>,
        grad: FloatTensor<Self>,
    ) -> [FloatTensor<Self>; 5];
    /// The aggregation forward.
    fn aggregation_forward(inputs: AggregationInputs<Self>) -> FloatTensor<Self>;
    /// `[∂values, ∂delta, ∂logits]`.
    fn aggregation_backward(
        inputs: AggregationInputs<Self>,
        grad: FloatTensor<Self>,
    ) -> [FloatTensor<Self>; 3];
}

/// Sizes of one call: `points` × `neighbours` × `channels`, of which `weights` attention
/// channels (the aggregation's; the relation's is unused).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct PointShape {
    /// Points n.
    pub points: usize,
    /// Neighbours per point k.
    pub neighbours: usize,
    /// Channels c.
    pub channels: usize,
    /// Attention channels `c/s` (a divisor of `channels`).
    pub weights: usize,
}

impl PointShape {
    fn of(pairs: &Shape, weights: usize) -> Self {
        Self {
            points: pairs[0],
            neighbours: pairs[1],
            channels: pairs[2],
            weights,
        }
    }
}

/// The relation forward on host slices (module docs).
pub fn relation_forward<T: Real>(
    keys: &[T],
    query: &[T],
    delta: &[T],
    scale: &[T],
    shift: &[T],
    shape: PointShape,
) -> Vec<T> {
    let PointShape {
        neighbours: k,
        channels: c,
        ..
    } = shape;
    let mut out = vec![T::zero(); keys.len()];
    out.par_chunks_mut(POINTS_PER_TASK * k * c)
        .enumerate()
        .for_each(|(task, out)| {
            for (local, out_i) in out.chunks_mut(k * c).enumerate() {
                let i = task * POINTS_PER_TASK + local;
                let q = &query[i * c..][..c];
                for j in 0..k {
                    let at = (i * k + j) * c;
                    let (kj, dj) = (&keys[at..][..c], &delta[at..][..c]);
                    for (m, o) in out_i[j * c..][..c].iter_mut().enumerate() {
                        let y = scale[m] * (kj[m] - q[m] + dj[m]) + shift[m];
                        // `≤ 0` rather than `max`: a NaN stays NaN, as in Burn's ReLU.
                        *o = if y <= T::zero() { T::zero() } else { y };
                    }
                }
            }
        });
    out
}

/// Gradients of [`relation_forward`]: `(∂keys = ∂delta, ∂query, ∂scale, ∂shift)`.
pub fn relation_backward<T: Real>(
    keys: &[T],
    query: &[T],
    delta: &[T],
    scale: &[T],
    shift: &[T],
    grad: &[T],
    shape: PointShape,
) -> (Vec<T>, Vec<T>, Vec<T>, Vec<T>) {
    let PointShape {
        neighbours: k,
        channels: c,
        ..
    } = shape;
    let mut d_pair = vec![T::zero(); keys.len()];
    let mut d_query = vec![T::zero(); query.len()];
    let partials: Vec<(Vec<T>, Vec<T>)> = d_pair
        .par_chunks_mut(POINTS_PER_TASK * k * c)
        .zip(d_query.par_chunks_mut(POINTS_PER_TASK * c))
        .enumerate()
        .map(|(task, (d_pair, d_query))| {
            let (mut d_scale, mut d_shift) = (vec![T::zero(); c], vec![T::zero(); c]);
            for (local, (dp_i, dq_i)) in d_pair
                .chunks_mut(k * c)
                .zip(d_query.chunks_mut(c))
                .enumerate()
            {
                let i = task * POINTS_PER_TASK + local;
                let q = &query[i * c..][..c];
                for j in 0..k {
                    let at = (i * k + j) * c;
                    let (kj, dj, gj) = (&keys[at..][..c], &delta[at..][..c], &grad[at..][..c]);
                    for m in 0..c {
                        let z = kj[m] - q[m] + dj[m];
                        let y = scale[m] * z + shift[m];
                        let h = if y <= T::zero() { T::zero() } else { gj[m] };
                        dp_i[j * c + m] = scale[m] * h;
                        dq_i[m] = dq_i[m] - scale[m] * h;
                        d_scale[m] += h * z;
                        d_shift[m] += h;
                    }
                }
            }
            (d_scale, d_shift)
        })
        .collect();
    let (mut d_scale, mut d_shift) = (vec![T::zero(); c], vec![T::zero(); c]);
    for (ds, dt) in partials {
        for m in 0..c {
            d_scale[m] += ds[m];
            d_shift[m] += dt[m];
        }
    }
    (d_pair, d_query, d_scale, d_shift)
}

/// `a ← softmax_j(logits_i·[m])` for every attention channel `m` of point `i`; `logits_i` and `a`
/// are `[k, c_w]`.
fn point_softmax<T: Real>(a: &mut [T], logits_i: &[T], k: usize, cw: usize) {
    for m in 0..cw {
        let max = (0..k).fold(T::neg_infinity(), |mx, j| mx.max(logits_i[j * cw + m]));
        let mut sum = T::zero();
        for j in 0..k {
            let e = (logits_i[j * cw + m] - max).exp();
            a[j * cw + m] = e;
            sum += e;
        }
        for j in 0..k {
            a[j * cw + m] = a[j * cw + m] / sum;
        }
    }
}

/// The aggregation forward on host slices (module docs).
pub fn aggregation_forward<T: Real>(
    values: &[T],
    delta: &[T],
    logits: &[T],
    shape: PointShape,
) -> Vec<T> {
    let PointShape {
        points: n,
        neighbours: k,
        channels: c,
        weights: cw,
    } = shape;
    let mut out = vec![T::zero(); n * c];
    out.par_chunks_mut(POINTS_PER_TASK * c)
        .enumerate()
        .for_each(|(task, out)| {
            let mut a = vec![T::zero(); k * cw];
            for (local, out_i) in out.chunks_mut(c).enumerate() {
                let i = task * POINTS_PER_TASK + local;
                point_softmax(&mut a, &logits[i * k * cw..][..k * cw], k, cw);
                for j in 0..k {
                    let at = (i * k + j) * c;
                    let (vj, dj, aj) = (&values[at..][..c], &delta[at..][..c], &a[j * cw..][..cw]);
                    for (ch, o) in out_i.iter_mut().enumerate() {
                        *o += aj[ch % cw] * (vj[ch] + dj[ch]);
                    }
                }
            }
        });
    out
}

/// Gradients of [`aggregation_forward`]: `(∂values = ∂delta, ∂logits)`.
pub fn aggregation_backward<T: Real>(
    values: &[T],
    delta: &[T],
    logits: &[T],
    grad: &[T],
    shape: PointShape,
) -> (Vec<T>, Vec<T>) {
    let PointShape {
        neighbours: k,
        channels: c,
        weights: cw,
        ..
    } = shape;
    let mut d_pair = vec![T::zero(); values.len()];
    let mut d_logits = vec![T::zero(); logits.len()];
    d_pair
        .par_chunks_mut(POINTS_PER_TASK * k * c)
        .zip(d_logits.par_chunks_mut(POINTS_PER_TASK * k * cw))
        .enumerate()
        .for_each(|(task, (d_pair, d_logits))| {
            let (mut a, mut da) = (vec![T::zero(); k * cw], vec![T::zero(); k * cw]);
            for (local, (dp_i, dl_i)) in d_pair
                .chunks_mut(k * c)
                .zip(d_logits.chunks_mut(k * cw))
                .enumerate()
            {
                let i = task * POINTS_PER_TASK + local;
                let g = &grad[i * c..][..c];
                point_softmax(&mut a, &logits[i * k * cw..][..k * cw], k, cw);
                da.fill(T::zero());
                for j in 0..k {
                    let at = (i * k + j) * c;
                    let (vj, dj) = (&values[at..][..c], &delta[at..][..c]);
                    for ch in 0..c {
                        let m = ch % cw;
                        dp_i[j * c + ch] = a[j * cw + m] * g[ch];
                        da[j * cw + m] += g[ch] * (vj[ch] + dj[ch]);
                    }
                }
                for m in 0..cw {
                    let dot = (0..k).fold(T::zero(), |s, j| s + a[j * cw + m] * da[j * cw + m]);
                    for j in 0..k {
                        dl_i[j * cw + m] = a[j * cw + m] * (da[j * cw + m] - dot);
                    }
                }
            }
        });
    (d_pair, d_logits)
}

fn cpu_relation_forward<B: HostLend>(inputs: RelationInputs<B>) -> FloatTensor<B> {
    in_precision!(inputs.keys.dtype(), cpu_relation_forward_in(inputs))
}

fn cpu_relation_forward_in<B: HostLend, T: Real + Element + Pod>(
    inputs: RelationInputs<B>,
) -> FloatTensor<B> {
    let (device, dtype, shape) = (
        inputs.keys.device(),
        inputs.keys.dtype(),
        inputs.keys.shape(),
    );
    let dims = PointShape::of(&shape, 0);
    let keys = B::lend_float::<T>("relation keys", &inputs.keys);
    let query = B::lend_float::<T>("relation query", &inputs.query);
    let delta = B::lend_float::<T>("relation positional encoding", &inputs.delta);
    let scale = B::lend_float::<T>("relation scale", &inputs.scale);
    let shift = B::lend_float::<T>("relation shift", &inputs.shift);
    let out = relation_forward(&keys, &query, &delta, &scale, &shift, dims);
    cpu_float_from::<B, T>(out, shape, dtype, &device)
}

fn cpu_relation_backward<B: HostLend>(
    inputs: RelationInputs<B>,
    grad: FloatTensor<B>,
) -> [FloatTensor<B>; 5] {
    in_precision!(inputs.keys.dtype(), cpu_relation_backward_in(inputs, grad))
}

fn cpu_relation_backward_in<B: HostLend, T: Real + Element + Pod>(
    inputs: RelationInputs<B>,
    grad: FloatTensor<B>,
) -> [FloatTensor<B>; 5] {
    let device = inputs.keys.device();
    let dims = PointShape::of(&inputs.keys.shape(), 0);
    let meta = |t: &FloatTensor<B>| (t.shape(), t.dtype());
    let [(sk, tk), (sq, tq), (sd, td), (ss, ts), (st, tt)] = [
        &inputs.keys,
        &inputs.query,
        &inputs.delta,
        &inputs.scale,
        &inputs.shift,
    ]
    .map(meta);
    let g = B::lend_float::<T>("relation gradient", &grad);
    let keys = B::lend_float::<T>("relation keys", &inputs.keys);
    let query = B::lend_float::<T>("relation query", &inputs.query);
    let delta = B::lend_float::<T>("relation positional encoding", &inputs.delta);
    let scale = B::lend_float::<T>("relation scale", &inputs.scale);
    let shift = B::lend_float::<T>("relation shift", &inputs.shift);
    let (d_pair, d_query, d_scale, d_shift) =
        relation_backward(&keys, &query, &delta, &scale, &shift, &g, dims);
    let d_delta = cpu_float_from::<B, T>(d_pair.clone(), sd, td, &device);
    [
        cpu_float_from::<B, T>(d_pair, sk, tk, &device),
        cpu_float_from::<B, T>(d_query, sq, tq, &device),
        d_delta,
        cpu_float_from::<B, T>(d_scale, ss, ts, &device),
        cpu_float_from::<B, T>(d_shift, st, tt, &device),
    ]
}

fn cpu_aggregation_forward<B: HostLend>(inputs: AggregationInputs<B>) -> FloatTensor<B> {
    in_precision!(inputs.values.dtype(), cpu_aggregation_forward_in(inputs))
}

fn cpu_aggregation_forward_in<B: HostLend, T: Real + Element + Pod>(
    inputs: AggregationInputs<B>,
) -> FloatTensor<B> {
    let (device, dtype, shape) = (
        inputs.values.device(),
        inputs.values.dtype(),
        inputs.values.shape(),
    );
    let dims = PointShape::of(&shape, inputs.logits.shape()[2]);
    let values = B::lend_float::<T>("aggregation values", &inputs.values);
    let delta = B::lend_float::<T>("aggregation positional encoding", &inputs.delta);
    let logits = B::lend_float::<T>("aggregation logits", &inputs.logits);
    let out = aggregation_forward(&values, &delta, &logits, dims);
    let out_shape = Shape::from(vec![dims.points, dims.channels]);
    cpu_float_from::<B, T>(out, out_shape, dtype, &device)
}

fn cpu_aggregation_backward<B: HostLend>(
    inputs: AggregationInputs<B>,
    grad: FloatTensor<B>,
) -> [FloatTensor<B>; 3] {
    in_precision!(
        inputs.values.dtype(),
        cpu_aggregation_backward_in(inputs, grad)
    )
}

fn cpu_aggregation_backward_in<B: HostLend, T: Real + Element + Pod>(
    inputs: AggregationInputs<B>,
    grad: FloatTensor<B>,
) -> [FloatTensor<B>; 3] {
    let device = inputs.values.device();
    let dims = PointShape::of(&inputs.values.shape(), inputs.logits.shape()[2]);
    let meta = |t: &FloatTensor<B>| (t.shape(), t.dtype());
    let [(sv, tv), (sd, td), (sl, tl)] = [&inputs.values, &inputs.delta, &inputs.logits].map(meta);
    let g = B::lend_float::<T>("aggregation gradient", &grad);
    let values = B::lend_float::<T>("aggregation values", &inputs.values);
    let delta = B::lend_float::<T>("aggregation positional encoding", &inputs.delta);
    let logits = B::lend_float::<T>("aggregation logits", &inputs.logits);
    let (d_pair, d_logits) = aggregation_backward(&values, &delta, &logits, &g, dims);
    let d_delta = cpu_float_from::<B, T>(d_pair.clone(), sd, td, &device);
    [
        cpu_float_from::<B, T>(d_pair, sv, tv, &device),
        d_delta,
        cpu_float_from::<B, T>(d_logits, sl, tl, &device),
    ]
}

/// Implements both ops for a CPU backend through the shared slice kernels.
macro_rules! cpu_vector_attention_backend {
    ($backend:ty) => {
        impl PointRelationOps for $backend {
            fn point_relation(
                keys: FloatTensor<Self>,
                query: FloatTensor<Self>,
                delta: FloatTensor<Self>,
                scale: FloatTensor<Self>,
                shift: FloatTensor<Self>,
            ) -> FloatTensor<Self> {
                cpu_relation_forward::<Self>(RelationInputs {
                    keys,
                    query,
                    delta,
                    scale,
                    shift,
                })
            }
        }

        impl PointAggregationOps for $backend {
            fn point_aggregation(
                values: FloatTensor<Self>,
                delta: FloatTensor<Self>,
                logits: FloatTensor<Self>,
            ) -> FloatTensor<Self> {
                cpu_aggregation_forward::<Self>(AggregationInputs {
                    values,
                    delta,
                    logits,
                })
            }
        }

        impl VectorAttentionKernels for $backend {
            fn relation_forward(inputs: RelationInputs<Self>) -> FloatTensor<Self> {
                cpu_relation_forward::<Self>(inputs)
            }

            fn relation_backward(
                inputs: RelationInputs<Self>,
                grad: FloatTensor<Self>,
            ) -> [FloatTensor<Self>; 5] {
                cpu_relation_backward::<Self>(inputs, grad)
            }

            fn aggregation_forward(inputs: AggregationInputs<Self>) -> FloatTensor<Self> {
                cpu_aggregation_forward::<Self>(inputs)
            }

            fn aggregation_backward(
                inputs: AggregationInputs<Self>,
                grad: FloatTensor<Self>,
            ) -> [FloatTensor<Self>; 3] {
                cpu_aggregation_backward::<Self>(inputs, grad)
            }
        }
    };
}

cpu_vector_attention_backend!(NdArray);
cpu_vector_attention_backend!(Flex);

#[derive(Debug)]
struct RelationBackward;

impl<B: VectorAttentionKernels> Backward<B, 5> for RelationBackward {
    type State = RelationInputs<B>;

    fn backward(
        self,
        ops: Ops<Self::State, 5>,
        grads: &mut Gradients,
        _checkpointer: &mut Checkpointer,
    ) {
        gradient_per_input::<B, _, 5>(ops, grads, B::relation_backward);
    }
}

#[derive(Debug)]
struct AggregationBackward;

impl<B: VectorAttentionKernels> Backward<B, 3> for AggregationBackward {
    type State = AggregationInputs<B>;

    fn backward(
        self,
        ops: Ops<Self::State, 3>,
        grads: &mut Gradients,
        _checkpointer: &mut Checkpointer,
    ) {
        gradient_per_input::<B, _, 3>(ops, grads, B::aggregation_backward);
    }
}

impl<B: PointRelationOps + VectorAttentionKernels, C: CheckpointStrategy> PointRelationOps
    for Autodiff<B, C>
{
    fn point_relation(
        keys: FloatTensor<Self>,
        query: FloatTensor<Self>,
        delta: FloatTensor<Self>,
        scale: FloatTensor<Self>,
        shift: FloatTensor<Self>,
    ) -> FloatTensor<Self> {
        let (keys, k_node) = keys.into_parts();
        let (query, q_node) = query.into_parts();
        let (delta, d_node) = delta.into_parts();
        let (scale, s_node) = scale.into_parts();
        let (shift, t_node) = shift.into_parts();
        record::<B, C, _, _, 5>(
            RelationBackward,
            [k_node, q_node, d_node, s_node, t_node],
            RelationInputs {
                keys,
                query,
                delta,
                scale,
                shift,
            },
            B::relation_forward,
        )
    }
}

impl<B: PointAggregationOps + VectorAttentionKernels, C: CheckpointStrategy> PointAggregationOps
    for Autodiff<B, C>
{
    fn point_aggregation(
        values: FloatTensor<Self>,
        delta: FloatTensor<Self>,
        logits: FloatTensor<Self>,
    ) -> FloatTensor<Self> {
        let (values, v_node) = values.into_parts();
        let (delta, d_node) = delta.into_parts();
        let (logits, l_node) = logits.into_parts();
        record::<B, C, _, _, 3>(
            AggregationBackward,
            [v_node, d_node, l_node],
            AggregationInputs {
                values,
                delta,
                logits,
            },
            B::aggregation_forward,
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::tensor::Distribution;
    use burn::tensor::activation::{relu, softmax};
    use lifegom_render::testing::read;

    /// The relation as tensor ops (the layer's reference route).
    fn relation_reference(
        keys: Tensor<3>,
        query: Tensor<2>,
        delta: Tensor<3>,
        scale: Tensor<1>,
        shift: Tensor<1>,
    ) -> Tensor<3> {
        let c = scale.dims()[0];
        relu(
            (keys - query.unsqueeze_dim::<3>(1) + delta) * scale.reshape([1, 1, c])
                + shift.reshape([1, 1, c]),
        )
    }

    /// The aggregation as tensor ops.
    fn aggregation_reference(values: Tensor<3>, delta: Tensor<3>, logits: Tensor<3>) -> Tensor<2> {
        let [n, k, c] = values.dims();
        let cw = logits.dims()[2];
        ((values + delta).reshape([n, k, c / cw, cw]) * softmax(logits, 1).unsqueeze_dim::<4>(2))
            .sum_dim(1)
            .reshape([n, c])
    }

    fn assert_close(ours: &[f32], theirs: &[f32], what: &str) {
        assert_eq!(ours.len(), theirs.len(), "{what}");
        let scale = theirs.iter().fold(1.0f32, |m, v| m.max(v.abs()));
        for (i, (x, y)) in ours.iter().zip(theirs).enumerate() {
            assert!((x - y).abs() <= 2e-5 * scale, "{what}[{i}]: {x} vs {y}");
        }
    }

    /// Both ops against their tensor-op compositions: values and every input's gradient, at a
    /// size that splits into several rayon tasks and one that does not, with inputs that put
    /// some relations below the ReLU's kink.
    fn ops_match_tensor_ops(device: &Device) {
        let ad = device.clone().autodiff();
        let normal = |dims: Vec<usize>, std: f64| {
            Tensor::<3>::random(
                [dims[0], dims[1], dims[2]],
                Distribution::Normal(0.0, std),
                &ad,
            )
            .require_grad()
        };
        for (n, k, c, share) in [
            (3usize, 4usize, 8usize, 4usize),
            (100, 16, 16, 4),
            (70, 8, 8, 1),
        ] {
            let (keys, delta, values) = (
                normal(vec![n, k, c], 1.0),
                normal(vec![n, k, c], 1.0),
                normal(vec![n, k, c], 1.0),
            );
            let logits = normal(vec![n, k, c / share], 3.0);
            let query =
                Tensor::<2>::random([n, c], Distribution::Normal(0.0, 1.0), &ad).require_grad();
            let scale =
                Tensor::<1>::random([c], Distribution::Uniform(0.5, 1.5), &ad).require_grad();
            let shift =
                Tensor::<1>::random([c], Distribution::Normal(0.0, 0.3), &ad).require_grad();
            let mix_r = Tensor::<3>::random([n, k, c], Distribution::Normal(0.0, 1.0), &ad);
            let mix_a = Tensor::<2>::random([n, c], Distribution::Normal(0.0, 1.0), &ad);

            let relation = |ours: bool| {
                let args = (
                    keys.clone(),
                    query.clone(),
                    delta.clone(),
                    scale.clone(),
                    shift.clone(),
                );
                let out = if ours {
                    point_relation(args.0, args.1, args.2, args.3, args.4)
                } else {
                    relation_reference(args.0, args.1, args.2, args.3, args.4)
                };
                let grads = (out.clone() * mix_r.clone()).sum().backward();
                vec![
                    read(out),
                    read(keys.grad(&grads).expect("keys gradient")),
                    read(query.grad(&grads).expect("query gradient")),
                    read(delta.grad(&grads).expect("delta gradient")),
                    read(scale.grad(&grads).expect("scale gradient")),
                    read(shift.grad(&grads).expect("shift gradient")),
                ]
            };
            let (ours, theirs) = (relation(true), relation(false));
            let zeros = ours[0].iter().filter(|&&v| v == 0.0).count();
            assert!(zeros > 0 && zeros < ours[0].len(), "both sides of the ReLU");
            for (t, what) in ["relation", "∂keys", "∂query", "∂delta", "∂scale", "∂shift"]
                .iter()
                .enumerate()
            {
                assert_close(&ours[t], &theirs[t], &format!("{n}×{k}×{c} {what}"));
            }

            let aggregation = |ours: bool| {
                let args = (values.clone(), delta.clone(), logits.clone());
                let out = if ours {
                    point_aggregation(args.0, args.1, args.2)
                } else {
                    aggregation_reference(args.0, args.1, args.2)
                };
                let grads = (out.clone() * mix_a.clone()).sum().backward();
                vec![
                    read(out),
                    read(values.grad(&grads).expect("values gradient")),
                    read(delta.grad(&grads).expect("delta gradient")),
                    read(logits.grad(&grads).expect("logits gradient")),
                ]
            };
            let (ours, theirs) = (aggregation(true), aggregation(false));
            for (t, what) in ["aggregation", "∂values", "∂delta", "∂logits"]
                .iter()
                .enumerate()
            {
                assert_close(&ours[t], &theirs[t], &format!("{n}×{k}×{c}/{share} {what}"));
            }
        }
    }

    lifegom_render::cpu_backend_tests!(vector_attention_ops => ops_match_tensor_ops);

    /// The kernels in `f64` against central finite differences of a random projection of their
    /// outputs, for every input.
    #[test]
    fn kernels_match_finite_differences() {
        let mut rng = lifegom_render::rng::Rng::new(11);
        let shape = PointShape {
            points: 3,
            neighbours: 4,
            channels: 6,
            weights: 3,
        };
        let (n, k, c, cw) = (3, 4, 6, 3);
        let mut random = |len: usize| (0..len).map(|_| rng.range(-1.0, 1.0)).collect::<Vec<f64>>();
        let (keys, delta, values) = (random(n * k * c), random(n * k * c), random(n * k * c));
        let (query, logits) = (random(n * c), random(n * k * cw));
        let (scale, shift) = (random(c), random(c));
        let (mix_r, mix_a) = (random(n * k * c), random(n * c));
        let dot = |a: &[f64], b: &[f64]| a.iter().zip(b).map(|(x, y)| x * y).sum::<f64>();
        let eps = 1e-6;
        let check = |analytic: &[f64], input: &[f64], loss: &dyn Fn(&[f64]) -> f64, what: &str| {
            for (i, &d) in analytic.iter().enumerate() {
                let (mut plus, mut minus) = (input.to_vec(), input.to_vec());
                plus[i] += eps;
                minus[i] -= eps;
                let numeric = (loss(&plus) - loss(&minus)) / (2.0 * eps);
                assert!(
                    (numeric - d).abs() < 1e-6 * (1.0 + d.abs()),
                    "{what}[{i}]: analytic {d} vs numeric {numeric}"
                );
            }
        };

        let (d_pair, d_query, d_scale, d_shift) =
            relation_backward(&keys, &query, &delta, &scale, &shift, &mix_r, shape);
        let rel = |kk: &[f64], q: &[f64], d: &[f64], s: &[f64], t: &[f64]| {
            dot(&relation_forward(kk, q, d, s, t, shape), &mix_r)
        };
        check(
            &d_pair,
            &keys,
            &|x| rel(x, &query, &delta, &scale, &shift),
            "∂keys",
        );
        check(
            &d_query,
            &query,
            &|x| rel(&keys, x, &delta, &scale, &shift),
            "∂query",
        );
        check(
            &d_pair,
            &delta,
            &|x| rel(&keys, &query, x, &scale, &shift),
            "∂delta",
        );
        check(
            &d_scale,
            &scale,
            &|x| rel(&keys, &query, &delta, x, &shift),
            "∂scale",
        );
        check(
            &d_shift,
            &shift,
            &|x| rel(&keys, &query, &delta, &scale, x),
            "∂shift",
        );

        let (d_vals, d_logits) = aggregation_backward(&values, &delta, &logits, &mix_a, shape);
        let agg =
            |v: &[f64], d: &[f64], l: &[f64]| dot(&aggregation_forward(v, d, l, shape), &mix_a);
        check(&d_vals, &values, &|x| agg(x, &delta, &logits), "∂values");
        check(&d_vals, &delta, &|x| agg(&values, x, &logits), "∂delta");
        check(&d_logits, &logits, &|x| agg(&values, &delta, x), "∂logits");
    }
}
