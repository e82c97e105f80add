//! Free-view turntables of a reconstructed avatar, and the motions it is animated with.
//!
//! - **Free view** (design.md §10.5): the output frame's camera orbits the body's vertical axis
//!   through the posed root joint, `2π·k/frames` per frame. The camera already has the body
//!   transform folded in (`cam_from_body`), so the orbit is `cam_from_body · T(r)·R_y(θ)·T(−r)`.
//! - **Novel poses** (design.md §10.5): the procedural motions and pose-sequence files live in
//!   [`lifegom_render::motion`] (the synthetic data generator drives its people with them too);
//!   they are re-exported here for the evaluation's callers.

use glam::{Affine3A, Vec3};
use lifegom_render::camera::Camera;

pub use lifegom_render::motion::{JointRoles, Motion, MotionSource, PoseSequence};

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
