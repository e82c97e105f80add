//! The Point Transformer layer's neighbourhood ops ([`super::relation`],
//! [`super::aggregate_gathered`]) as a Burn backend extension for CubeCL devices (design.md
//! §7.5).
//!
//! Listed for `Cube`, `Fusion` and `Autodiff` only: the CPU backends keep the tensor-op
//! composition, and the public functions never route them here. The autodiff nodes keep their
//! inputs (handles, no copies) and recompute what the backward needs. `scale` and `shift` of the
//! relation are the frozen BatchNorm's and take no gradient (design.md §7.5); the neighbour
//! table is an int tensor and takes none either.

use burn::backend::autodiff::checkpoint::base::Checkpointer;
use burn::backend::autodiff::checkpoint::strategy::CheckpointStrategy;
use burn::backend::autodiff::grads::Gradients;
use burn::backend::autodiff::ops::{Backward, Ops};
use burn::backend::fusion::{Fusion, FusionBackend};
use burn::backend::tensor::{FloatTensor, IntTensor};
use burn::backend::{Autodiff, Backend, TensorMetadata, backend_extension};
use lifegom_render::cube::deferred::{Input, Value, array, deferred, float_like};
use lifegom_render::op_backward::{gradient_per_input, record};

/// The neighbourhood half of vector attention (see [`super`]).
///
/// `qkv` `[n, 3c]` (query, key, value columns), `neighbours` `[n·k]` (int), `delta` `[n, k, c]`;
/// outputs in `delta`'s float dtype. Callers check shapes.
#[backend_extension(Cube, Fusion, Autodiff)]
pub trait NeighbourAttentionOps: Backend {
    /// `relu((k[nbr] − q[i] + δ)·scale + shift)`, `[n, k, c]`.
    #[fusion(dtype = delta, shape = delta.clone())]
    fn attention_relation(
        qkv: FloatTensor<Self>,
        neighbours: IntTensor<Self>,
        delta: FloatTensor<Self>,
        scale: FloatTensor<Self>,
        shift: FloatTensor<Self>,
    ) -> FloatTensor<Self>;

    /// `Σ_κ softmax_κ(logits)·(v[nbr] + δ)`, `[n, c]`, with `logits` `[n, k, C/S]`.
    #[fusion(dtype = delta, shape = burn::tensor::Shape::new([delta[0], delta[2]]))]
    fn attention_aggregate_gathered(
        qkv: FloatTensor<Self>,
        neighbours: IntTensor<Self>,
        delta: FloatTensor<Self>,
        logits: FloatTensor<Self>,
    ) -> FloatTensor<Self>;
}

/// What a backend implements so that `Autodiff<B>` can differentiate the ops.
#[doc(hidden)]
pub trait NeighbourAttentionKernels: Backend {
    /// `(∂qkv, ∂δ)` of [`NeighbourAttentionOps::attention_relation`] given its output's
    /// gradient.
    fn attention_relation_backward(
        qkv: FloatTensor<Self>,
        neighbours: IntTensor<Self>,
        delta: FloatTensor<Self>,
        scale: FloatTensor<Self>,
        shift: FloatTensor<Self>,
        grad: FloatTensor<Self>,
    ) -> (FloatTensor<Self>, FloatTensor<Self>);

    /// `(∂qkv, ∂δ, ∂logits)` of [`NeighbourAttentionOps::attention_aggregate_gathered`].
    fn attention_aggregate_gathered_backward(
        qkv: FloatTensor<Self>,
        neighbours: IntTensor<Self>,
        delta: FloatTensor<Self>,
        logits: FloatTensor<Self>,
        grad: FloatTensor<Self>,
    ) -> (FloatTensor<Self>, FloatTensor<Self>, FloatTensor<Self>);
}

/// The relation node's state: every input.
#[derive(Debug, Clone)]
pub struct RelationInputs<B: Backend> {
    qkv: FloatTensor<B>,
    neighbours: IntTensor<B>,
    delta: FloatTensor<B>,
    scale: FloatTensor<B>,
    shift: FloatTensor<B>,
}

/// The aggregation node's state: every input.
#[derive(Debug, Clone)]
pub struct GatheredInputs<B: Backend> {
    qkv: FloatTensor<B>,
    neighbours: IntTensor<B>,
    delta: FloatTensor<B>,
    logits: FloatTensor<B>,
}

#[derive(Debug)]
struct RelationBackward;

impl<B: NeighbourAttentionKernels> Backward<B, 2> for RelationBackward {
    type State = RelationInputs<B>;

    fn backward(
        self,
        ops: Ops<Self::State, 2>,
        grads: &mut Gradients,
        _checkpointer: &mut Checkpointer,
    ) {
        gradient_per_input::<B, _, 2>(ops, grads, |s, grad| {
            let (qkv, delta) = B::attention_relation_backward(
                s.qkv,
                s.neighbours,
                s.delta,
                s.scale,
                s.shift,
                grad,
            );
            [qkv, delta]
        });
    }
}

#[derive(Debug)]
struct GatheredBackward;

impl<B: NeighbourAttentionKernels> Backward<B, 3> for GatheredBackward {
    type State = GatheredInputs<B>;

    fn backward(
        self,
        ops: Ops<Self::State, 3>,
        grads: &mut Gradients,
        _checkpointer: &mut Checkpointer,
    ) {
        gradient_per_input::<B, _, 3>(ops, grads, |s, grad| {
            let (qkv, delta, logits) = B::attention_aggregate_gathered_backward(
                s.qkv,
                s.neighbours,
                s.delta,
                s.logits,
                grad,
            );
            [qkv, delta, logits]
        });
    }
}

impl<B: NeighbourAttentionOps + NeighbourAttentionKernels, C: CheckpointStrategy>
    NeighbourAttentionOps for Autodiff<B, C>
{
    fn attention_relation(
        qkv: FloatTensor<Self>,
        neighbours: IntTensor<Self>,
        delta: FloatTensor<Self>,
        scale: FloatTensor<Self>,
        shift: FloatTensor<Self>,
    ) -> FloatTensor<Self> {
        let (qkv, qkv_node) = qkv.into_parts();
        let (delta, delta_node) = delta.into_parts();
        // Constants of the frozen BatchNorm (module docs): their nodes are dropped.
        let (scale, _) = scale.into_parts();
        let (shift, _) = shift.into_parts();
        record::<B, C, _, _, 2>(
            RelationBackward,
            [qkv_node, delta_node],
            RelationInputs {
                qkv,
                neighbours,
                delta,
                scale,
                shift,
            },
            |s| B::attention_relation(s.qkv, s.neighbours, s.delta, s.scale, s.shift),
        )
    }

    fn attention_aggregate_gathered(
        qkv: FloatTensor<Self>,
        neighbours: IntTensor<Self>,
        delta: FloatTensor<Self>,
        logits: FloatTensor<Self>,
    ) -> FloatTensor<Self> {
        let (qkv, qkv_node) = qkv.into_parts();
        let (delta, delta_node) = delta.into_parts();
        let (logits, logits_node) = logits.into_parts();
        record::<B, C, _, _, 3>(
            GatheredBackward,
            [qkv_node, delta_node, logits_node],
            GatheredInputs {
                qkv,
                neighbours,
                delta,
                logits,
            },
            |s| B::attention_aggregate_gathered(s.qkv, s.neighbours, s.delta, s.logits),
        )
    }
}

impl<B: FusionBackend + NeighbourAttentionKernels> NeighbourAttentionKernels for Fusion<B> {
    fn attention_relation_backward(
        qkv: FloatTensor<Self>,
        neighbours: IntTensor<Self>,
        delta: FloatTensor<Self>,
        scale: FloatTensor<Self>,
        shift: FloatTensor<Self>,
        grad: FloatTensor<Self>,
    ) -> (FloatTensor<Self>, FloatTensor<Self>) {
        let specs = vec![
            float_like::<B>(&qkv, qkv.shape()),
            float_like::<B>(&delta, delta.shape()),
        ];
        let inputs = vec![
            Input::Float(qkv),
            Input::Int(neighbours),
            Input::Float(delta),
            Input::Float(scale),
            Input::Float(shift),
            Input::Float(grad),
        ];
        let [qkv, delta] = array(deferred::<B, _>(
            "attention_relation_backward",
            inputs,
            specs,
            |v| {
                let [qkv, neighbours, delta, scale, shift, grad] = array(v);
                let (qkv, delta) = B::attention_relation_backward(
                    qkv.float(),
                    neighbours.int(),
                    delta.float(),
                    scale.float(),
                    shift.float(),
                    grad.float(),
                );
                vec![Value::Float(qkv), Value::Float(delta)]
            },
        ));
        (qkv, delta)
    }

    fn attention_aggregate_gathered_backward(
        qkv: FloatTensor<Self>,
        neighbours: IntTensor<Self>,
        delta: FloatTensor<Self>,
        logits: FloatTensor<Self>,
        grad: FloatTensor<Self>,
    ) -> (FloatTensor<Self>, FloatTensor<Self>, FloatTensor<Self>) {
        let specs = vec![
            float_like::<B>(&qkv, qkv.shape()),
            float_like::<B>(&delta, delta.shape()),
            float_like::<B>(&logits, logits.shape()),
        ];
        let inputs = vec![
            Input::Float(qkv),
            Input::Int(neighbours),
            Input::Float(delta),
            Input::Float(logits),
            Input::Float(grad),
        ];
        let [qkv, delta, logits] = array(deferred::<B, _>(
            "attention_aggregate_gathered_backward",
            inputs,
            specs,
            |v| {
                let [qkv, neighbours, delta, logits, grad] = array(v);
                let (qkv, delta, logits) = B::attention_aggregate_gathered_backward(
                    qkv.float(),
                    neighbours.int(),
                    delta.float(),
                    logits.float(),
                    grad.float(),
                );
                vec![Value::Float(qkv), Value::Float(delta), Value::Float(logits)]
            },
        ));
        (qkv, delta, logits)
    }
}
