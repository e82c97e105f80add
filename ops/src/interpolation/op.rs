//! [`super::interpolate`] as a Burn backend extension for CubeCL devices.
//!
//! Listed for `Cube`, `Fusion` and `Autodiff` only: the CPU backends keep the gather, product
//! and sum, and the public function never routes them here. The index table and the weights take
//! no gradient (the reference's `pointops` interpolation gives them none); the autodiff node
//! keeps the table's inverse (`super::NeighbourTable`), the weights and the number of coarse
//! points.

use burn::backend::autodiff::checkpoint::base::Checkpointer;
use burn::backend::autodiff::checkpoint::strategy::CheckpointStrategy;
use burn::backend::autodiff::grads::Gradients;
use burn::backend::autodiff::ops::{Backward, Ops};
use burn::backend::fusion::{Fusion, FusionBackend};
use burn::backend::tensor::{FloatTensor, IntTensor};
use burn::backend::{Autodiff, Backend, TensorMetadata, backend_extension};
use lifegom_render::cube::deferred::{Input, Value, array, deferred, float_like};
use lifegom_render::op_backward::{gradient_per_input, record};

/// `Σ_j weights[i, j]·x[neighbours[i·K + j]]` as `[m, c]`, for `x` `[n, c]`, `neighbours`
/// `[m·K]` (int), its inverse `readers` (`[offsets (n + 1) | slots]`, `super::NeighbourTable`)
/// and `weights` `[m, K]`; with [`Base::Added`], `base` `[m, c]` plus that. Callers check shapes
/// and ranges.
#[backend_extension(Cube, Fusion, Autodiff)]
pub trait InterpolationOps: Backend {
    /// The interpolated rows, onto `base` when `onto` says so (else `base` is not read).
    #[fusion(dtype = x, shape = burn::tensor::Shape::new([weights[0], x[1]]))]
    fn point_interpolation(
        x: FloatTensor<Self>,
        neighbours: IntTensor<Self>,
        readers: IntTensor<Self>,
        weights: FloatTensor<Self>,
        base: FloatTensor<Self>,
        onto: Base,
    ) -> FloatTensor<Self>;
}

/// Whether the interpolated rows are added onto a base in the op's launch (the transition-up's
/// `fine + interpolated`: one launch fewer per level and pass).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Base {
    /// The interpolated rows alone.
    None,
    /// `base + interpolated`; the base's gradient is the output's.
    Added,
}

/// What a backend implements so that `Autodiff<B>` can differentiate the op.
#[doc(hidden)]
pub trait InterpolationKernels: Backend {
    /// `∂x` `[points, c]`: for each coarse point, the weighted gradients of the rows whose
    /// slots `readers` lists for it, summed in slot order.
    fn point_interpolation_backward(
        readers: IntTensor<Self>,
        weights: FloatTensor<Self>,
        grad: FloatTensor<Self>,
        points: usize,
    ) -> FloatTensor<Self>;
}

/// The node's state: the table and its inverse, the weights and the number of coarse points.
#[derive(Debug, Clone)]
pub struct InterpolationTable<B: Backend> {
    neighbours: IntTensor<B>,
    readers: IntTensor<B>,
    weights: FloatTensor<B>,
    points: usize,
}

#[derive(Debug)]
struct InterpolationBackward;

impl<B: InterpolationKernels> Backward<B, 2> for InterpolationBackward {
    type State = InterpolationTable<B>;

    fn backward(
        self,
        ops: Ops<Self::State, 2>,
        grads: &mut Gradients,
        _checkpointer: &mut Checkpointer,
    ) {
        // The base's gradient is the output's itself (no launch); without a base its node is
        // untracked and takes nothing.
        gradient_per_input::<B, _, 2>(ops, grads, |s, grad| {
            [
                B::point_interpolation_backward(s.readers, s.weights, grad.clone(), s.points),
                grad,
            ]
        });
    }
}

impl<B: InterpolationOps + InterpolationKernels, C: CheckpointStrategy> InterpolationOps
    for Autodiff<B, C>
{
    fn point_interpolation(
        x: FloatTensor<Self>,
        neighbours: IntTensor<Self>,
        readers: IntTensor<Self>,
        weights: FloatTensor<Self>,
        base: FloatTensor<Self>,
        onto: Base,
    ) -> FloatTensor<Self> {
        let points = x.shape()[0];
        let (x, x_node) = x.into_parts();
        // Constant weights (module docs): their node is dropped.
        let (weights, _) = weights.into_parts();
        // Callers pass a detached stand-in when nothing is added: its node is untracked.
        let (base, base_node) = base.into_parts();
        let table = InterpolationTable {
            neighbours,
            readers,
            weights,
            points,
        };
        // The forward needs `x`, the backward only the table: `x` goes in through the closure.
        let forward = {
            let x = x.clone();
            move |s: InterpolationTable<B>| {
                B::point_interpolation(x, s.neighbours, s.readers, s.weights, base, onto)
            }
        };
        record::<B, C, _, _, 2>(InterpolationBackward, [x_node, base_node], table, forward)
    }
}

impl<B: FusionBackend + InterpolationKernels> InterpolationKernels for Fusion<B> {
    fn point_interpolation_backward(
        readers: IntTensor<Self>,
        weights: FloatTensor<Self>,
        grad: FloatTensor<Self>,
        points: usize,
    ) -> FloatTensor<Self> {
        let c = grad.shape()[1];
        let specs = vec![float_like::<B>(
            &grad,
            burn::tensor::Shape::new([points, c]),
        )];
        let inputs = vec![
            Input::Int(readers),
            Input::Float(weights),
            Input::Float(grad),
        ];
        let [x] = array(deferred::<B, _>(
            "point_interpolation_backward",
            inputs,
            specs,
            move |v| {
                let [readers, weights, grad] = array(v);
                vec![Value::Float(B::point_interpolation_backward(
                    readers.int(),
                    weights.float(),
                    grad.float(),
                    points,
                ))]
            },
        ));
        x
    }
}
