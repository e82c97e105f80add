//! Skeletons and forward kinematics, SMPL-style, exactly as the reference code poses its body
//! model (design.md §4.1–§4.2).
//!
//! # Convention: world-aligned joint frames
//!
//! A skeleton is only a kinematic tree of joint *positions* (`rest_joints`, the joint heads of
//! the canonical body). Joints carry no bone orientation: every joint frame is aligned with the
//! world axes in the canonical pose, so a joint's axis-angle rotates about world-aligned axes
//! through the joint head. This is what SMPL(-X) does, and what the reference code computes:
//!
//! * local rotation `R_i = rodrigues(pose_i)`;
//! * local translation `t_0 = J_0` for a root, `t_i = J_i − J_parent(i)` otherwise;
//! * global transform `G_i = G_parent(i) · [R_i | t_i]` (a root has no parent factor);
//! * skinning transform `M_i = G_i · Trans(−J_i)`.
//!
//! The canonical pose is the zero pose, whose global transforms are pure translations
//! `G_i^cnl = Trans(J_i)`, so `M_i = G_i · (G_i^cnl)⁻¹` is `G_i · Trans(−J_i)`, and the zero pose
//! gives `M_i = I` exactly: skinning with it reproduces the bind vertices. The posed joint heads
//! are the translations of `G_i`.
//!
//! Forward kinematics runs in f64 (a chain of ~10 joints from the root to a fingertip) and
//! returns f32; the f64 Rodrigues uses the same formula as [`rodrigues`].
//!
//! # Invariants
//!
//! [`Skeleton::new`] checks that the three vectors have one entry per joint, that names are
//! unique, that every parent index is a valid joint other than the joint itself, that the
//! parent links form a forest (no cycle, at least one root), and that the joint positions are
//! finite. Parents need not come before their children: forward kinematics visits joints in a
//! topological order (the glTF order when it is already topological, as in the Anny files).

use glam::{Affine3A, DAffine3, DMat3, DVec3, Mat3, Vec3};

use crate::error::{RenderError, Result};

/// Axis-angle to rotation matrix, as the reference computes it: `r = v/(|v| + 1e-5)`, `θ = |v|`
/// (so a zero vector is exactly the identity and 360° comes back to the identity).
pub fn rodrigues(axis_angle: Vec3) -> Mat3 {
    let theta = axis_angle.length();
    let r = axis_angle / (theta + 1e-5);
    let (s, c) = theta.sin_cos();
    let k = Mat3::from_cols(
        Vec3::new(0.0, r.z, -r.y),
        Vec3::new(-r.z, 0.0, r.x),
        Vec3::new(r.y, -r.x, 0.0),
    );
    Mat3::IDENTITY + k * s + k * k * (1.0 - c)
}

/// [`rodrigues`] in f64, for forward kinematics. The `1e-5` guard is kept, so both agree to f32
/// rounding (the guard makes the matrix very slightly non-orthogonal, as in the reference).
fn rodrigues_f64(axis_angle: DVec3) -> DMat3 {
    let theta = axis_angle.length();
    let r = axis_angle / (theta + 1e-5);
    let (s, c) = theta.sin_cos();
    let k = DMat3::from_cols(
        DVec3::new(0.0, r.z, -r.y),
        DVec3::new(-r.z, 0.0, r.x),
        DVec3::new(r.y, -r.x, 0.0),
    );
    DMat3::IDENTITY + k * s + k * k * (1.0 - c)
}

/// A kinematic tree of joint heads with world-aligned frames (see the module docs).
#[derive(Debug, Clone, PartialEq)]
pub struct Skeleton {
    /// Joint names, unique (the Anny bone labels: `root`, `pelvis.L`, `upperarm01.L`, ...).
    pub names: Vec<String>,
    /// Parent of each joint; `None` for a root.
    pub parents: Vec<Option<usize>>,
    /// Canonical (rest) joint heads, in the template's frame (metres).
    pub rest_joints: Vec<Vec3>,
}

/// A body pose: one local axis-angle rotation per joint (radians), about world-aligned axes
/// through the joint head, as the reference's `poses[3i..3i+3]`.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct BodyPose {
    /// Axis-angle of joint `i`, in the skeleton's joint order.
    pub joint_rotations: Vec<Vec3>,
}

impl BodyPose {
    /// The canonical pose: every rotation zero.
    pub fn rest(num_joints: usize) -> Self {
        Self {
            joint_rotations: vec![Vec3::ZERO; num_joints],
        }
    }

    /// Reads a flat `[x0, y0, z0, x1, ...]` axis-angle vector (the reference's `poses`). Its
    /// length must be a multiple of 3; finiteness is checked against a skeleton, which can name
    /// the joint (see [`Skeleton::validate_pose`]).
    pub fn from_flat(values: &[f32]) -> Result<Self> {
        if !values.len().is_multiple_of(3) {
            return Err(RenderError::InvalidInput {
                what: "pose",
                reason: format!(
                    "a flat axis-angle pose has 3 values per joint, got {} values",
                    values.len()
                ),
            });
        }
        let joint_rotations = values.chunks_exact(3).map(Vec3::from_slice).collect();
        Ok(Self { joint_rotations })
    }

    /// The flat `[x0, y0, z0, x1, ...]` form.
    pub fn to_flat(&self) -> Vec<f32> {
        self.joint_rotations
            .iter()
            .flat_map(|r| r.to_array())
            .collect()
    }

    /// Number of joints the pose covers.
    pub fn num_joints(&self) -> usize {
        self.joint_rotations.len()
    }
}

impl Skeleton {
    /// Builds and validates a skeleton (invariants in the module docs). Errors name the joint.
    pub fn new(
        names: Vec<String>,
        parents: Vec<Option<usize>>,
        rest_joints: Vec<Vec3>,
    ) -> Result<Self> {
        let skeleton = Self {
            names,
            parents,
            rest_joints,
        };
        skeleton.validate()?;
        Ok(skeleton)
    }

    /// The same tree with other rest joint heads (e.g. a shaped body's joints).
    pub fn with_rest_joints(&self, rest_joints: Vec<Vec3>) -> Result<Self> {
        Self::new(self.names.clone(), self.parents.clone(), rest_joints)
    }

    /// Number of joints.
    pub fn num_joints(&self) -> usize {
        self.names.len()
    }

    /// Index of the joint called `name`.
    pub fn joint_index(&self, name: &str) -> Option<usize> {
        self.names.iter().position(|n| n == name)
    }

    /// Checks the invariants documented on the module.
    pub fn validate(&self) -> Result<()> {
        let n = self.names.len();
        if self.parents.len() != n || self.rest_joints.len() != n {
            return Err(invalid(
                "skeleton",
                format!(
                    "{} names, {} parents and {} rest joints: need one of each per joint",
                    n,
                    self.parents.len(),
                    self.rest_joints.len()
                ),
            ));
        }
        for (i, name) in self.names.iter().enumerate() {
            if let Some(first) = self.names[..i].iter().position(|other| other == name) {
                return Err(invalid(
                    "skeleton.names",
                    format!("joints {first} and {i} are both called `{name}`"),
                ));
            }
        }
        for (i, parent) in self.parents.iter().enumerate() {
            match *parent {
                Some(p) if p >= n => {
                    return Err(invalid(
                        "skeleton.parents",
                        format!(
                            "joint {i} `{}` has parent {p}, past the {n} joints",
                            self.names[i]
                        ),
                    ));
                }
                Some(p) if p == i => {
                    return Err(invalid(
                        "skeleton.parents",
                        format!("joint {i} `{}` is its own parent", self.names[i]),
                    ));
                }
                _ => {}
            }
        }
        for (i, j) in self.rest_joints.iter().enumerate() {
            if !j.is_finite() {
                return Err(invalid(
                    "skeleton.rest_joints",
                    format!(
                        "joint {i} `{}` has a non-finite position {j}",
                        self.names[i]
                    ),
                ));
            }
        }
        self.topological_order().map(|_| ())
    }

    /// Joint indices, parents before children: the identity when the stored order already is
    /// topological. Fails on a cycle or when there is no root.
    pub fn topological_order(&self) -> Result<Vec<usize>> {
        let n = self.parents.len();
        if n > 0 && !self.parents.iter().any(Option::is_none) {
            return Err(invalid(
                "skeleton.parents",
                "no root joint (every joint has a parent)".into(),
            ));
        }
        if self
            .parents
            .iter()
            .enumerate()
            .all(|(i, p)| p.is_none_or(|p| p < i))
        {
            return Ok((0..n).collect());
        }
        // Depth of every joint by walking up its chain; a chain longer than `n` is a cycle.
        let mut depth = vec![0usize; n];
        for (i, depth_i) in depth.iter_mut().enumerate() {
            let (mut d, mut j) = (0usize, i);
            while let Some(p) = self.parents[j] {
                d += 1;
                if d > n || p >= n {
                    return Err(invalid(
                        "skeleton.parents",
                        format!("joint {i} `{}` is on a parent cycle", self.names[i]),
                    ));
                }
                j = p;
            }
            *depth_i = d;
        }
        let mut order: Vec<usize> = (0..n).collect();
        // Stable: joints of equal depth keep the stored order.
        order.sort_by_key(|&i| depth[i]);
        Ok(order)
    }

    /// Checks that `pose` has one finite rotation per joint; the error names the first bad joint
    /// by index and name.
    pub fn validate_pose(&self, pose: &BodyPose) -> Result<()> {
        if pose.num_joints() != self.num_joints() {
            return Err(RenderError::InvalidInput {
                what: "pose",
                reason: format!(
                    "{} joint rotations for a skeleton of {} joints",
                    pose.num_joints(),
                    self.num_joints()
                ),
            });
        }
        match pose.joint_rotations.iter().position(|r| !r.is_finite()) {
            Some(i) => Err(RenderError::InvalidInput {
                what: "pose",
                reason: format!(
                    "joint {i} `{}` has a non-finite rotation {}",
                    self.names[i], pose.joint_rotations[i]
                ),
            }),
            None => Ok(()),
        }
    }

    /// Global joint transforms `G_i` of `pose`, in f64.
    fn global_transforms(&self, pose: &BodyPose) -> Result<Vec<DAffine3>> {
        self.validate_pose(pose)?;
        let order = self.topological_order()?;
        let mut global = vec![DAffine3::IDENTITY; self.num_joints()];
        for i in order {
            let joint = self.rest_joints[i].as_dvec3();
            let rotation = rodrigues_f64(pose.joint_rotations[i].as_dvec3());
            global[i] = match self.parents[i] {
                None => DAffine3::from_mat3_translation(rotation, joint),
                Some(p) => {
                    let local = joint - self.rest_joints[p].as_dvec3();
                    global[p] * DAffine3::from_mat3_translation(rotation, local)
                }
            };
        }
        Ok(global)
    }

    /// Skinning transforms `M_i = G_i · Trans(−J_i)` of `pose` (module docs): they map a
    /// canonical point rigidly attached to joint `i` to its posed position. The zero pose gives
    /// identities.
    pub fn skinning_transforms(&self, pose: &BodyPose) -> Result<Vec<Affine3A>> {
        let global = self.global_transforms(pose)?;
        Ok(global
            .iter()
            .zip(&self.rest_joints)
            .map(|(g, joint)| {
                let translation = g.translation - g.matrix3 * joint.as_dvec3();
                Affine3A::from_mat3_translation(g.matrix3.as_mat3(), translation.as_vec3())
            })
            .collect())
    }

    /// Posed joint heads: the translations of the global transforms `G_i`.
    pub fn posed_joints(&self, pose: &BodyPose) -> Result<Vec<Vec3>> {
        Ok(self
            .global_transforms(pose)?
            .iter()
            .map(|g| g.translation.as_vec3())
            .collect())
    }
}

fn invalid(what: &'static str, reason: String) -> RenderError {
    RenderError::InvalidInput { what, reason }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn max_abs(a: Mat3, b: Mat3) -> f32 {
        (a - b)
            .to_cols_array()
            .iter()
            .fold(0.0f32, |m, v| m.max(v.abs()))
    }

    /// A small chain with a branch: 0 → 1 → 2, 0 → 3.
    fn toy() -> Skeleton {
        Skeleton::new(
            ["root", "spine", "head", "leg"].map(String::from).to_vec(),
            vec![None, Some(0), Some(1), Some(0)],
            vec![
                Vec3::new(0.0, 0.1, 0.0),
                Vec3::new(0.0, 0.4, 0.05),
                Vec3::new(0.0, 0.8, 0.0),
                Vec3::new(0.1, -0.4, 0.0),
            ],
        )
        .unwrap()
    }

    #[test]
    fn rodrigues_zero_is_identity_and_full_turns_are_finite() {
        assert_eq!(rodrigues(Vec3::ZERO), Mat3::IDENTITY);
        let axis = Vec3::new(1.0, -2.0, 0.5).normalize();
        let half = rodrigues(axis * std::f32::consts::PI);
        assert!(half.is_finite());
        // 180° about `axis`: the axis is fixed, a perpendicular vector flips.
        assert!((half * axis - axis).length() < 1e-4);
        let perp = axis.any_orthonormal_vector();
        assert!((half * perp + perp).length() < 1e-4);
        let full = rodrigues(axis * std::f32::consts::TAU);
        assert!(full.is_finite());
        assert!(max_abs(full, Mat3::IDENTITY) < 1e-5, "{full}");
    }

    #[test]
    fn rodrigues_matches_glam_for_a_generic_angle() {
        let axis = Vec3::new(0.3, 0.8, -0.5).normalize();
        let angle = 1.1;
        let ours = rodrigues(axis * angle);
        let glam = Mat3::from_axis_angle(axis, angle);
        // The 1e-5 guard in `r = v/(|v|+1e-5)` bounds the difference at about 1e-5.
        assert!(max_abs(ours, glam) < 3e-5, "{ours} vs {glam}");
        let ours64 = rodrigues_f64(axis.as_dvec3() * angle as f64).as_mat3();
        assert!(max_abs(ours, ours64) < 1e-6);
    }

    #[test]
    fn rest_pose_gives_identity_transforms() {
        let s = toy();
        let m = s.skinning_transforms(&BodyPose::rest(4)).unwrap();
        for t in &m {
            assert_eq!(*t, Affine3A::IDENTITY);
        }
        assert_eq!(s.posed_joints(&BodyPose::rest(4)).unwrap(), s.rest_joints);
    }

    #[test]
    fn child_joint_follows_its_parent() {
        let s = toy();
        let mut pose = BodyPose::rest(4);
        pose.joint_rotations[0] = Vec3::new(0.1, 0.7, -0.2);
        pose.joint_rotations[1] = Vec3::new(0.0, 0.0, 0.9);
        pose.joint_rotations[2] = Vec3::new(0.5, 0.0, 0.0);
        let m = s.skinning_transforms(&pose).unwrap();
        let posed = s.posed_joints(&pose).unwrap();
        // A child's head is rigidly attached to its parent: the parent's skinning transform
        // carries the child's rest head to its posed head.
        for (child, parent) in [(1, 0), (2, 1), (3, 0)] {
            let moved = m[parent].transform_point3(s.rest_joints[child]);
            assert!((moved - posed[child]).length() < 1e-6, "joint {child}");
        }
        // A joint's own rotation does not move its own head.
        assert!((m[2].transform_point3(s.rest_joints[2]) - posed[2]).length() < 1e-6);
        // The root rotates about its own head, which stays put.
        assert!((posed[0] - s.rest_joints[0]).length() < 1e-7);
    }

    #[test]
    fn template_joints_follow_their_parents_in_a_random_pose() {
        let body =
            crate::template::BodyTemplate::load(crate::template::lowres_template_path()).unwrap();
        let s = &body.skeleton;
        let mut seed = 3u32;
        let mut next = || {
            seed = seed.wrapping_mul(1664525).wrapping_add(1013904223);
            (seed >> 8) as f32 / (1u32 << 24) as f32 - 0.5
        };
        let pose = BodyPose {
            joint_rotations: (0..s.num_joints())
                .map(|_| Vec3::new(next(), next(), next()))
                .collect(),
        };
        let m = s.skinning_transforms(&pose).unwrap();
        let posed = s.posed_joints(&pose).unwrap();
        for (child, parent) in s.parents.iter().enumerate() {
            let Some(parent) = *parent else { continue };
            let moved = m[parent].transform_point3(s.rest_joints[child]);
            assert!(
                (moved - posed[child]).length() < 1e-5,
                "joint {child} `{}`: {moved} vs {}",
                s.names[child],
                posed[child]
            );
        }
    }

    #[test]
    fn non_topological_order_is_handled() {
        let s = toy();
        // Same tree, stored leaf-first: [head, spine, leg, root].
        let perm = [2usize, 1, 3, 0];
        let inv = |j: usize| perm.iter().position(|&p| p == j).unwrap();
        let shuffled = Skeleton::new(
            perm.iter().map(|&i| s.names[i].clone()).collect(),
            perm.iter().map(|&i| s.parents[i].map(inv)).collect(),
            perm.iter().map(|&i| s.rest_joints[i]).collect(),
        )
        .unwrap();
        assert_eq!(shuffled.topological_order().unwrap()[0], 3);
        let pose = BodyPose {
            joint_rotations: vec![Vec3::new(0.2, 0.1, 0.3); 4],
        };
        let a = s.posed_joints(&pose).unwrap();
        let b = shuffled.posed_joints(&pose).unwrap();
        for (k, &i) in perm.iter().enumerate() {
            assert!((a[i] - b[k]).length() < 1e-6);
        }
    }

    #[test]
    fn invalid_skeletons_name_the_joint() {
        let names = || ["a", "b"].map(String::from).to_vec();
        let j = vec![Vec3::ZERO, Vec3::X];
        let err = Skeleton::new(names(), vec![None, Some(5)], j.clone())
            .unwrap_err()
            .to_string();
        assert!(err.contains("`b`"), "{err}");
        let err = Skeleton::new(names(), vec![Some(1), Some(0)], j.clone())
            .unwrap_err()
            .to_string();
        assert!(err.contains("cycle") || err.contains("no root"), "{err}");
        let err = Skeleton::new(names(), vec![None, Some(0)], vec![Vec3::ZERO, Vec3::NAN])
            .unwrap_err()
            .to_string();
        assert!(err.contains("`b`") && err.contains("non-finite"), "{err}");
        assert!(Skeleton::new(names(), vec![None], j.clone()).is_err());
        let dup = ["a", "a"].map(String::from).to_vec();
        assert!(Skeleton::new(dup, vec![None, Some(0)], j).is_err());
        // A cycle below a valid root.
        let err = Skeleton::new(
            ["r", "x", "y"].map(String::from).to_vec(),
            vec![None, Some(2), Some(1)],
            vec![Vec3::ZERO; 3],
        )
        .unwrap_err()
        .to_string();
        assert!(err.contains("cycle"), "{err}");
    }

    #[test]
    fn nan_pose_is_rejected_with_the_joint_named() {
        let s = toy();
        let mut pose = BodyPose::rest(4);
        pose.joint_rotations[2].y = f32::NAN;
        let err = s.skinning_transforms(&pose).unwrap_err().to_string();
        assert!(err.contains("joint 2") && err.contains("`head`"), "{err}");
        pose.joint_rotations[2].y = f32::INFINITY;
        assert!(
            s.posed_joints(&pose)
                .unwrap_err()
                .to_string()
                .contains("`head`")
        );
        assert!(s.skinning_transforms(&BodyPose::rest(3)).is_err());
    }

    #[test]
    fn flat_pose_round_trips() {
        let flat: Vec<f32> = (0..12).map(|i| i as f32 * 0.1).collect();
        let pose = BodyPose::from_flat(&flat).unwrap();
        assert_eq!(pose.num_joints(), 4);
        assert_eq!(pose.joint_rotations[1], Vec3::new(0.3, 0.4, 0.5));
        assert_eq!(pose.to_flat(), flat);
        assert!(BodyPose::from_flat(&flat[..5]).is_err());
    }
}
