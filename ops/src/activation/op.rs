//! ReLU as a Burn backend extension for CubeCL devices. Listed for `Cube` and `Autodiff` only:
//! [`super::relu`] routes the CPU backends to Burn's own. The autodiff node keeps the output, as
//! Burn's ReLU node does.

use burn::backend::autodiff::checkpoint::base::Checkpointer;
use burn::backend::autodiff::checkpoint::strategy::CheckpointStrategy;
use burn::backend::autodiff::grads::Gradients;
use burn::backend::autodiff::ops::{Backward, Ops, OpsKind};
use burn::backend::fusion::{Fusion, FusionBackend};
use burn::backend::tensor::FloatTensor;
use burn::backend::{Autodiff, Backend, TensorMetadata, backend_extension};
use lifegom_render::cube::deferred::{Input, Value, array, deferred, float_like};
use lifegom_render::op_backward::gradient_per_input;

/// `max(x, 0)` elementwise with Burn's semantics (see [`super`]).
#[backend_extension(Cube, Fusion, Autodiff)]
pub trait ReluOps: Backend {
    /// The activation.
    #[fusion(dtype = x, shape = x)]
    fn fused_relu(x: FloatTensor<Self>) -> FloatTensor<Self>;
}

/// What a backend implements so that `Autodiff<B>` can differentiate the op.
#[doc(hidden)]
pub trait ReluKernels: Backend {
    /// `grad` where `output > 0` (or NaN), else 0.
    fn fused_relu_backward(output: FloatTensor<Self>, grad: FloatTensor<Self>)
    -> FloatTensor<Self>;
}

#[derive(Debug)]
struct ReluBackward;

impl<B: ReluKernels> Backward<B, 1> for ReluBackward {
    type State = FloatTensor<B>;

    fn backward(
        self,
        ops: Ops<Self::State, 1>,
        grads: &mut Gradients,
        _checkpointer: &mut Checkpointer,
    ) {
        gradient_per_input::<B, _, 1>(ops, grads, |output, grad| {
            [B::fused_relu_backward(output, grad)]
        });
    }
}

impl<B: ReluOps + ReluKernels, C: CheckpointStrategy> ReluOps for Autodiff<B, C> {
    fn fused_relu(x: FloatTensor<Self>) -> FloatTensor<Self> {
        let (x, node) = x.into_parts();
        match ReluBackward.prepare::<C>([node]).compute_bound().stateful() {
            OpsKind::Tracked(prep) => {
                let output = B::fused_relu(x);
                prep.finish(output.clone(), output)
            }
            OpsKind::UnTracked(prep) => prep.finish(B::fused_relu(x)),
        }
    }
}

impl<B: FusionBackend + ReluKernels> ReluKernels for Fusion<B> {
    fn fused_relu_backward(
        output: FloatTensor<Self>,
        grad: FloatTensor<Self>,
    ) -> FloatTensor<Self> {
        let spec = float_like::<B>(&grad, grad.shape());
        let inputs = vec![Input::Float(output), Input::Float(grad)];
        let [dx] = array(deferred::<B, _>(
            "fused_relu_backward",
            inputs,
            vec![spec],
            |v| {
                let [output, grad] = array(v);
                vec![Value::Float(B::fused_relu_backward(
                    output.float(),
                    grad.float(),
                ))]
            },
        ));
        dx
    }
}
