//! The Point Transformer layer's neighbourhood ops ([`super::relation`],
//! [`super::aggregate_gathered`]) as a Burn backend extension for CubeCL devices (design.md
//! §7.5).
//!
//! Listed for `Cube`, `Fusion` and `Autodiff` only: the CPU backends keep the tensor-op
//! composition, and the public functions never route them here. The autodiff nodes keep their
//! inputs (handles, no copies) and recompute what the backward needs. `scale` and `shift` of the
//! relation are the frozen BatchNorm's and take no gradient (design.md §7.5); the neighbour
//! table is an int tensor and takes none either.
//!
//! **Paired ops.** In a layer both ops read the same `qkv` and `δ`, so Burn adds their
//! gradients: two more launches per layer and pass. A relation and the aggregation whose logits
//! come from it can share an [`AttentionPair`]: the aggregation's node, which Burn runs first
//! (it is deeper), files its `∂qkv` and `∂δ` with the pair instead of registering them, and the
//! relation's backward kernels add them to their own as they write them. The aggregation then
//! leaves its values' scatter onto the neighbours' rows of `∂qkv` to the relation, whose keys'
//! scatter walks the same neighbours: one scatter launch for both ([`ValueScatter`]). A pair must join
//! exactly one relation to one aggregation whose logits depend on the relation's output;
//! otherwise the filed gradients are never taken (the public functions pair nothing; the Point
//! Transformer layer pairs its own two ops).

use burn::backend::autodiff::checkpoint::base::Checkpointer;
use burn::backend::autodiff::checkpoint::strategy::CheckpointStrategy;
use burn::backend::autodiff::grads::Gradients;
use burn::backend::autodiff::ops::{Backward, Ops, OpsKind};
use burn::backend::fusion::{Fusion, FusionBackend};
use burn::backend::tensor::{FloatTensor, IntTensor};
use burn::backend::{Autodiff, Backend, TensorMetadata, backend_extension};
use lifegom_render::cube::deferred::{Input, Value, array, deferred, float_like};
use lifegom_render::op_backward::{gradient_per_input, record};

use crate::handoff::Handoff;

/// A relation and an aggregation whose gradients for `qkv` and `δ` are added inside the
/// relation's backward (module docs), or no pairing: a [`Handoff`] of `(∂qkv, ∂δ)`.
#[derive(Debug, Clone, Default)]
pub struct AttentionPair(Handoff);

impl AttentionPair {
    /// A pair for one relation and one aggregation.
    pub fn new() -> Self {
        Self(Handoff::new())
    }

    /// Whether the pair joins two ops.
    fn is_paired(&self) -> bool {
        self.0.is_joined()
    }

    /// No pairing: each op registers its own gradients.
    pub fn unpaired() -> Self {
        Self(Handoff::none())
    }

    /// Files the aggregation's `(∂qkv, ∂δ)`; `false` when unpaired.
    fn file<B: Backend>(&self, grads: (FloatTensor<B>, FloatTensor<B>)) -> bool {
        self.0.file(grads)
    }

    /// The aggregation's filed `(∂qkv, ∂δ)`, if any.
    fn take<B: Backend>(&self) -> Option<(FloatTensor<B>, FloatTensor<B>)> {
        self.0.take()
    }
}

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
        pair: AttentionPair,
    ) -> FloatTensor<Self>;

    /// `h = Σ_κ softmax_κ(logits)·(v[nbr] + δ)`, `[n, c]`, with `logits` `[n, k, C/S]`; with
    /// [`AggregateEnding::NormRelu`], `relu(h·out_scale + out_shift)` (`[c]` each, a frozen
    /// BatchNorm's, no gradient), else `h` (the two are not read).
    #[allow(clippy::too_many_arguments)]
    #[fusion(dtype = delta, shape = burn::tensor::Shape::new([delta[0], delta[2]]))]
    fn attention_aggregate_gathered(
        qkv: FloatTensor<Self>,
        neighbours: IntTensor<Self>,
        delta: FloatTensor<Self>,
        logits: FloatTensor<Self>,
        out_scale: FloatTensor<Self>,
        out_shift: FloatTensor<Self>,
        ending: AggregateEnding,
        pair: AttentionPair,
    ) -> FloatTensor<Self>;
}

/// What the aggregation's launch applies to its result (the Point Transformer block's BatchNorm
/// and ReLU after the layer: one launch fewer each way).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum AggregateEnding {
    /// The aggregation itself.
    Plain,
    /// `relu(h·scale + shift)`.
    NormRelu,
}

/// Where the aggregation's values' gradient `∂v[nbr] += ∂(v + δ)` is scattered onto `∂qkv`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ValueScatter {
    /// By the aggregation's backward.
    Here,
    /// By the paired relation's backward, with its keys' (module docs): the aggregation's
    /// `∂qkv` lacks it.
    ToRelation,
}

/// What a backend implements so that `Autodiff<B>` can differentiate the ops.
#[doc(hidden)]
pub trait NeighbourAttentionKernels: Backend {
    /// `(∂qkv, ∂δ)` of [`NeighbourAttentionOps::attention_relation`] given its output's
    /// gradient, plus `addends` (the paired aggregation's `(∂qkv, ∂δ)`, its values' scatter
    /// left to this one: [`ValueScatter::ToRelation`]) when given.
    #[allow(clippy::too_many_arguments)]
    fn attention_relation_backward(
        qkv: FloatTensor<Self>,
        neighbours: IntTensor<Self>,
        delta: FloatTensor<Self>,
        scale: FloatTensor<Self>,
        shift: FloatTensor<Self>,
        grad: FloatTensor<Self>,
        addends: Option<(FloatTensor<Self>, FloatTensor<Self>)>,
    ) -> (FloatTensor<Self>, FloatTensor<Self>);

    /// `(∂qkv, ∂δ, ∂logits)` of [`NeighbourAttentionOps::attention_aggregate_gathered`], the
    /// values' part of `∂qkv` scattered as `scatter` says; `norm` is the op's output and
    /// `out_scale` under [`AggregateEnding::NormRelu`] (`grad` is then the gradient after the
    /// ReLU).
    fn attention_aggregate_gathered_backward(
        qkv: FloatTensor<Self>,
        neighbours: IntTensor<Self>,
        delta: FloatTensor<Self>,
        logits: FloatTensor<Self>,
        grad: FloatTensor<Self>,
        scatter: ValueScatter,
        norm: Option<(FloatTensor<Self>, FloatTensor<Self>)>,
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
    pair: AttentionPair,
}

/// The aggregation node's state: every input, and under [`AggregateEnding::NormRelu`] the
/// output (the ReLU's mask) and the norm's scale.
#[derive(Debug, Clone)]
pub struct GatheredInputs<B: Backend> {
    qkv: FloatTensor<B>,
    neighbours: IntTensor<B>,
    delta: FloatTensor<B>,
    logits: FloatTensor<B>,
    out_scale: FloatTensor<B>,
    out_shift: FloatTensor<B>,
    ending: AggregateEnding,
    pair: AttentionPair,
    norm: Option<(FloatTensor<B>, FloatTensor<B>)>,
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
            let addends = s.pair.take::<B>();
            let (qkv, delta) = B::attention_relation_backward(
                s.qkv,
                s.neighbours,
                s.delta,
                s.scale,
                s.shift,
                grad,
                addends,
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
        let grad = grads.consume::<B>(&ops.node);
        let [qkv_node, delta_node, logits_node] = ops.parents;
        let s = ops.state;
        let scatter = if s.pair.is_paired() {
            ValueScatter::ToRelation
        } else {
            ValueScatter::Here
        };
        let (qkv, delta, logits) = B::attention_aggregate_gathered_backward(
            s.qkv,
            s.neighbours,
            s.delta,
            s.logits,
            grad,
            scatter,
            s.norm,
        );
        if let Some(node) = logits_node {
            grads.register::<B>(node.id, logits);
        }
        if s.pair.file::<B>((qkv.clone(), delta.clone())) {
            return;
        }
        for (node, grad) in [(qkv_node, qkv), (delta_node, delta)] {
            if let Some(node) = node {
                grads.register::<B>(node.id, grad);
            }
        }
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
        pair: AttentionPair,
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
                pair,
            },
            |s| B::attention_relation(s.qkv, s.neighbours, s.delta, s.scale, s.shift, s.pair),
        )
    }

    fn attention_aggregate_gathered(
        qkv: FloatTensor<Self>,
        neighbours: IntTensor<Self>,
        delta: FloatTensor<Self>,
        logits: FloatTensor<Self>,
        out_scale: FloatTensor<Self>,
        out_shift: FloatTensor<Self>,
        ending: AggregateEnding,
        pair: AttentionPair,
    ) -> FloatTensor<Self> {
        let (qkv, qkv_node) = qkv.into_parts();
        let (delta, delta_node) = delta.into_parts();
        let (logits, logits_node) = logits.into_parts();
        // Constants of the frozen BatchNorm: their nodes are dropped.
        let (out_scale, out_shift) = (out_scale.into_primitive(), out_shift.into_primitive());
        let inputs = GatheredInputs {
            qkv,
            neighbours,
            delta,
            logits,
            out_scale,
            out_shift,
            ending,
            pair,
            norm: None,
        };
        let forward = |s: GatheredInputs<B>| {
            B::attention_aggregate_gathered(
                s.qkv,
                s.neighbours,
                s.delta,
                s.logits,
                s.out_scale,
                s.out_shift,
                s.ending,
                s.pair,
            )
        };
        match GatheredBackward
            .prepare::<C>([qkv_node, delta_node, logits_node])
            .compute_bound()
            .stateful()
        {
            OpsKind::Tracked(prep) => {
                let output = forward(inputs.clone());
                // The ReLU's mask is the output; the norm's scale multiplies the gradient.
                let norm = (ending == AggregateEnding::NormRelu)
                    .then(|| (output.clone(), inputs.out_scale.clone()));
                prep.finish(GatheredInputs { norm, ..inputs }, output)
            }
            OpsKind::UnTracked(prep) => prep.finish(forward(inputs)),
        }
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
        addends: Option<(FloatTensor<Self>, FloatTensor<Self>)>,
    ) -> (FloatTensor<Self>, FloatTensor<Self>) {
        let specs = vec![
            float_like::<B>(&qkv, qkv.shape()),
            float_like::<B>(&delta, delta.shape()),
        ];
        let added = addends.is_some();
        let mut inputs = vec![
            Input::Float(qkv),
            Input::Int(neighbours),
            Input::Float(delta),
            Input::Float(scale),
            Input::Float(shift),
            Input::Float(grad),
        ];
        if let Some((q, d)) = addends {
            inputs.extend([Input::Float(q), Input::Float(d)]);
        }
        let [qkv, delta] = array(deferred::<B, _>(
            "attention_relation_backward",
            inputs,
            specs,
            move |mut v| {
                let addends = if added {
                    let d = v.pop().map(Value::float);
                    let q = v.pop().map(Value::float);
                    q.zip(d)
                } else {
                    None
                };
                let [qkv, neighbours, delta, scale, shift, grad] = array(v);
                let (qkv, delta) = B::attention_relation_backward(
                    qkv.float(),
                    neighbours.int(),
                    delta.float(),
                    scale.float(),
                    shift.float(),
                    grad.float(),
                    addends,
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
        scatter: ValueScatter,
        norm: Option<(FloatTensor<Self>, FloatTensor<Self>)>,
    ) -> (FloatTensor<Self>, FloatTensor<Self>, FloatTensor<Self>) {
        let specs = vec![
            float_like::<B>(&qkv, qkv.shape()),
            float_like::<B>(&delta, delta.shape()),
            float_like::<B>(&logits, logits.shape()),
        ];
        let normed = norm.is_some();
        let mut inputs = vec![
            Input::Float(qkv),
            Input::Int(neighbours),
            Input::Float(delta),
            Input::Float(logits),
            Input::Float(grad),
        ];
        if let Some((output, scale)) = norm {
            inputs.extend([Input::Float(output), Input::Float(scale)]);
        }
        let [qkv, delta, logits] = array(deferred::<B, _>(
            "attention_aggregate_gathered_backward",
            inputs,
            specs,
            move |mut v| {
                let norm = if normed {
                    let scale = v.pop().map(Value::float);
                    let output = v.pop().map(Value::float);
                    output.zip(scale)
                } else {
                    None
                };
                let [qkv, neighbours, delta, logits, grad] = array(v);
                let (qkv, delta, logits) = B::attention_aggregate_gathered_backward(
                    qkv.float(),
                    neighbours.int(),
                    delta.float(),
                    logits.float(),
                    grad.float(),
                    scatter,
                    norm,
                );
                vec![Value::Float(qkv), Value::Float(delta), Value::Float(logits)]
            },
        ));
        (qkv, delta, logits)
    }
}
