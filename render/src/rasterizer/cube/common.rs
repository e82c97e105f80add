//! What the rasterizer's CubeCL stages share: tile geometry, the layouts of the per-Gaussian
//! records that pass from one stage to the next, and the alpha evaluation that the forward and
//! the backward blend with.
//!
//! Each kernel mirrors a piece of [`crate::rasterizer::cpu`] line by line (same formulas, same
//! evaluation order), so the two agree to rounding.
//!
//! Buffers are flat `f32`/`u32` slices of fixed-width records, one per Gaussian:
//! - `splats`: `[N, SPLAT_LANES]`, lanes `SPLAT_X ..= SPLAT_LOG_CUTOFF`: `x, y, conic A, B, C,
//!   opacity, depth, log_cutoff` (the CPU's `Splat2d`); read whole with [`load_splat`].
//! - `rects`: `[N, RECT_LANES]`, the tile rectangle `x0, y0, x1, y1` (`[x0, x1) × [y0, y1)`).
//! - `grad2d`: `[N, GRAD_LANES]`, lanes `GRAD_X ..= GRAD_DEPTH`: `x, y, conic A, B, C, opacity,
//!   r, g, b, depth` (the CPU's slot).
//!
//! The camera is not a buffer but a launch argument with named fields,
//! [`crate::cube::view::ViewArgs`].
//!
//! Guards test finiteness on the float's bits ([`crate::cube::float::finite`]), matching the
//! CPU's `is_finite` checks.

use burn_cubecl::cubecl;
use burn_cubecl::cubecl::prelude::*;

use super::super::cpu::{ALPHA_MAX, ALPHA_MIN, SMOOTH_HI, SMOOTH_LO, TILE};

/// Tile side in pixels (the CPU's `TILE`): the forward's cube is `TILE_SIDE × TILE_SIDE`.
pub(crate) const TILE_SIDE: u32 = 16;
const _: () = assert!(TILE_SIDE as usize == TILE);
/// Pixels per tile.
pub(crate) const TILE_PIXELS: u32 = TILE_SIDE * TILE_SIDE;

/// Floats per projected splat.
pub(crate) const SPLAT_LANES: usize = 8;
/// Splat lane: pixel x of the centre.
pub(crate) const SPLAT_X: usize = 0;
/// Splat lane: pixel y of the centre.
pub(crate) const SPLAT_Y: usize = 1;
/// Splat lane: conic (inverse 2D covariance) entry A, the `xx` term.
pub(crate) const SPLAT_CONIC_A: usize = 2;
/// Splat lane: conic entry B, the `xy` term.
pub(crate) const SPLAT_CONIC_B: usize = 3;
/// Splat lane: conic entry C, the `yy` term.
pub(crate) const SPLAT_CONIC_C: usize = 4;
/// Splat lane: opacity.
pub(crate) const SPLAT_OPACITY: usize = 5;
/// Splat lane: camera-space depth.
pub(crate) const SPLAT_DEPTH: usize = 6;
/// Splat lane: the power below which the splat contributes nothing.
pub(crate) const SPLAT_LOG_CUTOFF: usize = 7;

/// `u32`s per tile rectangle.
pub(crate) const RECT_LANES: usize = 4;
/// Rect lane: first tile column.
pub(crate) const RECT_X0: usize = 0;
/// Rect lane: first tile row.
pub(crate) const RECT_Y0: usize = 1;
/// Rect lane: one past the last tile column.
pub(crate) const RECT_X1: usize = 2;
/// Rect lane: one past the last tile row.
pub(crate) const RECT_Y1: usize = 3;

/// Floats per per-Gaussian 2D gradient.
pub(crate) const GRAD_LANES: usize = 10;
/// Gradient lane: splat x.
pub(crate) const GRAD_X: usize = 0;
/// Gradient lane: splat y.
pub(crate) const GRAD_Y: usize = 1;
/// Gradient lane: conic A.
pub(crate) const GRAD_CONIC_A: usize = 2;
/// Gradient lane: conic B.
pub(crate) const GRAD_CONIC_B: usize = 3;
/// Gradient lane: conic C.
pub(crate) const GRAD_CONIC_C: usize = 4;
/// Gradient lane: opacity.
pub(crate) const GRAD_OPACITY: usize = 5;
/// Gradient lane: red; green and blue follow.
pub(crate) const GRAD_COLOR: usize = 6;
/// Gradient lane: depth.
pub(crate) const GRAD_DEPTH: usize = 9;

/// Channels per pixel at most, and floats per blended feature: `r, g, b, alpha, depth`.
pub(crate) const FEATURE_LANES: usize = 5;
/// Colour channels, first in every feature and pixel.
pub(crate) const COLOR_CHANNELS: u32 = 3;
/// Channel index of alpha (the feature is 1).
pub(crate) const ALPHA_CHANNEL: u32 = 3;
/// Channel index of depth, present when the op renders 5 channels.
pub(crate) const DEPTH_CHANNEL: u32 = 4;

/// One projected splat, as stored in `splats` (see the module docs).
#[derive(CubeType, Clone, Copy)]
pub(crate) struct Splat {
    pub(crate) x: f32,
    pub(crate) y: f32,
    pub(crate) conic_a: f32,
    pub(crate) conic_b: f32,
    pub(crate) conic_c: f32,
    pub(crate) opacity: f32,
    pub(crate) depth: f32,
    pub(crate) log_cutoff: f32,
}

/// The splat of Gaussian `gid`.
#[cube]
pub(crate) fn load_splat(splats: &[f32], gid: u32) -> Splat {
    let s = SPLAT_LANES * gid as usize;
    Splat {
        x: splats[s + SPLAT_X],
        y: splats[s + SPLAT_Y],
        conic_a: splats[s + SPLAT_CONIC_A],
        conic_b: splats[s + SPLAT_CONIC_B],
        conic_c: splats[s + SPLAT_CONIC_C],
        opacity: splats[s + SPLAT_OPACITY],
        depth: splats[s + SPLAT_DEPTH],
        log_cutoff: splats[s + SPLAT_LOG_CUTOFF],
    }
}

/// Alpha of a splat at offset `(dx, dy)` and the factors the backward needs (`cpu::eval_alpha`).
#[derive(CubeType, Clone, Copy)]
pub(crate) struct AlphaEval {
    pub(crate) alpha: f32,
    /// d(final alpha)/d(o·G).
    pub(crate) dcap: f32,
    /// G itself.
    pub(crate) g: f32,
    /// Whether the pixel blends this splat at all.
    pub(crate) hit: bool,
}

/// See [`AlphaEval`]; `smooth` selects [`crate::rasterizer::AlphaCutoff::Smooth`].
#[cube]
#[allow(clippy::too_many_arguments)]
pub(crate) fn eval_alpha(
    qa: f32,
    qb: f32,
    qc: f32,
    opacity: f32,
    log_cutoff: f32,
    dx: f32,
    dy: f32,
    #[comptime] smooth: bool,
) -> AlphaEval {
    let power = -0.5f32 * (qa * dx * dx + qc * dy * dy) - qb * dx * dy;
    let mut alpha = 0.0f32;
    let mut dcap_out = 0.0f32;
    let mut g_out = 0.0f32;
    let mut hit = false;
    if !(power > 0.0 || power < log_cutoff) {
        let g = power.exp();
        let raw = opacity * g;
        let mut capped = raw;
        let mut dcap = 1.0f32;
        if raw > ALPHA_MAX {
            capped = ALPHA_MAX;
            dcap = 0.0;
        }
        if smooth {
            if capped > SMOOTH_LO {
                let width = SMOOTH_HI - SMOOTH_LO;
                let u = min((capped - SMOOTH_LO) / width, 1.0f32);
                let w = u * u * (3.0 - 2.0 * u);
                let dw = 6.0 * u * (1.0 - u) / width;
                alpha = capped * w;
                dcap_out = dcap * (w + capped * dw);
                g_out = g;
                hit = true;
            }
        } else if capped >= ALPHA_MIN {
            alpha = capped;
            dcap_out = dcap;
            g_out = g;
            hit = true;
        }
    }
    AlphaEval {
        alpha,
        dcap: dcap_out,
        g: g_out,
        hit,
    }
}
