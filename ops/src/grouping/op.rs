//! [`super::relative_positions`] as a Burn backend extension for CubeCL devices.
//!
//! Listed for `Cube`, `Fusion` and `Autodiff` only: the CPU backends keep the gathers and the
//! subtraction, and the public function never routes them here. The index tables are int
//! tensors and take no gradient; the autodiff node keeps them and nothing else.

use burn::backend::autodiff::checkpoint::base::Checkpointer;
use burn::backend::autodiff::checkpoint::strategy::CheckpointStrategy;
use burn::backend::autodiff::grads::Gradients;
use burn::backend::autodiff::ops::{Backward, Ops};
use burn::backend::fusion::{Fusion, FusionBackend};
use burn::backend::tensor::{FloatTensor, IntTensor};
use burn::backend::{Autodiff, Backend, TensorMetadata, backend_extension};
use lifegom_render::cube::deferred::{Input, Value, array, deferred, float_like};
use lifegom_render::op_backward::{gradient_per_input, record};

/// `p[neighbours[i·k + κ]] − p[centres[i]]` as `[m, k, 3]`, for `p` `[n, 3]`, `neighbours`
/// `[m·k]` and `centres` `[m]` (int), with the tables' inverses `readers`
/// (`super::GroupTable`) for the backward. Callers check shapes and ranges.
#[backend_extension(Cube, Fusion, Autodiff)]
pub trait GroupingOps: Backend {
    /// The offsets.
    #[fusion(dtype = p, shape = burn::tensor::Shape::new([
        centres[0],
        neighbours[0] / centres[0].max(1),
        3,
    ]))]
    fn relative_positions(
        p: FloatTensor<Self>,
        neighbours: IntTensor<Self>,
        centres: IntTensor<Self>,
        readers: IntTensor<Self>,
    ) -> FloatTensor<Self>;
}

/// What a backend implements so that `Autodiff<B>` can differentiate the op.
#[doc(hidden)]
pub trait GroupingKernels: Backend {
    /// `∂p` `[n, 3]`: each offset's gradient added at its neighbour and subtracted at its
    /// centre, each point's sum gathered over the slots and groups `readers` lists for it, for
    /// groups of `k`.
    fn relative_positions_backward(
        readers: IntTensor<Self>,
        grad: FloatTensor<Self>,
        points: usize,
        k: usize,
    ) -> FloatTensor<Self>;
}

/// The node's state: the index tables, their inverses and the number of points.
#[derive(Debug, Clone)]
pub struct GroupTables<B: Backend> {
    neighbours: IntTensor<B>,
    centres: IntTensor<B>,
    readers: IntTensor<B>,
    points: usize,
}

#[derive(Debug)]
struct GroupingBackward;

impl<B: GroupingKernels> Backward<B, 1> for GroupingBackward {
    type State = GroupTables<B>;

    fn backward(
        self,
        ops: Ops<Self::State, 1>,
        grads: &mut Gradients,
        _checkpointer: &mut Checkpointer,
    ) {
        gradient_per_input::<B, _, 1>(ops, grads, |s, grad| {
            let k = s.neighbours.shape()[0] / s.centres.shape()[0].max(1);
            [B::relative_positions_backward(s.readers, grad, s.points, k)]
        });
    }
}

impl<B: GroupingOps + GroupingKernels, C: CheckpointStrategy> GroupingOps for Autodiff<B, C> {
    fn relative_positions(
        p: FloatTensor<Self>,
        neighbours: IntTensor<Self>,
        centres: IntTensor<Self>,
        readers: IntTensor<Self>,
    ) -> FloatTensor<Self> {
        let points = p.shape()[0];
        let (p, p_node) = p.into_parts();
        let tables = GroupTables {
            neighbours,
            centres,
            readers,
            points,
        };
        // The forward needs `p`, the backward only the tables: `p` goes in through the closure.
        let forward = {
            let p = p.clone();
            move |s: GroupTables<B>| B::relative_positions(p, s.neighbours, s.centres, s.readers)
        };
        record::<B, C, _, _, 1>(GroupingBackward, [p_node], tables, forward)
    }
}

impl<B: FusionBackend + GroupingKernels> GroupingKernels for Fusion<B> {
    fn relative_positions_backward(
        readers: IntTensor<Self>,
        grad: FloatTensor<Self>,
        points: usize,
        k: usize,
    ) -> FloatTensor<Self> {
        let specs = vec![float_like::<B>(
            &grad,
            burn::tensor::Shape::new([points, 3]),
        )];
        let inputs = vec![Input::Int(readers), Input::Float(grad)];
        let [p] = array(deferred::<B, _>(
            "relative_positions_backward",
            inputs,
            specs,
            move |v| {
                let [readers, grad] = array(v);
                vec![Value::Float(B::relative_positions_backward(
                    readers.int(),
                    grad.float(),
                    points,
                    k,
                ))]
            },
        ));
        p
    }
}
