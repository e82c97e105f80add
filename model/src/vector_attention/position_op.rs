//! The Point Transformer layer's positional encoding ([`super::position_encoding`]) as a Burn
//! backend extension for CubeCL devices (design.md §7.5).
//!
//! Listed for `Cube`, `Fusion` and `Autodiff` only: the CPU backends keep the two Linear layers,
//! and the public function never routes them here. The autodiff node keeps the inputs (handles)
//! and its backward recomputes the hidden layer; every input takes a gradient.

use burn::backend::autodiff::checkpoint::base::Checkpointer;
use burn::backend::autodiff::checkpoint::strategy::CheckpointStrategy;
use burn::backend::autodiff::grads::Gradients;
use burn::backend::autodiff::ops::{Backward, Ops};
use burn::backend::fusion::{Fusion, FusionBackend};
use burn::backend::tensor::FloatTensor;
use burn::backend::{Autodiff, Backend, TensorMetadata, backend_extension};
use lifegom_render::cube::deferred::{Input, Value, array, deferred, float_like};
use lifegom_render::op_backward::{gradient_per_input, record};

/// `relu(rel·W₀ + b₀)·W₃ + b₃` over the last axis of `rel` (`[.., 3]`), with `W₀` `[3, 3]`,
/// `b₀` `[3]`, `W₃` `[3, c]`, `b₃` `[c]`; the output is `rel`'s shape with `c` last, in `rel`'s
/// float dtype. Callers check shapes.
#[backend_extension(Cube, Fusion, Autodiff)]
pub trait PositionEncodingOps: Backend {
    /// The encoding.
    #[fusion(dtype = rel, shape = {
        let mut shape = rel.clone();
        let last = shape.num_dims() - 1;
        shape[last] = w3[1];
        shape
    })]
    fn position_encoding(
        rel: FloatTensor<Self>,
        w0: FloatTensor<Self>,
        b0: FloatTensor<Self>,
        w3: FloatTensor<Self>,
        b3: FloatTensor<Self>,
    ) -> FloatTensor<Self>;
}

/// What a backend implements so that `Autodiff<B>` can differentiate the op.
#[doc(hidden)]
pub trait PositionEncodingKernels: Backend {
    /// `[∂rel, ∂W₀, ∂b₀, ∂W₃, ∂b₃]` given the output's gradient (`b₃` does not enter them).
    fn position_encoding_backward(
        rel: FloatTensor<Self>,
        w0: FloatTensor<Self>,
        b0: FloatTensor<Self>,
        w3: FloatTensor<Self>,
        grad: FloatTensor<Self>,
    ) -> [FloatTensor<Self>; 5];
}

/// The autodiff node's state: the inputs the backward reads.
#[derive(Debug, Clone)]
pub struct PositionInputs<B: Backend> {
    rel: FloatTensor<B>,
    w0: FloatTensor<B>,
    b0: FloatTensor<B>,
    w3: FloatTensor<B>,
    b3: FloatTensor<B>,
}

#[derive(Debug)]
struct PositionBackward;

impl<B: PositionEncodingKernels> Backward<B, 5> for PositionBackward {
    type State = PositionInputs<B>;

    fn backward(
        self,
        ops: Ops<Self::State, 5>,
        grads: &mut Gradients,
        _checkpointer: &mut Checkpointer,
    ) {
        gradient_per_input::<B, _, 5>(ops, grads, |s, grad| {
            B::position_encoding_backward(s.rel, s.w0, s.b0, s.w3, grad)
        });
    }
}

impl<B: PositionEncodingOps + PositionEncodingKernels, C: CheckpointStrategy> PositionEncodingOps
    for Autodiff<B, C>
{
    fn position_encoding(
        rel: FloatTensor<Self>,
        w0: FloatTensor<Self>,
        b0: FloatTensor<Self>,
        w3: FloatTensor<Self>,
        b3: FloatTensor<Self>,
    ) -> FloatTensor<Self> {
        let (rel, rel_node) = rel.into_parts();
        let (w0, w0_node) = w0.into_parts();
        let (b0, b0_node) = b0.into_parts();
        let (w3, w3_node) = w3.into_parts();
        let (b3, b3_node) = b3.into_parts();
        record::<B, C, _, _, 5>(
            PositionBackward,
            [rel_node, w0_node, b0_node, w3_node, b3_node],
            PositionInputs {
                rel,
                w0,
                b0,
                w3,
                b3,
            },
            |s| B::position_encoding(s.rel, s.w0, s.b0, s.w3, s.b3),
        )
    }
}

impl<B: FusionBackend + PositionEncodingKernels> PositionEncodingKernels for Fusion<B> {
    fn position_encoding_backward(
        rel: FloatTensor<Self>,
        w0: FloatTensor<Self>,
        b0: FloatTensor<Self>,
        w3: FloatTensor<Self>,
        grad: FloatTensor<Self>,
    ) -> [FloatTensor<Self>; 5] {
        let c = w3.shape()[1];
        let specs = vec![
            float_like::<B>(&rel, rel.shape()),
            float_like::<B>(&w0, w0.shape()),
            float_like::<B>(&b0, b0.shape()),
            float_like::<B>(&w3, w3.shape()),
            float_like::<B>(&w3, burn::tensor::Shape::new([c])),
        ];
        let inputs = vec![
            Input::Float(rel),
            Input::Float(w0),
            Input::Float(b0),
            Input::Float(w3),
            Input::Float(grad),
        ];
        array(deferred::<B, _>(
            "position_encoding_backward",
            inputs,
            specs,
            |v| {
                let [rel, w0, b0, w3, grad] = array(v);
                B::position_encoding_backward(
                    rel.float(),
                    w0.float(),
                    b0.float(),
                    w3.float(),
                    grad.float(),
                )
                .map(Value::Float)
                .into()
            },
        ))
    }
}
