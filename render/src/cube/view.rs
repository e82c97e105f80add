//! The camera record of the CubeCL kernels: world-to-camera `[R | t]`, pinhole intrinsics and
//! image size, the GPU twin of [`crate::camera::ViewParams`].
//!
//! [`ViewArgs`] is a `#[derive(CubeLaunch)]` struct: the host passes it by value
//! ([`view_args`] builds its `ViewArgsLaunch`), CubeCL registers each field as a launch scalar,
//! and kernels read named fields (`view.fx`, `view.r12`) instead of offsets into a flat
//! 16-float buffer. The values reach the kernel bit for bit, exactly as a buffer read would
//! give them.
//!
//! The methods keep the expressions of the kernels they came from, term for term and in the
//! same order, so that results do not move by a rounding.

use burn_cubecl::cubecl;
use burn_cubecl::cubecl::prelude::*;

use crate::camera::ViewParams;

/// World-to-camera rotation `R` (`r{row}{col}`) and translation `t`, focal lengths and principal
/// point in pixels, and the image size.
#[derive(CubeLaunch, CubeType)]
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

/// The launch argument for `params` (its row-major `[R | t]` read row by row).
pub(crate) fn view_args(params: &ViewParams) -> ViewArgsLaunch {
    let m = &params.view;
    ViewArgsLaunch::new(
        m[0],
        m[1],
        m[2],
        m[3],
        m[4],
        m[5],
        m[6],
        m[7],
        m[8],
        m[9],
        m[10],
        m[11],
        params.fx,
        params.fy,
        params.cx,
        params.cy,
        params.width,
        params.height,
    )
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
