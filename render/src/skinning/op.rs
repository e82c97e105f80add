//! [`super::skin_vertices`] as a Burn backend extension for CubeCL devices (see [`super`]).
//!
//! Listed for `Cube`, `Fusion` and `Autodiff`; the CPU backends keep the tensor ops. The
//! autodiff node keeps the vertices, the weights and the transforms: its backward recomputes
//! each joint's transform of each vertex, which the weights' gradient needs, instead of keeping
//! `[V, J, 3]` of them.

use burn::backend::autodiff::checkpoint::base::Checkpointer;
use burn::backend::autodiff::checkpoint::strategy::CheckpointStrategy;
use burn::backend::autodiff::grads::Gradients;
use burn::backend::autodiff::ops::{Backward, Ops};
use burn::backend::fusion::{Fusion, FusionBackend};
use burn::backend::tensor::FloatTensor;
use burn::backend::{Autodiff, Backend, backend_extension};

use crate::cube::deferred::{Input, Value, array, deferred, float_like};
use crate::op_backward::{gradient_per_input, record};

/// `x'_v = Σ_j w_vj (R_j x_v + t_j)` for `vertices` `[V, 3]`, `weights` `[V, J]` and
/// `transforms` `[J, 12]` (row-major `[R | t]`, [`super::transforms_tensor`]), `[V, 3]`.
/// Callers check the shapes.
#[backend_extension(Cube, Fusion, Autodiff)]
pub trait SkinningOps: Backend {
    /// The posed vertices.
    #[fusion(dtype = vertices, shape = vertices.clone())]
    fn skin(
        vertices: FloatTensor<Self>,
        weights: FloatTensor<Self>,
        transforms: FloatTensor<Self>,
    ) -> FloatTensor<Self>;
}

/// What a backend implements so that `Autodiff<B>` can differentiate the skinning.
#[doc(hidden)]
pub trait SkinningKernels: Backend {
    /// `(∂vertices [V, 3], ∂weights [V, J])` for the output's gradient `grad` `[V, 3]`:
    /// `∂x_v = Σ_j w_vj R_jᵀ g_v` and `∂w_vj = g_v · (R_j x_v + t_j)`.
    fn skin_backward(
        vertices: FloatTensor<Self>,
        weights: FloatTensor<Self>,
        transforms: FloatTensor<Self>,
        grad: FloatTensor<Self>,
    ) -> (FloatTensor<Self>, FloatTensor<Self>);
}

impl<B: FusionBackend + SkinningKernels> SkinningKernels for Fusion<B> {
    fn skin_backward(
        vertices: FloatTensor<Self>,
        weights: FloatTensor<Self>,
        transforms: FloatTensor<Self>,
        grad: FloatTensor<Self>,
    ) -> (FloatTensor<Self>, FloatTensor<Self>) {
        let specs = vec![
            float_like::<B>(&vertices, vertices.shape.clone()),
            float_like::<B>(&weights, weights.shape.clone()),
        ];
        let inputs = [vertices, weights, transforms, grad]
            .into_iter()
            .map(Input::Float)
            .collect();
        let [dx, dw] = array(deferred::<B, _>("skin_backward", inputs, specs, |v| {
            let [x, w, m, g] = array(v);
            let (dx, dw) = B::skin_backward(x.float(), w.float(), m.float(), g.float());
            vec![Value::Float(dx), Value::Float(dw)]
        }));
        (dx, dw)
    }
}

/// The node's state: the op's three inputs.
#[derive(Debug, Clone)]
pub struct SkinInputs<B: Backend> {
    vertices: FloatTensor<B>,
    weights: FloatTensor<B>,
    transforms: FloatTensor<B>,
}

#[derive(Debug)]
struct SkinBackward;

impl<B: SkinningKernels> Backward<B, 2> for SkinBackward {
    type State = SkinInputs<B>;

    fn backward(
        self,
        ops: Ops<Self::State, 2>,
        grads: &mut Gradients,
        _checkpointer: &mut Checkpointer,
    ) {
        gradient_per_input::<B, _, 2>(ops, grads, |s, grad| {
            let (dx, dw) = B::skin_backward(s.vertices, s.weights, s.transforms, grad);
            [dx, dw]
        });
    }
}

impl<B: SkinningOps + SkinningKernels, C: CheckpointStrategy> SkinningOps for Autodiff<B, C> {
    fn skin(
        vertices: FloatTensor<Self>,
        weights: FloatTensor<Self>,
        transforms: FloatTensor<Self>,
    ) -> FloatTensor<Self> {
        let (vertices, vertices_node) = vertices.into_parts();
        let (weights, weights_node) = weights.into_parts();
        // The transforms are constants of the pose.
        let transforms = transforms.into_primitive();
        record::<B, C, _, _, 2>(
            SkinBackward,
            [vertices_node, weights_node],
            SkinInputs {
                vertices,
                weights,
                transforms,
            },
            |s| B::skin(s.vertices, s.weights, s.transforms),
        )
    }
}
