//! [`super::max_over_neighbours`] as a Burn backend extension for CubeCL devices.
//!
//! Listed for `Cube`, `Fusion` and `Autodiff` only: the CPU backends keep Burn's `max_dim`, and
//! the public function never routes them here. The autodiff node keeps the neighbour each
//! maximum came from, which the forward writes anyway.

use burn::backend::autodiff::checkpoint::base::Checkpointer;
use burn::backend::autodiff::checkpoint::strategy::CheckpointStrategy;
use burn::backend::autodiff::grads::Gradients;
use burn::backend::autodiff::ops::{Backward, Ops};
use burn::backend::fusion::custom::TensorSpec;
use burn::backend::fusion::{Fusion, FusionBackend};
use burn::backend::tensor::{FloatTensor, IntTensor};
use burn::backend::{Autodiff, Backend, TensorMetadata, backend_extension};
use burn::tensor::{DType, Shape};
use lifegom_render::cube::deferred::{Input, Output, Value, array, deferred, float_like};
use lifegom_render::op_backward::{gradient_per_input, record};

/// `max_j h[i, j, ch]` `[m, c]` for `h` `[m, k, c]`. Callers check shapes.
#[backend_extension(Cube, Fusion, Autodiff)]
pub trait NeighbourMaxOps: Backend {
    /// The maxima.
    #[fusion(dtype = h, shape = Shape::new([h[0], h[2]]))]
    fn neighbour_max(h: FloatTensor<Self>) -> FloatTensor<Self>;
}

/// What a backend implements so that `Autodiff<B>` can differentiate the op.
#[doc(hidden)]
pub trait NeighbourMaxKernels: Backend {
    /// The maxima `[m, c]` and the neighbour each came from, `j` in `0..k` (int `[m, c]`; the
    /// first on ties).
    fn neighbour_max_indexed(h: FloatTensor<Self>) -> (FloatTensor<Self>, IntTensor<Self>);

    /// `∂h` `[m, k, c]`: `grad[i, ch]` where `j` is `argmax[i, ch]`, zero elsewhere.
    fn neighbour_max_backward(
        argmax: IntTensor<Self>,
        grad: FloatTensor<Self>,
        k: usize,
    ) -> FloatTensor<Self>;
}

/// The node's state: where each maximum came from, and the neighbourhood size.
#[derive(Debug, Clone)]
pub struct MaxSources<B: Backend> {
    argmax: IntTensor<B>,
    k: usize,
}

#[derive(Debug)]
struct NeighbourMaxBackward;

impl<B: NeighbourMaxKernels> Backward<B, 1> for NeighbourMaxBackward {
    type State = MaxSources<B>;

    fn backward(
        self,
        ops: Ops<Self::State, 1>,
        grads: &mut Gradients,
        _checkpointer: &mut Checkpointer,
    ) {
        gradient_per_input::<B, _, 1>(ops, grads, |s, grad| {
            [B::neighbour_max_backward(s.argmax, grad, s.k)]
        });
    }
}

impl<B: NeighbourMaxOps + NeighbourMaxKernels, C: CheckpointStrategy> NeighbourMaxOps
    for Autodiff<B, C>
{
    fn neighbour_max(h: FloatTensor<Self>) -> FloatTensor<Self> {
        let k = h.shape()[1];
        let (h, h_node) = h.into_parts();
        let (max, argmax) = B::neighbour_max_indexed(h);
        record::<B, C, _, _, 1>(
            NeighbourMaxBackward,
            [h_node],
            MaxSources { argmax, k },
            move |_| max,
        )
    }
}

impl<B: FusionBackend + NeighbourMaxKernels> NeighbourMaxKernels for Fusion<B> {
    fn neighbour_max_indexed(h: FloatTensor<Self>) -> (FloatTensor<Self>, IntTensor<Self>) {
        let shape = h.shape();
        let out = Shape::new([shape[0], shape[2]]);
        let specs = vec![
            float_like::<B>(&h, out.clone()),
            Output::Int(TensorSpec::new(out, DType::I32)),
        ];
        let [max, argmax] = array(deferred::<B, _>(
            "neighbour_max_indexed",
            vec![Input::Float(h)],
            specs,
            |v| {
                let [h] = array(v);
                let (max, argmax) = B::neighbour_max_indexed(h.float());
                vec![Value::Float(max), Value::Int(argmax)]
            },
        ));
        (max, argmax)
    }

    fn neighbour_max_backward(
        argmax: IntTensor<Self>,
        grad: FloatTensor<Self>,
        k: usize,
    ) -> FloatTensor<Self> {
        let [m, c] = grad.shape().dims::<2>();
        let specs = vec![float_like::<B>(&grad, Shape::new([m, k, c]))];
        let [h] = array(deferred::<B, _>(
            "neighbour_max_backward",
            vec![Input::Int(argmax), Input::Float(grad)],
            specs,
            move |v| {
                let [argmax, grad] = array(v);
                vec![Value::Float(B::neighbour_max_backward(
                    argmax.int(),
                    grad.float(),
                    k,
                ))]
            },
        ));
        h
    }
}
