//! Stage 1 of the forward: **project** every Gaussian to a screen-space splat (`cpu::project_one`).
//!
//! One thread per Gaussian: view transform, culling, EWA covariance (with the FOV clamp and
//! the dilation), conic, radius and tile rectangle. Each thread writes its splat record, its
//! tile rectangle, the number of tiles it touches (0 when culled) and a depth sort key: the
//! depth's bit pattern, which orders like the positive float; culled Gaussians get
//! [`CULLED_KEY`] and sort last.
//!
//! [`ewa`] and [`sym_row`] are shared with the projection's backward
//! ([`super::project_backward`]).

// `!(a <= b)` is the deliberate NaN-failing guard form (as in `cpu.rs`); `(a + b - 1) / b` stays
// spelled out because `#[cube]` traces the arithmetic operators, not `u32::div_ceil`.
#![allow(clippy::neg_cmp_op_on_partial_ord, clippy::manual_div_ceil)]

use burn_cubecl::cubecl;
use burn_cubecl::cubecl::prelude::*;

use super::common::{
    RECT_LANES, RECT_X0, RECT_X1, RECT_Y0, RECT_Y1, SPLAT_CONIC_A, SPLAT_CONIC_B, SPLAT_CONIC_C,
    SPLAT_DEPTH, SPLAT_LANES, SPLAT_LOG_CUTOFF, SPLAT_OPACITY, SPLAT_X, SPLAT_Y, TILE_SIDE,
};
use crate::cube::float::finite;
use crate::cube::view::{ViewArgs, camera_of};
use crate::rasterizer::cpu::{ALPHA_MIN, DILATION, FOV_CLAMP, NEAR_Z, SMOOTH_LO};

/// Key of a culled Gaussian in the depth sort: sorts after every positive float's bits.
pub(crate) const CULLED_KEY: u32 = 0xffff_ffff;

/// The dilated 2D covariance and EWA Jacobian of a Gaussian at view-space `t`.
#[derive(CubeType, Clone, Copy)]
pub(crate) struct Ewa {
    /// Rows of `T = J·R`.
    pub(crate) t0x: f32,
    pub(crate) t0y: f32,
    pub(crate) t0z: f32,
    pub(crate) t1x: f32,
    pub(crate) t1y: f32,
    pub(crate) t1z: f32,
    /// Whether x/z and y/z were clamped.
    pub(crate) clamped_x: bool,
    pub(crate) clamped_y: bool,
}

/// The EWA Jacobian rows `T = J·R` at view-space `(tx, ty, tz)`, with the FOV clamp.
#[cube]
pub(crate) fn ewa(view: &ViewArgs, tx: f32, ty: f32, tz: f32) -> Ewa {
    let fx = view.fx;
    let fy = view.fy;
    let limx = FOV_CLAMP * f32::cast_from(view.width) / (2.0 * fx);
    let limy = FOV_CLAMP * f32::cast_from(view.height) / (2.0 * fy);
    let xz = tx / tz;
    let yz = ty / tz;
    let clamped_x = !(xz.abs() <= limx);
    let clamped_y = !(yz.abs() <= limy);
    let txc = min(max(xz, -limx), limx) * tz;
    let tyc = min(max(yz, -limy), limy) * tz;
    let z2 = tz * tz;
    let j00 = fx / tz;
    let j02 = -fx * txc / z2;
    let j11 = fy / tz;
    let j12 = -fy * tyc / z2;
    Ewa {
        t0x: j00 * view.r00 + j02 * view.r20,
        t0y: j00 * view.r01 + j02 * view.r21,
        t0z: j00 * view.r02 + j02 * view.r22,
        t1x: j11 * view.r10 + j12 * view.r20,
        t1y: j11 * view.r11 + j12 * view.r21,
        t1z: j11 * view.r12 + j12 * view.r22,
        clamped_x,
        clamped_y,
    }
}

/// Floats per covariance: the symmetric Σ as `(xx, xy, xz, yy, yz, zz)`.
pub(crate) const COV_LANES: usize = 6;

/// `Σ·v` for the symmetric Σ stored as (xx, xy, xz, yy, yz, zz) at `covs[base..]`; one lane.
#[cube]
pub(crate) fn sym_row(covs: &[f32], base: usize, row: u32, vx: f32, vy: f32, vz: f32) -> f32 {
    let c0 = covs[base];
    let c1 = covs[base + 1];
    let c2 = covs[base + 2];
    let c3 = covs[base + 3];
    let c4 = covs[base + 4];
    let c5 = covs[base + 5];
    let mut out = c2 * vx + c4 * vy + c5 * vz;
    if row == 0u32 {
        out = c0 * vx + c1 * vy + c2 * vz;
    } else if row == 1u32 {
        out = c1 * vx + c3 * vy + c4 * vz;
    }
    out
}

/// One thread per Gaussian: view transform, culling, EWA covariance, conic, radius and tile
/// rectangle (`cpu::project_one`). Culled Gaussians get zero tiles and `CULLED_KEY`.
#[cube(launch)]
#[allow(clippy::too_many_arguments)]
pub(crate) fn project_kernel(
    means: &[f32],
    covs: &[f32],
    colors: &[f32],
    opacities: &[f32],
    cameras: &[f32],
    splats: &mut [f32],
    rects: &mut [u32],
    tile_counts: &mut [u32],
    depth_keys: &mut [u32],
    num_gaussians: u32,
    views: u32,
    #[comptime] smooth: bool,
) {
    // One thread per splat: Gaussian `g` seen in view `k`, at `k·num_gaussians + g` of the
    // outputs.
    let splat = ABSOLUTE_POS as u32;
    if splat < num_gaussians * views {
        let g = (splat % num_gaussians) as usize;
        let view = camera_of(cameras, splat / num_gaussians);
        let mut visible = true;
        let cr = colors[3 * g];
        let cg = colors[3 * g + 1];
        let cb = colors[3 * g + 2];
        if !(finite(cr) && finite(cg) && finite(cb)) {
            visible = false;
        }
        let mx = means[3 * g];
        let my = means[3 * g + 1];
        let mz = means[3 * g + 2];
        let tx = view.camera_x(mx, my, mz);
        let ty = view.camera_y(mx, my, mz);
        let tz = view.camera_z(mx, my, mz);
        if !(finite(tz) && finite(tx) && finite(ty) && tz > NEAR_Z) {
            visible = false;
        }
        let thr = if smooth { SMOOTH_LO } else { ALPHA_MIN };
        let opacity = opacities[g];
        if !(finite(opacity) && opacity > thr) {
            visible = false;
        }
        // Keep the arithmetic below on finite values even for culled Gaussians.
        let sx = select(visible, tx, 0.0f32);
        let sy = select(visible, ty, 0.0f32);
        let sz = select(visible, tz, 1.0f32);
        let e = ewa(&view, sx, sy, sz);
        let base = COV_LANES * g;
        let s0x = sym_row(covs, base, 0u32, e.t0x, e.t0y, e.t0z);
        let s0y = sym_row(covs, base, 1u32, e.t0x, e.t0y, e.t0z);
        let s0z = sym_row(covs, base, 2u32, e.t0x, e.t0y, e.t0z);
        let s1x = sym_row(covs, base, 0u32, e.t1x, e.t1y, e.t1z);
        let s1y = sym_row(covs, base, 1u32, e.t1x, e.t1y, e.t1z);
        let s1z = sym_row(covs, base, 2u32, e.t1x, e.t1y, e.t1z);
        let a = e.t0x * s0x + e.t0y * s0y + e.t0z * s0z + DILATION;
        let b = e.t0x * s1x + e.t0y * s1y + e.t0z * s1z;
        let c = e.t1x * s1x + e.t1y * s1y + e.t1z * s1z + DILATION;
        let det = a * c - b * b;
        if !(finite(det) && finite(a) && det > 0.0 && a > 0.0) {
            visible = false;
        }
        let qa = c / det;
        let qb = -b / det;
        let qc = a / det;
        let mid = 0.5 * (a + c);
        let lambda_max = mid + max(mid * mid - det, 0.1f32).sqrt();
        let k2 = 2.0 * (opacity / thr).ln();
        let mut radius = (3.0 * lambda_max.sqrt()).ceil();
        if smooth {
            radius = (k2 * lambda_max).sqrt().ceil();
        }
        let x = view.fx * sx / sz + view.cx - 0.5;
        let y = view.fy * sy / sz + view.cy - 0.5;
        let log_cutoff = -0.5f32 * k2;
        let inv_det = 1.0 / (qa * qc - qb * qb);
        let kk = -2.0f32 * log_cutoff;
        let ex = (kk * qc * inv_det).sqrt() * 1.001 + 1e-3;
        let ey = (kk * qa * inv_det).sqrt() * 1.001 + 1e-3;
        if !(finite(x) && finite(y) && finite(radius) && finite(ex) && finite(ey)) {
            visible = false;
        }
        let gx = f32::cast_from((view.width + TILE_SIDE - 1) / TILE_SIDE);
        let gy = f32::cast_from((view.height + TILE_SIDE - 1) / TILE_SIDE);
        let t = f32::cast_from(TILE_SIDE);
        // The clamps also make the casts below well defined for culled (possibly NaN) values.
        let x0 = u32::cast_from(min(max(((x - radius) / t).floor(), 0.0f32), gx));
        let y0 = u32::cast_from(min(max(((y - radius) / t).floor(), 0.0f32), gy));
        let x1 = u32::cast_from(min(max(((x + radius + t - 1.0) / t).floor(), 0.0f32), gx));
        let y1 = u32::cast_from(min(max(((y + radius + t - 1.0) / t).floor(), 0.0f32), gy));
        if !(x1 > x0 && y1 > y0) {
            visible = false;
        }
        let out = splat as usize;
        let r = RECT_LANES * out;
        let s = SPLAT_LANES * out;
        if visible {
            splats[s + SPLAT_X] = x;
            splats[s + SPLAT_Y] = y;
            splats[s + SPLAT_CONIC_A] = qa;
            splats[s + SPLAT_CONIC_B] = qb;
            splats[s + SPLAT_CONIC_C] = qc;
            splats[s + SPLAT_OPACITY] = opacity;
            splats[s + SPLAT_DEPTH] = tz;
            splats[s + SPLAT_LOG_CUTOFF] = log_cutoff;
            rects[r + RECT_X0] = x0;
            rects[r + RECT_Y0] = y0;
            rects[r + RECT_X1] = x1;
            rects[r + RECT_Y1] = y1;
            tile_counts[out] = (x1 - x0) * (y1 - y0);
            // Depth is > NEAR_Z > 0, so its bit pattern orders like the float.
            depth_keys[out] = u32::reinterpret(tz);
        } else {
            for k in 0..SPLAT_LANES {
                splats[s + k] = 0.0;
            }
            for k in 0..RECT_LANES {
                rects[r + k] = 0u32;
            }
            tile_counts[out] = 0u32;
            depth_keys[out] = CULLED_KEY;
        }
    }
}
