//! The vector-attention aggregation as a Burn backend extension for CubeCL devices (design.md
//! §7.5).
//!
//! [`VectorAttentionOps`] is listed for `Cube` and `Autodiff` only: the CPU backends keep the
//! tensor-op composition, and [`super::aggregate`] never routes them here. The autodiff node
//! keeps both inputs (handles, no copies); the backward recomputes the softmax.

use burn::backend::autodiff::checkpoint::base::Checkpointer;
use burn::backend::autodiff::checkpoint::strategy::CheckpointStrategy;
use burn::backend::autodiff::grads::Gradients;
use burn::backend::autodiff::ops::{Backward, Ops};
use burn::backend::fusion::{Fusion, FusionBackend};
use burn::backend::tensor::FloatTensor;
use burn::backend::{Autodiff, Backend, TensorMetadata, backend_extension};
use lifegom_render::cube::deferred::{Input, Value, array, deferred, float_like};
use lifegom_render::op_backward::{gradient_per_input, record};

/// `Σ_κ softmax_κ(logits)·values` (see [`super`]).
///
/// `values` `[n, k, S, C/S]`, `logits` `[n, k, C/S]` → `[n, S, C/S]` in `values`' float dtype.
/// Gradients flow to both inputs. Callers check shapes ([`super::aggregate`]).
#[backend_extension(Cube, Fusion, Autodiff)]
pub trait VectorAttentionOps: Backend {
    /// The softmax-weighted sum over the neighbours.
    #[fusion(dtype = values, shape = {
        let [n, _, s, c] = values.dims::<4>();
        burn::tensor::Shape::new([n, s, c])
    })]
    fn attention_aggregate(
        values: FloatTensor<Self>,
        logits: FloatTensor<Self>,
    ) -> FloatTensor<Self>;
}

/// What a backend implements so that `Autodiff<B>` can differentiate the op.
#[doc(hidden)]
pub trait VectorAttentionKernels: Backend {
    /// `(∂values, ∂logits)` given the output's gradient `[n, S, C/S]`, each in its input's
    /// dtype.
    fn attention_aggregate_backward(
        values: FloatTensor<Self>,
        logits: FloatTensor<Self>,
        grad: FloatTensor<Self>,
    ) -> (FloatTensor<Self>, FloatTensor<Self>);
}

/// The autodiff node's state: both inputs.
#[derive(Debug, Clone)]
pub struct AggregateInputs<B: Backend> {
    values: FloatTensor<B>,
    logits: FloatTensor<B>,
}

#[derive(Debug)]
struct AggregateBackward;

impl<B: VectorAttentionKernels> Backward<B, 2> for AggregateBackward {
    type State = AggregateInputs<B>;

    fn backward(
        self,
        ops: Ops<Self::State, 2>,
        grads: &mut Gradients,
        _checkpointer: &mut Checkpointer,
    ) {
        gradient_per_input::<B, _, 2>(ops, grads, |state, grad| {
            let (values, logits) =
                B::attention_aggregate_backward(state.values, state.logits, grad);
            [values, logits]
        });
    }
}

impl<B: VectorAttentionOps + VectorAttentionKernels, C: CheckpointStrategy> VectorAttentionOps
    for Autodiff<B, C>
{
    fn attention_aggregate(
        values: FloatTensor<Self>,
        logits: FloatTensor<Self>,
    ) -> FloatTensor<Self> {
        let (values, values_node) = values.into_parts();
        let (logits, logits_node) = logits.into_parts();
        record::<B, C, _, _, 2>(
            AggregateBackward,
            [values_node, logits_node],
            AggregateInputs { values, logits },
            |inputs| B::attention_aggregate(inputs.values, inputs.logits),
        )
    }
}

impl<B: FusionBackend + VectorAttentionKernels> VectorAttentionKernels for Fusion<B> {
    fn attention_aggregate_backward(
        values: FloatTensor<Self>,
        logits: FloatTensor<Self>,
        grad: FloatTensor<Self>,
    ) -> (FloatTensor<Self>, FloatTensor<Self>) {
        let specs = vec![
            float_like::<B>(&values, values.shape()),
            float_like::<B>(&logits, logits.shape()),
        ];
        let inputs = vec![
            Input::Float(values),
            Input::Float(logits),
            Input::Float(grad),
        ];
        let [d_values, d_logits] = array(deferred::<B, _>(
            "attention_aggregate_backward",
            inputs,
            specs,
            |v| {
                let [values, logits, grad] = array(v);
                let (d_values, d_logits) =
                    B::attention_aggregate_backward(values.float(), logits.float(), grad.float());
                vec![Value::Float(d_values), Value::Float(d_logits)]
            },
        ));
        (d_values, d_logits)
    }
}
