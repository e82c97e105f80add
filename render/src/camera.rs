//! Pinhole cameras with OpenCV axes, as the official LIFe-GoM data stores them.
//!
//! A camera is the intrinsic matrix `K` (pixels), the world-to-camera extrinsic `E` (a rigid
//! transform; camera axes x right, y down, z forward) and an image size.
//!
//! # Pixel convention
//!
//! A point `x` projects to `(u, v) = (fx·X/Z + cx, fy·Y/Z + cy)` with `(X, Y, Z) = E·x`. Pixel
//! `(i, j)` covers `[i, i+1) × [j, j+1)` in these coordinates, so its centre is `(i + ½, j + ½)`.
//! This is exactly the reference rasterizer's convention (it shifts the projected centre by −½
//! and samples pixels at integers; design.md §3.3). The Gaussian rasterizer and the triangle-ID
//! rasterizer both sample at pixel centres.
//!
//! # Global body transform
//!
//! The reference folds each frame's global body rotation/translation (`Rh`, `Th`) into the
//! extrinsic: `E' = E · [R(Rh) | Th]`. [`Camera::with_body_transform`] does that, so skinning
//! never has to apply a global transform to points.

use glam::{Affine3A, Mat3, Mat3A, Vec2, Vec3, Vec3A};

use crate::error::{RenderError, Result};

/// Intrinsics in pixels.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Intrinsics {
    /// Focal length along x, pixels.
    pub fx: f32,
    /// Focal length along y, pixels.
    pub fy: f32,
    /// Principal point x, pixels (pixel `i` covers `[i, i+1)`).
    pub cx: f32,
    /// Principal point y, pixels.
    pub cy: f32,
}

impl Intrinsics {
    /// Reads a row-major 3×3 `K`. Skew is not supported and must be zero.
    pub fn from_matrix(k: [[f32; 3]; 3]) -> Result<Self> {
        if k.iter().flatten().any(|v| !v.is_finite()) {
            return Err(invalid("K", "non-finite entry"));
        }
        if k[0][1] != 0.0 || k[1][0] != 0.0 || k[2] != [0.0, 0.0, 1.0] {
            return Err(invalid(
                "K",
                format!("expected [[fx,0,cx],[0,fy,cy],[0,0,1]], got {k:?}"),
            ));
        }
        Ok(Self {
            fx: k[0][0],
            fy: k[1][1],
            cx: k[0][2],
            cy: k[1][2],
        })
    }

    /// Square pixels of focal length `focal` with the principal point at the image centre.
    pub fn centered(focal: f32, width: u32, height: u32) -> Self {
        Self {
            fx: focal,
            fy: focal,
            cx: width as f32 / 2.0,
            cy: height as f32 / 2.0,
        }
    }

    /// The row-major 3×3 matrix.
    pub fn matrix(&self) -> [[f32; 3]; 3] {
        [
            [self.fx, 0.0, self.cx],
            [0.0, self.fy, self.cy],
            [0.0, 0.0, 1.0],
        ]
    }
}

/// A pinhole camera: intrinsics, world-to-camera extrinsics and the image size.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Camera {
    /// Intrinsics in pixels.
    pub intrinsics: Intrinsics,
    /// Rigid world-to-camera transform (OpenCV axes: x right, y down, z forward).
    pub cam_from_world: Affine3A,
    /// Image width in pixels.
    pub width: u32,
    /// Image height in pixels.
    pub height: u32,
}

/// Camera and image, flattened for the kernels.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ViewParams {
    /// Row-major 3×4 world-to-camera `[R | t]`.
    pub view: [f32; 12],
    /// Focal length x, pixels.
    pub fx: f32,
    /// Focal length y, pixels.
    pub fy: f32,
    /// Principal point x, pixels.
    pub cx: f32,
    /// Principal point y, pixels.
    pub cy: f32,
    /// Image width.
    pub width: u32,
    /// Image height.
    pub height: u32,
}

impl Camera {
    /// The flattened form the kernels take: `[R | t]`, intrinsics and image size.
    pub fn view_params(&self) -> ViewParams {
        let k = self.intrinsics;
        ViewParams {
            view: self.view_matrix(),
            fx: k.fx,
            fy: k.fy,
            cx: k.cx,
            cy: k.cy,
            width: self.width,
            height: self.height,
        }
    }

    /// Builds and validates a camera. Fails on a non-positive or non-finite focal length, a zero
    /// image size, a non-finite principal point, or an extrinsic whose linear part is not a
    /// rotation (determinant 1, orthonormal to 1e-3).
    pub fn new(
        intrinsics: Intrinsics,
        cam_from_world: Affine3A,
        width: u32,
        height: u32,
    ) -> Result<Self> {
        let camera = Self {
            intrinsics,
            cam_from_world,
            width,
            height,
        };
        camera.validate()?;
        Ok(camera)
    }

    /// Builds a camera from a row-major `K` and a row-major 4×4 world-to-camera `E`.
    pub fn from_matrices(
        k: [[f32; 3]; 3],
        e: [[f32; 4]; 4],
        width: u32,
        height: u32,
    ) -> Result<Self> {
        if e.iter().flatten().any(|v| !v.is_finite()) {
            return Err(invalid("E", "non-finite entry"));
        }
        if e[3] != [0.0, 0.0, 0.0, 1.0] {
            return Err(invalid(
                "E",
                format!("last row must be [0,0,0,1], got {:?}", e[3]),
            ));
        }
        let rot = Mat3::from_cols(
            Vec3::new(e[0][0], e[1][0], e[2][0]),
            Vec3::new(e[0][1], e[1][1], e[2][1]),
            Vec3::new(e[0][2], e[1][2], e[2][2]),
        );
        let cam_from_world =
            Affine3A::from_mat3_translation(rot, Vec3::new(e[0][3], e[1][3], e[2][3]));
        Self::new(Intrinsics::from_matrix(k)?, cam_from_world, width, height)
    }

    /// A camera at `eye` looking at `target`, with image-up roughly along `up`.
    pub fn look_at(
        eye: Vec3,
        target: Vec3,
        up: Vec3,
        intrinsics: Intrinsics,
        width: u32,
        height: u32,
    ) -> Result<Self> {
        let forward = (target - eye).normalize_or_zero();
        let right = forward.cross(up).normalize_or_zero();
        if forward == Vec3::ZERO || right == Vec3::ZERO {
            return Err(invalid(
                "cam_from_world",
                "look_at with eye == target or up parallel to the view",
            ));
        }
        // OpenCV axes: y points down in the image.
        let down = forward.cross(right);
        let world_from_cam_rot = Mat3::from_cols(right, down, forward);
        let rot = world_from_cam_rot.transpose();
        let cam_from_world = Affine3A::from_mat3_translation(rot, -(rot * eye));
        Self::new(intrinsics, cam_from_world, width, height)
    }

    /// Folds a global body transform into the extrinsic: `E' = E · [R(rh) | th]`, with `rh` an
    /// axis-angle vector. Points then stay in the body frame (design.md §3.4).
    pub fn with_body_transform(&self, rh: Vec3, th: Vec3) -> Result<Self> {
        if !rh.is_finite() || !th.is_finite() {
            return Err(invalid("body_transform", "non-finite Rh or Th"));
        }
        let body = Affine3A::from_mat3_translation(crate::skeleton::rodrigues(rh), th);
        Self::new(
            self.intrinsics,
            self.cam_from_world * body,
            self.width,
            self.height,
        )
    }

    /// Checks the invariants documented on [`Camera::new`].
    pub fn validate(&self) -> Result<()> {
        let k = &self.intrinsics;
        for (name, v) in [("fx", k.fx), ("fy", k.fy)] {
            if !(v.is_finite() && v > 0.0) {
                return Err(invalid(
                    name,
                    format!("focal length must be finite and > 0, got {v}"),
                ));
            }
        }
        for (name, v) in [("cx", k.cx), ("cy", k.cy)] {
            if !v.is_finite() {
                return Err(invalid(
                    name,
                    format!("principal point must be finite, got {v}"),
                ));
            }
        }
        if self.width == 0 || self.height == 0 {
            return Err(invalid(
                "width/height",
                format!("image size must be > 0, got {}x{}", self.width, self.height),
            ));
        }
        let m = self.rotation();
        let t = self.cam_from_world.translation;
        if !(m.is_finite() && t.is_finite()) {
            return Err(invalid("cam_from_world", "non-finite entry"));
        }
        let ortho = (m * m.transpose() - Mat3A::IDENTITY)
            .to_cols_array()
            .iter()
            .fold(0.0f32, |a, v| a.max(v.abs()));
        let det = m.determinant();
        if !(ortho < 1e-3 && (det - 1.0).abs() < 1e-3) {
            return Err(invalid(
                "cam_from_world",
                format!(
                    "rotation part is not a rotation (|R·Rᵀ − I|max = {ortho:.2e}, det = {det:.4})"
                ),
            ));
        }
        Ok(())
    }

    /// The rotation part of the world-to-camera transform.
    pub fn rotation(&self) -> Mat3A {
        self.cam_from_world.matrix3
    }

    /// World point to camera coordinates (OpenCV axes).
    pub fn world_to_camera(&self, p: Vec3) -> Vec3 {
        self.cam_from_world.transform_point3(p)
    }

    /// Projects a world point to pixel coordinates (pixel `i` covers `[i, i+1)`), with its depth.
    /// Returns `None` for points at or behind the camera plane.
    #[allow(clippy::neg_cmp_op_on_partial_ord)] // worded so that a NaN depth fails the test
    pub fn project(&self, p: Vec3) -> Option<(Vec2, f32)> {
        let c = self.world_to_camera(p);
        if !(c.z > 0.0) {
            return None;
        }
        let k = &self.intrinsics;
        Some((
            Vec2::new(k.fx * c.x / c.z + k.cx, k.fy * c.y / c.z + k.cy),
            c.z,
        ))
    }

    /// `(tan(fovx/2), tan(fovy/2))` as the reference computes them: `W/(2fx)`, `H/(2fy)`.
    pub fn tan_half_fov(&self) -> (f32, f32) {
        let k = &self.intrinsics;
        (
            self.width as f32 / (2.0 * k.fx),
            self.height as f32 / (2.0 * k.fy),
        )
    }

    /// Camera centre in world coordinates.
    pub fn center(&self) -> Vec3 {
        let inv = self.cam_from_world.inverse();
        Vec3::from(inv.translation)
    }

    /// The camera's viewing direction (+z of the camera) in world coordinates.
    pub fn forward(&self) -> Vec3 {
        Vec3::from(self.rotation().transpose() * Vec3A::Z)
    }

    /// Row-major 3×4 world-to-camera matrix `[R | t]`, the layout the CPU kernels read.
    pub fn view_matrix(&self) -> [f32; 12] {
        let r = self.rotation();
        let t = self.cam_from_world.translation;
        [
            r.x_axis.x, r.y_axis.x, r.z_axis.x, t.x, //
            r.x_axis.y, r.y_axis.y, r.z_axis.y, t.y, //
            r.x_axis.z, r.y_axis.z, r.z_axis.z, t.z,
        ]
    }
}

fn invalid(field: &'static str, reason: impl Into<String>) -> RenderError {
    RenderError::InvalidCamera {
        field,
        reason: reason.into(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn intr() -> Intrinsics {
        Intrinsics {
            fx: 100.0,
            fy: 120.0,
            cx: 32.0,
            cy: 24.0,
        }
    }

    #[test]
    fn look_at_puts_target_at_principal_point() {
        let cam = Camera::look_at(
            Vec3::new(0.3, 0.2, 2.5),
            Vec3::new(0.3, 0.2, 0.0),
            Vec3::Y,
            intr(),
            64,
            48,
        )
        .unwrap();
        let (uv, z) = cam.project(Vec3::new(0.3, 0.2, 0.0)).unwrap();
        assert!((uv - Vec2::new(32.0, 24.0)).length() < 1e-4, "{uv}");
        assert!((z - 2.5).abs() < 1e-5);
        // World +y (up) must go to image up, i.e. smaller v.
        let (up, _) = cam.project(Vec3::new(0.3, 0.7, 0.0)).unwrap();
        assert!(up.y < 24.0);
        assert!((cam.center() - Vec3::new(0.3, 0.2, 2.5)).length() < 1e-5);
    }

    #[test]
    fn matrices_round_trip() {
        let cam = Camera::look_at(
            Vec3::new(1.0, 0.5, 2.0),
            Vec3::ZERO,
            Vec3::Y,
            intr(),
            64,
            48,
        )
        .unwrap();
        let v = cam.view_matrix();
        let e = [
            [v[0], v[1], v[2], v[3]],
            [v[4], v[5], v[6], v[7]],
            [v[8], v[9], v[10], v[11]],
            [0.0, 0.0, 0.0, 1.0],
        ];
        let again = Camera::from_matrices(intr().matrix(), e, 64, 48).unwrap();
        let p = Vec3::new(0.1, -0.2, 0.3);
        assert!((cam.world_to_camera(p) - again.world_to_camera(p)).length() < 1e-6);
    }

    #[test]
    fn degenerate_cameras_are_rejected_with_the_field_named() {
        let e = Affine3A::IDENTITY;
        let bad_f = Intrinsics { fx: 0.0, ..intr() };
        let err = Camera::new(bad_f, e, 8, 8).unwrap_err().to_string();
        assert!(err.contains("`fx`"), "{err}");
        let nan_c = Intrinsics {
            cy: f32::NAN,
            ..intr()
        };
        assert!(
            Camera::new(nan_c, e, 8, 8)
                .unwrap_err()
                .to_string()
                .contains("`cy`")
        );
        assert!(
            Camera::new(intr(), e, 0, 8)
                .unwrap_err()
                .to_string()
                .contains("image size")
        );
        let scaled = Affine3A::from_scale(Vec3::splat(2.0));
        assert!(
            Camera::new(intr(), scaled, 8, 8)
                .unwrap_err()
                .to_string()
                .contains("cam_from_world")
        );
        let skew = [[100.0, 1.0, 4.0], [0.0, 100.0, 4.0], [0.0, 0.0, 1.0]];
        assert!(Intrinsics::from_matrix(skew).is_err());
    }

    #[test]
    fn body_transform_is_folded_into_extrinsics() {
        let cam = Camera::look_at(
            Vec3::new(0.0, 0.0, 3.0),
            Vec3::ZERO,
            Vec3::Y,
            intr(),
            64,
            48,
        )
        .unwrap();
        let rh = Vec3::new(0.0, 0.7, 0.0);
        let th = Vec3::new(0.1, 0.2, -0.3);
        let folded = cam.with_body_transform(rh, th).unwrap();
        let p = Vec3::new(0.2, -0.1, 0.05);
        let moved = crate::skeleton::rodrigues(rh) * p + th;
        assert!((folded.world_to_camera(p) - cam.world_to_camera(moved)).length() < 1e-5);
    }
}
