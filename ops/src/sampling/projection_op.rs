//! The pinhole projection of [`super::project_points`] as a Burn backend extension for CubeCL
//! devices.
//!
//! Listed for `Cube`, `Fusion` and `Autodiff`; the CPU backends keep the tensor ops. As tensor
//! ops the projection is a product, column slices of the camera-space points and of the
//! intrinsics (copies, and each slice's backward a zero-fill and a write), a concatenation and
//! the division: about twenty launches forward and backward per call. Here it is one launch each
//! way: one thread per view and point writes `(u, v, Z)`, and its backward `∂p` from
//! `(∂u, ∂v, ∂Z)`. The cameras are constants.

use burn::backend::autodiff::checkpoint::base::Checkpointer;
use burn::backend::autodiff::checkpoint::strategy::CheckpointStrategy;
use burn::backend::autodiff::grads::Gradients;
use burn::backend::autodiff::ops::{Backward, Ops};
use burn::backend::fusion::{Fusion, FusionBackend};
use burn::backend::tensor::FloatTensor;
use burn::backend::{Autodiff, Backend, backend_extension};
use lifegom_render::cube::deferred::{Input, Value, array, deferred, float_like};
use lifegom_render::op_backward::{gradient_per_input, record};

/// Floats per camera in the cameras tensor: `Rᵀ` row-major (9), `t` (3), `fx, fy, cx, cy`.
pub const CAMERA_FLOATS: usize = 16;

/// `(u, v, Z)` `[N, V, 3]` of `points` `[N, V, 3]` seen by `cameras` `[N, 16]`
/// ([`CAMERA_FLOATS`]): `c = p·Rᵀ + t`, `u = c_x / max(c_z, MIN_DEPTH)·fx + cx`, likewise `v`,
/// and `Z = c_z` unclamped ([`super::MIN_DEPTH`]). Callers check the shapes.
#[backend_extension(Cube, Fusion, Autodiff)]
pub trait ProjectionOps: Backend {
    /// The projected points.
    #[fusion(dtype = points, shape = points.clone())]
    fn project(points: FloatTensor<Self>, cameras: FloatTensor<Self>) -> FloatTensor<Self>;
}

/// What a backend implements so that `Autodiff<B>` can differentiate the projection.
#[doc(hidden)]
pub trait ProjectionKernels: Backend {
    /// `∂points` `[N, V, 3]` for the output's gradient `grad` `[N, V, 3]`.
    fn project_backward(
        points: FloatTensor<Self>,
        cameras: FloatTensor<Self>,
        grad: FloatTensor<Self>,
    ) -> FloatTensor<Self>;
}

impl<B: FusionBackend + ProjectionKernels> ProjectionKernels for Fusion<B> {
    fn project_backward(
        points: FloatTensor<Self>,
        cameras: FloatTensor<Self>,
        grad: FloatTensor<Self>,
    ) -> FloatTensor<Self> {
        let specs = vec![float_like::<B>(&points, points.shape.clone())];
        let inputs = [points, cameras, grad]
            .into_iter()
            .map(Input::Float)
            .collect();
        let [dp] = array(deferred::<B, _>("project_backward", inputs, specs, |v| {
            let [p, c, g] = array(v);
            vec![Value::Float(B::project_backward(
                p.float(),
                c.float(),
                g.float(),
            ))]
        }));
        dp
    }
}

/// The node's state: the points and the cameras.
#[derive(Debug, Clone)]
pub struct ProjectInputs<B: Backend> {
    points: FloatTensor<B>,
    cameras: FloatTensor<B>,
}

#[derive(Debug)]
struct ProjectBackward;

impl<B: ProjectionKernels> Backward<B, 1> for ProjectBackward {
    type State = ProjectInputs<B>;

    fn backward(
        self,
        ops: Ops<Self::State, 1>,
        grads: &mut Gradients,
        _checkpointer: &mut Checkpointer,
    ) {
        gradient_per_input::<B, _, 1>(ops, grads, |s, grad| {
            [B::project_backward(s.points, s.cameras, grad)]
        });
    }
}

impl<B: ProjectionOps + ProjectionKernels, C: CheckpointStrategy> ProjectionOps for Autodiff<B, C> {
    fn project(points: FloatTensor<Self>, cameras: FloatTensor<Self>) -> FloatTensor<Self> {
        let (points, points_node) = points.into_parts();
        let cameras = cameras.into_primitive();
        record::<B, C, _, _, 1>(
            ProjectBackward,
            [points_node],
            ProjectInputs { points, cameras },
            |s| B::project(s.points, s.cameras),
        )
    }
}
