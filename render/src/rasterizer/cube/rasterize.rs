//! Stage 7 of the forward: **rasterize**, front-to-back alpha blending per tile
//! (`cpu::rasterize_tile`).
//!
//! One `TILE_SIDE × TILE_SIDE` cube per tile, one thread per pixel. The tile's list is consumed
//! in batches of [`FWD_BATCH`] splats that the threads load together into shared memory, one
//! splat per thread; each pixel blends front to back and stops at `T < T_MIN`; the whole tile
//! stops early once every pixel has (a shared counter read with a uniform load, so the loop exit
//! is provably uniform for WGSL's barrier rules). Also writes the final transmittance and the
//! last contributor per pixel, which the backward starts from.

// `(a + b - 1) / b` stays spelled out because `#[cube]` traces the arithmetic operators, not
// `u32::div_ceil`.
#![allow(clippy::manual_div_ceil)]

use burn_cubecl::cubecl;
use burn_cubecl::cubecl::prelude::*;

use super::common::{
    ALPHA_CHANNEL, DEPTH_CHANNEL, FEATURE_LANES, SPLAT_CONIC_A, SPLAT_CONIC_B, SPLAT_CONIC_C,
    SPLAT_DEPTH, SPLAT_LANES, SPLAT_LOG_CUTOFF, SPLAT_OPACITY, SPLAT_X, SPLAT_Y, TILE_PIXELS,
    TILE_SIDE, eval_alpha,
};
use crate::rasterizer::cpu::T_MIN;

/// Splats per shared-memory batch: one per thread of the tile's cube.
pub(crate) const FWD_BATCH: u32 = TILE_PIXELS;
const BATCH_LEN: usize = FWD_BATCH as usize;
/// Floats per batch entry in `batch_xy`: the splat centre.
const XY_LANES: usize = 2;
/// Floats per batch entry in `batch_conic`: conic A, B, C.
const CONIC_LANES: usize = 3;
/// Floats per batch entry in `batch_feature`: r, g, b, then depth at [`BATCH_DEPTH`].
const BATCH_FEATURE_LANES: usize = 4;
/// Lane of the depth in a `batch_feature` entry.
const BATCH_DEPTH: usize = 3;
/// Shared-memory lengths of the batch arrays.
const SHARED_XY_LEN: usize = XY_LANES * BATCH_LEN;
const SHARED_CONIC_LEN: usize = CONIC_LANES * BATCH_LEN;
const SHARED_FEATURE_LEN: usize = BATCH_FEATURE_LANES * BATCH_LEN;

/// See the module docs. `channels` is 4 (RGBA) or 5 (RGBA and depth).
#[cube(launch)]
#[allow(clippy::too_many_arguments)]
pub(crate) fn rasterize_kernel(
    splats: &[f32],
    colors: &[f32],
    gid_from_isect: &[u32],
    tile_offsets: &[u32],
    image: &mut [f32],
    final_t: &mut [f32],
    last_contrib: &mut [u32],
    width: u32,
    height: u32,
    tiles_x: u32,
    num_gaussians: u32,
    #[comptime] channels: u32,
    #[comptime] smooth: bool,
) {
    // One cube per tile of every view: view `CUBE_POS_Z`'s tiles follow the views before it.
    let view = CUBE_POS_Z;
    let tile = view * tiles_x * CUBE_COUNT_Y + CUBE_POS_Y * tiles_x + CUBE_POS_X;
    let first_pixel_of_view = view * width * height;
    let px = CUBE_POS_X * TILE_SIDE + UNIT_POS_X;
    let py = CUBE_POS_Y * TILE_SIDE + UNIT_POS_Y;
    let lane = UNIT_POS;
    let inside = px < width && py < height;

    // The tile's `[start, end)` in `gid_from_isect`, and how many pixels have finished.
    let mut range = Shared::<[u32]>::new_slice(2usize);
    let finished = Shared::<[Atomic<u32>]>::new_slice(1usize);
    let mut batch_xy = Shared::<[f32]>::new_slice(SHARED_XY_LEN);
    let mut batch_conic = Shared::<[f32]>::new_slice(SHARED_CONIC_LEN);
    let mut batch_opacity = Shared::<[f32]>::new_slice(BATCH_LEN);
    let mut batch_cutoff = Shared::<[f32]>::new_slice(BATCH_LEN);
    let mut batch_feature = Shared::<[f32]>::new_slice(SHARED_FEATURE_LEN);
    if lane == 0u32 {
        range[0] = tile_offsets[tile as usize];
        range[1] = tile_offsets[(tile + 1u32) as usize];
        finished[0].store(0u32);
    }
    let start = workgroup_uniform_load(&range[0]);
    let end = workgroup_uniform_load(&range[1]);

    let fpx = f32::cast_from(px);
    let fpy = f32::cast_from(py);
    let mut trans = 1.0f32;
    let mut acc = Array::<f32>::new(FEATURE_LANES);
    for ch in 0..FEATURE_LANES {
        acc[ch] = 0.0;
    }
    let mut last = 0u32;
    let mut done = !inside;
    if done {
        finished[0].fetch_add(1u32);
    }

    let num_batches = (end - start + FWD_BATCH - 1u32) / FWD_BATCH;
    for batch in 0..num_batches {
        // The uniform load is also the barrier that keeps this batch's loads from overwriting
        // splats a slower thread is still blending.
        let done_count = workgroup_uniform_load_atomic(&finished[0]);
        if done_count >= TILE_PIXELS {
            break;
        }
        let batch_start = start + batch * FWD_BATCH;
        let at = batch_start + lane;
        if at < end {
            let gid = gid_from_isect[at as usize];
            let s = SPLAT_LANES * gid as usize;
            let l = lane as usize;
            batch_xy[XY_LANES * l] = splats[s + SPLAT_X];
            batch_xy[XY_LANES * l + 1] = splats[s + SPLAT_Y];
            batch_conic[CONIC_LANES * l] = splats[s + SPLAT_CONIC_A];
            batch_conic[CONIC_LANES * l + 1] = splats[s + SPLAT_CONIC_B];
            batch_conic[CONIC_LANES * l + 2] = splats[s + SPLAT_CONIC_C];
            batch_opacity[l] = splats[s + SPLAT_OPACITY];
            batch_cutoff[l] = splats[s + SPLAT_LOG_CUTOFF];
            // Splats are per (view, Gaussian); colours per Gaussian.
            let g = gid % num_gaussians;
            batch_feature[BATCH_FEATURE_LANES * l] = colors[(3 * g) as usize];
            batch_feature[BATCH_FEATURE_LANES * l + 1] = colors[(3 * g + 1) as usize];
            batch_feature[BATCH_FEATURE_LANES * l + 2] = colors[(3 * g + 2) as usize];
            batch_feature[BATCH_FEATURE_LANES * l + BATCH_DEPTH] = splats[s + SPLAT_DEPTH];
        }
        sync_cube();
        let batch_len = min(FWD_BATCH, end - batch_start);
        for j in 0..batch_len {
            if done {
                break;
            }
            let k = j as usize;
            let e = eval_alpha(
                batch_conic[CONIC_LANES * k],
                batch_conic[CONIC_LANES * k + 1],
                batch_conic[CONIC_LANES * k + 2],
                batch_opacity[k],
                batch_cutoff[k],
                batch_xy[XY_LANES * k] - fpx,
                batch_xy[XY_LANES * k + 1] - fpy,
                smooth,
            );
            if e.hit {
                let t_next = trans * (1.0 - e.alpha);
                if t_next < T_MIN {
                    done = true;
                    finished[0].fetch_add(1u32);
                } else {
                    for ch in 0..channels {
                        // Colour from the batch, 1 for alpha, depth from the batch.
                        let mut f = 1.0f32;
                        if ch < ALPHA_CHANNEL {
                            f = batch_feature[BATCH_FEATURE_LANES * k + ch as usize];
                        } else if ch == DEPTH_CHANNEL {
                            f = batch_feature[BATCH_FEATURE_LANES * k + BATCH_DEPTH];
                        }
                        acc[ch as usize] += f * e.alpha * trans;
                    }
                    trans = t_next;
                    last = batch * FWD_BATCH + j + 1u32;
                }
            }
        }
    }

    if inside {
        let pix = first_pixel_of_view + py * width + px;
        for ch in 0..channels {
            image[(pix * channels + ch) as usize] = acc[ch as usize];
        }
        final_t[pix as usize] = trans;
        last_contrib[pix as usize] = last;
    }
}
