//! The camera record of the CubeCL kernels: world-to-camera `[R | t]`, pinhole intrinsics and
//! image size, the GPU twin of [`crate::camera::ViewParams`].
//!
//! The host uploads the cameras of a call as a table, one row of [`CAMERA_FLOATS`] per view
//! ([`camera_table`]), and a kernel builds the record of the view it works on from it
//! ([`camera_of`]), then reads named fields (`view.fx`, `view.r12`) instead of offsets into the
//! row. One kernel then serves one view or many (the rasterizer and the triangle-ID visibility
//! render every view of a call in one launch per stage). The values reach the kernel bit for
//! bit.
//!
//! The methods keep the expressions of the kernels they came from, term for term and in the
//! same order, so that results do not move by a rounding.

use burn_cubecl::cubecl;
use burn_cubecl::cubecl::prelude::*;

use burn_cubecl::cubecl::server::Handle;

use crate::camera::ViewParams;
use crate::cube::host::{ComputeClient, u32_bytes};

/// World-to-camera rotation `R` (`r{row}{col}`) and translation `t`, focal lengths and principal
/// point in pixels, and the image size.
#[derive(CubeType)]
pub(crate) struct ViewArgs {
    pub(crate) r00: f32,
    pub(crate) r01: f32,
    pub(crate) r02: f32,
    pub(crate) t0: f32,
    pub(crate) r10: f32,
    pub(crate) r11: f32,
    pub(crate) r12: f32,
    pub(crate) t1: f32,
    pub(crate) r20: f32,
    pub(crate) r21: f32,
    pub(crate) r22: f32,
    pub(crate) t2: f32,
    pub(crate) fx: f32,
    pub(crate) fy: f32,
    pub(crate) cx: f32,
    pub(crate) cy: f32,
    pub(crate) width: u32,
    pub(crate) height: u32,
}

#[cube]
impl ViewArgs {
    /// Camera-space `x` of the world point `(x, y, z)`: row 0 of `[R | t]`.
    pub(crate) fn camera_x(&self, x: f32, y: f32, z: f32) -> f32 {
        self.r00 * x + self.r01 * y + self.r02 * z + self.t0
    }

    /// Camera-space `y`: row 1 of `[R | t]`.
    pub(crate) fn camera_y(&self, x: f32, y: f32, z: f32) -> f32 {
        self.r10 * x + self.r11 * y + self.r12 * z + self.t1
    }

    /// Camera-space `z` (depth): row 2 of `[R | t]`.
    pub(crate) fn camera_z(&self, x: f32, y: f32, z: f32) -> f32 {
        self.r20 * x + self.r21 * y + self.r22 * z + self.t2
    }

    /// `R[row][col]` for a column known only at run time (a loop index).
    pub(crate) fn rotation(&self, #[comptime] row: u32, col: u32) -> f32 {
        if row == 0u32 {
            select(
                col == 0u32,
                self.r00,
                select(col == 1u32, self.r01, self.r02),
            )
        } else if row == 1u32 {
            select(
                col == 0u32,
                self.r10,
                select(col == 1u32, self.r11, self.r12),
            )
        } else {
            select(
                col == 0u32,
                self.r20,
                select(col == 1u32, self.r21, self.r22),
            )
        }
    }
}

/// Floats per camera in a camera table ([`camera_table`]): `[R | t]` row by row, `fx`, `fy`,
/// `cx`, `cy`, width, height. The kernels that see several views at once read their cameras
/// from such a table ([`camera_of`]) rather than from launch scalars.
pub(crate) const CAMERA_FLOATS: usize = 18;

/// Camera `view` of a camera table, as the kernels' camera record.
#[cube]
pub(crate) fn camera_of(cameras: &[f32], view: u32) -> ViewArgs {
    let b = view as usize * CAMERA_FLOATS;
    ViewArgs {
        r00: cameras[b],
        r01: cameras[b + 1],
        r02: cameras[b + 2],
        t0: cameras[b + 3],
        r10: cameras[b + 4],
        r11: cameras[b + 5],
        r12: cameras[b + 6],
        t1: cameras[b + 7],
        r20: cameras[b + 8],
        r21: cameras[b + 9],
        r22: cameras[b + 10],
        t2: cameras[b + 11],
        fx: cameras[b + 12],
        fy: cameras[b + 13],
        cx: cameras[b + 14],
        cy: cameras[b + 15],
        width: u32::cast_from(cameras[b + 16]),
        height: u32::cast_from(cameras[b + 17]),
    }
}

/// `views` as the table [`camera_of`] reads, uploaded (image sizes are below 2²⁴, exact in
/// `f32`).
pub(crate) fn camera_table(client: &ComputeClient, views: &[ViewParams]) -> Handle {
    let mut bits = Vec::with_capacity(views.len() * CAMERA_FLOATS);
    for params in views {
        bits.extend(params.view.map(f32::to_bits));
        bits.extend([params.fx, params.fy, params.cx, params.cy].map(f32::to_bits));
        bits.extend([params.width as f32, params.height as f32].map(f32::to_bits));
    }
    client.create_from_slice(&u32_bytes(&bits))
}
