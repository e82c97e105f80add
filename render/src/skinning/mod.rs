//! Linear blend skinning (LBS), as the reference applies it (`apply_lbs`; design.md §4.3).
//!
//! A canonical point `x` with weights `w_j` moves to
//!
//! ```text
//! x' = Σ_j w_j (R_j x + t_j)
//! ```
//!
//! where `[R_j | t_j]` are the skinning transforms `M_j = G_j · Trans(−J_j)` of
//! [`Skeleton::skinning_transforms`](crate::skeleton::Skeleton::skinning_transforms). There is
//! **no division by Σ_j w_j**: the reference does not normalise (the paper does; design.md §4.3, §12). The
//! template's weights sum to 1 within 1.2e-7, so the two agree on it, but a caller that edits
//! weights gets exactly the reference behaviour.
//!
//! Two implementations of the same formula:
//!
//! * [`skin_points`]: CPU, `glam`, no gradient (data preparation, tests, visualisation);
//! * [`skin_vertices`]: Burn tensor ops, differentiable with respect to the vertices and the
//!   weights. The transforms become a `[J, 12]` tensor (row-major 3×4 per joint,
//!   [`transforms_tensor`]); one matmul blends them per vertex (`[V, J]·[J, 12] → [V, 12]`,
//!   i.e. `Σ_j w_j M_j`, which equals `Σ_j w_j (M_j x)` by linearity), and the blended 3×4
//!   matrices are applied to `[x, 1]` with elementwise ops. Blending the matrices first is one
//!   matmul and never builds the `[V, J, 3]` tensor of every joint's transform of every vertex.
//!
//!   On CubeCL devices [`skin_vertices`] is one op instead (the `op` and `cube` modules): one
//!   thread per vertex sums its joints' transforms of it, and the backward recomputes them for
//!   the weights' gradient. The tensor ops are five to six launches forward and as many
//!   backward (the matmul, a ones tensor and its concatenation, the broadcast product and its
//!   sum, and their gradients); the op is one each way. The CPU backends keep the tensor ops.
//!
//! Weights are stored sparse, 4 per vertex as in the glTF (`JOINTS_0`/`WEIGHTS_0`), and made
//! dense (`[V, J]`, row-major) for the tensor path.

mod cube;
pub mod op;

use burn::backend::Dispatch;
use burn::tensor::{Device, Tensor, TensorData};
use glam::{Affine3A, Vec3};

use crate::device::runs_on_host;
use crate::error::{RenderError, Result};

/// Sparse skinning weights: 4 (joint, weight) pairs per vertex, as `JOINTS_0`/`WEIGHTS_0`.
/// Unused slots have weight 0; a joint may appear in several slots (their weights add up).
#[derive(Debug, Clone, PartialEq)]
pub struct SkinWeights {
    /// Number of joints `J` of the skeleton the indices refer to.
    pub num_joints: usize,
    /// Joint indices per vertex, each `< num_joints`.
    pub joints: Vec<[u16; 4]>,
    /// Weights per vertex, finite and `>= 0`, matching `joints` slot by slot.
    pub weights: Vec<[f32; 4]>,
}

impl SkinWeights {
    /// Builds and validates sparse weights (see [`SkinWeights::validate`]).
    pub fn new(num_joints: usize, joints: Vec<[u16; 4]>, weights: Vec<[f32; 4]>) -> Result<Self> {
        let skin = Self {
            num_joints,
            joints,
            weights,
        };
        skin.validate()?;
        Ok(skin)
    }

    /// Number of vertices.
    pub fn num_vertices(&self) -> usize {
        self.joints.len()
    }

    /// Checks that there is one joint set and one weight set per vertex, that every joint index
    /// is below `num_joints` and that every weight is finite and non-negative. Errors name the
    /// vertex.
    pub fn validate(&self) -> Result<()> {
        if self.joints.len() != self.weights.len() {
            return Err(invalid(format!(
                "{} joint sets but {} weight sets",
                self.joints.len(),
                self.weights.len()
            )));
        }
        for (v, (joints, weights)) in self.joints.iter().zip(&self.weights).enumerate() {
            if let Some(&j) = joints.iter().find(|&&j| j as usize >= self.num_joints) {
                return Err(invalid(format!(
                    "vertex {v} refers to joint {j}, past the {} joints",
                    self.num_joints
                )));
            }
            if weights.iter().any(|w| !(w.is_finite() && *w >= 0.0)) {
                return Err(invalid(format!(
                    "vertex {v} has a negative or non-finite weight {weights:?}"
                )));
            }
        }
        Ok(())
    }

    /// The dense `[V, J]` matrix, row-major. Slots naming the same joint are summed.
    ///
    /// # Panics
    ///
    /// If a joint index is `>= num_joints` (an invariant [`SkinWeights::new`] checks).
    pub fn to_dense(&self) -> Vec<f32> {
        let j_count = self.num_joints;
        let mut dense = vec![0.0f32; self.num_vertices() * j_count];
        for (v, (joints, weights)) in self.joints.iter().zip(&self.weights).enumerate() {
            for (&j, &w) in joints.iter().zip(weights) {
                assert!(
                    (j as usize) < j_count,
                    "vertex {v}: joint {j} >= {j_count} joints"
                );
                dense[v * j_count + j as usize] += w;
            }
        }
        dense
    }

    /// The dense weights as a `[V, J]` tensor on `device`.
    pub fn tensor(&self, device: &Device) -> Tensor<2> {
        let shape = [self.num_vertices(), self.num_joints];
        Tensor::<2>::from_data(TensorData::new(self.to_dense(), shape), device)
    }
}

/// Skinning transforms as a `[J, 12]` tensor: row `j` is `M_j` as a row-major 3×4 `[R | t]`.
pub fn transforms_tensor(transforms: &[Affine3A], device: &Device) -> Tensor<2> {
    let mut rows = Vec::with_capacity(transforms.len() * 12);
    for m in transforms {
        let (r, t) = (m.matrix3, m.translation);
        rows.extend_from_slice(&[
            r.x_axis.x, r.y_axis.x, r.z_axis.x, t.x, //
            r.x_axis.y, r.y_axis.y, r.z_axis.y, t.y, //
            r.x_axis.z, r.y_axis.z, r.z_axis.z, t.z,
        ]);
    }
    Tensor::<2>::from_data(TensorData::new(rows, [transforms.len(), 12]), device)
}

/// LBS on the CPU: `x' = Σ_j w_j (R_j x + t_j)`, no normalisation by `Σ w` (module docs).
///
/// Fails if `points`, `weights` and `transforms` disagree on the vertex or joint count, or if
/// `weights` is invalid.
pub fn skin_points(
    points: &[Vec3],
    weights: &SkinWeights,
    transforms: &[Affine3A],
) -> Result<Vec<Vec3>> {
    weights.validate()?;
    if points.len() != weights.num_vertices() {
        return Err(RenderError::InvalidInput {
            what: "skin_points",
            reason: format!(
                "{} points but skinning weights for {} vertices",
                points.len(),
                weights.num_vertices()
            ),
        });
    }
    check_joint_count(weights.num_joints, transforms.len())?;
    Ok(points
        .iter()
        .zip(weights.joints.iter().zip(&weights.weights))
        .map(|(&x, (joints, w))| {
            joints
                .iter()
                .zip(w)
                .map(|(&j, &w)| w * transforms[j as usize].transform_point3(x))
                .sum()
        })
        .collect())
}

/// LBS as differentiable Burn ops: `vertices` `[V, 3]`, dense `weights` `[V, J]` and one
/// transform per joint give the posed `[V, 3]` vertices. Gradients flow to `vertices` and
/// `weights`; the transforms are constants. The transforms tensor is made on the device of
/// `vertices`.
pub fn skin_vertices(
    vertices: Tensor<2>,
    weights: Tensor<2>,
    transforms: &[Affine3A],
) -> Result<Tensor<2>> {
    let [num_vertices, three] = vertices.dims();
    if three != 3 {
        return Err(RenderError::Shape {
            tensor: "vertices",
            expected: "[V, 3]".into(),
            got: vertices.dims().to_vec(),
        });
    }
    let [weight_rows, num_joints] = weights.dims();
    if weight_rows != num_vertices || num_joints != transforms.len() {
        return Err(RenderError::Shape {
            tensor: "weights",
            expected: format!("[V, J] = [{num_vertices}, {}]", transforms.len()),
            got: weights.dims().to_vec(),
        });
    }
    let device = vertices.device();
    if !runs_on_host(&device) {
        return Ok(Tensor::from_dispatch(<Dispatch as op::SkinningOps>::skin(
            vertices.into_dispatch(),
            weights.into_dispatch(),
            transforms_tensor(transforms, &device).into_dispatch(),
        )));
    }
    // Σ_j w_j M_j per vertex: [V, J]·[J, 12] → [V, 12] → [V, 3, 4].
    let blended = weights
        .matmul(transforms_tensor(transforms, &device))
        .reshape([num_vertices, 3, 4]);
    // [x, y, z, 1] broadcast over the three rows of each blended matrix.
    let ones = Tensor::<2>::ones([num_vertices, 1], &device);
    let homogeneous = Tensor::cat(vec![vertices, ones], 1).reshape([num_vertices, 1, 4]);
    Ok(blended
        .mul(homogeneous)
        .sum_dim(2)
        .reshape([num_vertices, 3]))
}

fn check_joint_count(weight_joints: usize, transforms: usize) -> Result<()> {
    if weight_joints != transforms {
        return Err(RenderError::InvalidInput {
            what: "transforms",
            reason: format!(
                "{transforms} skinning transforms for weights over {weight_joints} joints"
            ),
        });
    }
    Ok(())
}

fn invalid(reason: String) -> RenderError {
    RenderError::InvalidInput {
        what: "skin weights",
        reason,
    }
}

#[cfg(test)]
mod tests {
    #![allow(deprecated)] // `Device::ndarray()` is deprecated in Burn 0.22; CI still covers it.

    use super::*;
    use crate::skeleton::BodyPose;
    use crate::template::{BodyTemplate, lowres_template_path};

    /// Deterministic pseudo-random numbers in [-1, 1) from the workspace's seeded generator.
    struct Lcg(crate::rng::Rng);
    impl Lcg {
        fn next(&mut self) -> f32 {
            self.0.range_f32(-1.0, 1.0)
        }
        fn vec3(&mut self, scale: f32) -> Vec3 {
            Vec3::new(self.next(), self.next(), self.next()) * scale
        }
    }

    fn template() -> BodyTemplate {
        BodyTemplate::load(lowres_template_path()).unwrap()
    }

    fn random_pose(joints: usize, rng: &mut Lcg) -> BodyPose {
        BodyPose {
            joint_rotations: (0..joints).map(|_| rng.vec3(0.6)).collect(),
        }
    }

    fn max_dist(a: &[Vec3], b: &[Vec3]) -> f32 {
        assert_eq!(a.len(), b.len());
        a.iter()
            .zip(b)
            .map(|(a, b)| (*a - *b).length())
            .fold(0.0, f32::max)
    }

    fn to_points(t: Tensor<2>) -> Vec<Vec3> {
        t.into_data()
            .try_into_vec::<f32>()
            .unwrap()
            .chunks_exact(3)
            .map(Vec3::from_slice)
            .collect()
    }

    #[test]
    fn rest_pose_reproduces_the_bind_vertices() {
        let body = template();
        let m = body
            .skeleton
            .skinning_transforms(&BodyPose::rest(body.skeleton.num_joints()))
            .unwrap();
        let skinned = skin_points(&body.vertices, &body.skin, &m).unwrap();
        let err = max_dist(&skinned, &body.vertices);
        assert!(err <= 1e-5, "rest-pose LBS error {err} m");
    }

    #[test]
    fn posing_the_left_upper_arm_moves_the_hand_not_the_feet() {
        let body = template();
        let s = &body.skeleton;
        let arm = s.joint_index("upperarm01.L").expect("upperarm01.L");
        let mut pose = BodyPose::rest(s.num_joints());
        // 45° about the body's forward axis (+Z): the T-posed left arm (along +X) is raised.
        pose.joint_rotations[arm] = Vec3::Z * std::f32::consts::FRAC_PI_4;
        let m = s.skinning_transforms(&pose).unwrap();
        let skinned = skin_points(&body.vertices, &body.skin, &m).unwrap();
        let dense = body.skin.to_dense();
        let j = s.num_joints();
        // Vertices bound mostly to the named joint (dominant weight > 0.5).
        let bound_to = |name: &str| {
            let k = s.joint_index(name).unwrap();
            (0..body.vertices.len())
                .filter(|&v| dense[v * j + k] > 0.5)
                .collect::<Vec<_>>()
        };
        let hand = bound_to("wrist.L");
        let feet: Vec<_> = bound_to("foot.L")
            .into_iter()
            .chain(bound_to("foot.R"))
            .collect();
        assert!(!hand.is_empty() && !feet.is_empty());
        for &v in &hand {
            let moved = (skinned[v] - body.vertices[v]).length();
            assert!(moved > 0.1, "hand vertex {v} moved only {moved} m");
        }
        for &v in &feet {
            assert!(
                (skinned[v] - body.vertices[v]).length() < 1e-6,
                "foot vertex {v} moved"
            );
        }
        // The hand vertex stays at its distance from the shoulder joint (a rigid rotation).
        let shoulder = s.rest_joints[arm];
        for &v in &hand {
            let before = (body.vertices[v] - shoulder).length();
            let after = (skinned[v] - shoulder).length();
            assert!((before - after).abs() < 1e-4);
        }
    }

    fn check_tensor_matches_cpu(device: &Device) {
        let body = template();
        let mut rng = Lcg(crate::rng::Rng::new(7));
        let pose = random_pose(body.skeleton.num_joints(), &mut rng);
        let m = body.skeleton.skinning_transforms(&pose).unwrap();
        let cpu = skin_points(&body.vertices, &body.skin, &m).unwrap();
        let posed =
            skin_vertices(body.vertex_tensor(device), body.skin.tensor(device), &m).unwrap();
        assert_eq!(posed.dims(), [body.vertices.len(), 3]);
        let err = max_dist(&to_points(posed), &cpu);
        assert!(err <= 1e-5, "tensor vs CPU LBS: {err} m");
    }

    crate::cpu_backend_tests!(tensor_lbs_matches_cpu_on => check_tensor_matches_cpu);

    /// The same on lavapipe, where the skinning is one op.
    #[test]
    fn tensor_lbs_matches_cpu_on_wgpu() {
        if let Some(device) = crate::testing::wgpu_test_device() {
            check_tensor_matches_cpu(&device);
        }
    }

    #[test]
    fn no_normalisation_by_the_weight_sum() {
        // One vertex, weights 0.5 + 0.25 on two translations: x' = 0.5(x+a) + 0.25(x+b).
        let skin = SkinWeights::new(2, vec![[0, 1, 0, 0]], vec![[0.5, 0.25, 0.0, 0.0]]).unwrap();
        let (a, b) = (Vec3::new(1.0, 0.0, 0.0), Vec3::new(0.0, 2.0, 0.0));
        let m = [Affine3A::from_translation(a), Affine3A::from_translation(b)];
        let x = Vec3::new(0.2, 0.4, 0.8);
        let expected = 0.5 * (x + a) + 0.25 * (x + b);
        assert!((skin_points(&[x], &skin, &m).unwrap()[0] - expected).length() < 1e-6);
        let device = Device::ndarray();
        let xt = Tensor::<2>::from_data(TensorData::new(x.to_array().to_vec(), [1, 3]), &device);
        let got = to_points(skin_vertices(xt, skin.tensor(&device), &m).unwrap());
        assert!((got[0] - expected).length() < 1e-6);
    }

    #[test]
    fn gradient_matches_central_differences() {
        check_gradient(&Device::ndarray());
    }

    /// The same on lavapipe, where the backward is one kernel (central differences on ndarray).
    #[test]
    fn gradient_matches_central_differences_wgpu() {
        if let Some(device) = crate::testing::wgpu_test_device() {
            check_gradient(&device);
        }
    }

    /// The gradients of `device`'s skinning against central differences of the loss on
    /// ndarray.
    fn check_gradient(device: &Device) {
        // A small random instance: 5 vertices, 3 joints, dense random weights; the loss
        // Σ (x' − target)² is quadratic in the vertices and in the weights, so central
        // differences are exact up to f32 rounding.
        let device = device.clone().autodiff();
        let mut rng = Lcg(crate::rng::Rng::new(11));
        let (v, j) = (5usize, 3usize);
        let transforms: Vec<Affine3A> = (0..j)
            .map(|_| {
                Affine3A::from_mat3_translation(
                    crate::skeleton::rodrigues(rng.vec3(1.0)),
                    rng.vec3(0.5),
                )
            })
            .collect();
        let points: Vec<f32> = (0..v * 3).map(|_| rng.next()).collect();
        let weights: Vec<f32> = (0..v * j).map(|_| rng.next().abs()).collect();
        let target: Vec<f32> = (0..v * 3).map(|_| rng.next()).collect();
        let loss_of = |pts: &[f32], wts: &[f32], dev: &Device| {
            let x = Tensor::<2>::from_data(TensorData::new(pts.to_vec(), [v, 3]), dev);
            let w = Tensor::<2>::from_data(TensorData::new(wts.to_vec(), [v, j]), dev);
            let (x, w) = if dev.is_autodiff() {
                (x.require_grad(), w.require_grad())
            } else {
                (x, w)
            };
            let t = Tensor::<2>::from_data(TensorData::new(target.clone(), [v, 3]), dev);
            let diff = skin_vertices(x.clone(), w.clone(), &transforms).unwrap() - t;
            (x, w, diff.clone().mul(diff).sum())
        };
        let (x, w, loss) = loss_of(&points, &weights, &device);
        let grads = loss.backward();
        let read = |g: Option<Tensor<2>>| g.unwrap().into_data().try_into_vec::<f32>().unwrap();
        let (dx, dw) = (read(x.grad(&grads)), read(w.grad(&grads)));
        let plain = Device::ndarray();
        let f = |p: &[f32], w: &[f32]| loss_of(p, w, &plain).2.into_scalar::<f32>();
        let eps = 1e-2f32;
        let central = |values: &[f32], k: usize, eval: &dyn Fn(&[f32]) -> f32| {
            let (mut plus, mut minus) = (values.to_vec(), values.to_vec());
            plus[k] += eps;
            minus[k] -= eps;
            (eval(&plus) - eval(&minus)) / (2.0 * eps)
        };
        assert_eq!((dx.len(), dw.len()), (v * 3, v * j));
        for (k, &analytic) in dx.iter().enumerate() {
            let numeric = central(&points, k, &|p| f(p, &weights));
            let tol = 2e-3 * (1.0 + numeric.abs());
            assert!(
                (numeric - analytic).abs() < tol,
                "d/dx[{k}]: numeric {numeric}, analytic {analytic}"
            );
        }
        for (k, &analytic) in dw.iter().enumerate() {
            let numeric = central(&weights, k, &|w| f(&points, w));
            let tol = 2e-3 * (1.0 + numeric.abs());
            assert!(
                (numeric - analytic).abs() < tol,
                "d/dw[{k}]: numeric {numeric}, analytic {analytic}"
            );
        }
    }

    #[test]
    fn shape_and_count_mismatches_are_errors() {
        let device = Device::ndarray();
        let m = [Affine3A::IDENTITY; 2];
        let x = Tensor::<2>::zeros([4, 2], &device);
        let w = Tensor::<2>::zeros([4, 2], &device);
        assert!(matches!(
            skin_vertices(x, w.clone(), &m),
            Err(RenderError::Shape {
                tensor: "vertices",
                ..
            })
        ));
        let x = Tensor::<2>::zeros([4, 3], &device);
        assert!(matches!(
            skin_vertices(x, w, &m[..1]),
            Err(RenderError::Shape {
                tensor: "weights",
                ..
            })
        ));
        let skin = SkinWeights::new(2, vec![[0, 1, 0, 0]], vec![[1.0, 0.0, 0.0, 0.0]]).unwrap();
        assert!(skin_points(&[Vec3::ZERO; 2], &skin, &m).is_err());
        assert!(skin_points(&[Vec3::ZERO], &skin, &m[..1]).is_err());
        assert!(SkinWeights::new(2, vec![[0, 2, 0, 0]], vec![[1.0, 0.0, 0.0, 0.0]]).is_err());
        assert!(SkinWeights::new(2, vec![[0, 1, 0, 0]], vec![[f32::NAN, 0.0, 0.0, 0.0]]).is_err());
    }

    #[test]
    fn dense_weights_sum_repeated_joints() {
        let skin = SkinWeights::new(3, vec![[2, 2, 0, 0]], vec![[0.25, 0.5, 0.25, 0.0]]).unwrap();
        assert_eq!(skin.to_dense(), vec![0.25, 0.0, 0.75]);
        let t = skin.tensor(&Device::flex());
        assert_eq!(t.dims(), [1, 3]);
    }
}
