//! Backward of stage 7, **rasterize backward**: the blend replayed back to front per tile
//! (`cpu::backward_tile`), giving dense per-Gaussian 2D gradients (`grad2d`, see
//! [`super::common`]) that [`super::project_backward`] then chains to the 3D inputs.
//!
//! One [`BWD_BATCH`]-thread cube per tile and pixel group, one thread per splat, and one atomic
//! add per gradient component per batch, into `grad2d`: native float atomics where the runtime
//! has them, an atomic-exchange emulation otherwise ([`crate::cube::atomic`]). Nothing is
//! recomputed: the kernel starts from the forward's final transmittance and last contributor per
//! pixel.
//!
//! **Pixel groups.** Pixels are independent in the backward: each one replays its own splats.
//! A tile's pixels can therefore be split into groups of [`BWD_BATCH`]·k row-major pixels, each
//! group a cube of its own that sums its splats' gradients over its pixels only and adds them
//! into `grad2d` as a whole tile would. A cube's sweep over a batch takes `group + 31` barrier
//! steps instead of `256 + 31`, and there are as many times more cubes, for as many times more
//! atomic adds. On an H200 the most groups ([`BWD_PIXEL_GROUPS`], eight 32-pixel groups) were the
//! fastest at every size measured, from a 96² image (36 tiles: one cube per tile left the card
//! nearly idle) to 1024² (backward 36.4 → 9.8 ms; BENCHMARKS.md, "On a GPU (NVIDIA H200,
//! 2026-11-28, 954c62a → 6ad3593)").

// `(a + b - 1) / b` stays spelled out because `#[cube]` traces the arithmetic operators, not
// `u32::div_ceil`.
#![allow(clippy::manual_div_ceil)]

use burn_cubecl::cubecl;
use burn_cubecl::cubecl::prelude::*;

use crate::cube::atomic::AtomicAddF32;

use super::common::{
    ALPHA_CHANNEL, COLOR_CHANNELS, DEPTH_CHANNEL, FEATURE_LANES, GRAD_COLOR, GRAD_CONIC_A,
    GRAD_CONIC_B, GRAD_CONIC_C, GRAD_DEPTH, GRAD_LANES, GRAD_OPACITY, GRAD_X, GRAD_Y, TILE_PIXELS,
    TILE_SIDE, eval_alpha, load_splat,
};

/// Splats per backward batch: the backward's cube size, one thread per splat.
pub(crate) const BWD_BATCH: u32 = 32;
/// Pixel groups per tile: the most there can be (a group is a whole number of batch-wide
/// rounds of pixels), and the fastest on an H200 at every image size measured (module docs).
/// Tests and benchmarks force the smaller powers of two (`force_backward_pixel_groups`).
pub(crate) const BWD_PIXEL_GROUPS: u32 = TILE_PIXELS / BWD_BATCH;
/// Lane of the depth channel in a per-pixel `FEATURE_LANES` group.
const DEPTH_LANE: usize = DEPTH_CHANNEL as usize;

/// The Gaussian's feature in channel `ch`: `[r, g, b, 1, depth]`.
#[cube]
fn feature(colors: &[f32], gid: u32, depth: f32, ch: u32) -> f32 {
    let mut f = depth;
    if ch < COLOR_CHANNELS {
        f = colors[(3 * gid + ch) as usize];
    } else if ch == ALPHA_CHANNEL {
        f = 1.0;
    }
    f
}

/// Backward of the blend, one 32-thread cube per tile and pixel group, one thread per splat.
///
/// The cube's pixels are the tile's `group_pixels` row-major pixels from
/// `CUBE_POS_Z · group_pixels` (the whole tile when `group_pixels` is [`TILE_PIXELS`]). The
/// tile's list is replayed back to front in batches of 32 splats, from the largest last
/// contributor over those pixels, thread `t` holding the `t`-th splat from the back of the batch
/// in registers. Per-pixel state (transmittance, colour of everything behind, `dL/dpixel`, last
/// contributor) lives in shared memory. Work follows a diagonal: at step `s` thread `t` handles
/// pixel `s − t`, so every pixel meets the batch's splats strictly back to front (thread 0
/// first) and no two threads touch one pixel in one step. Each thread sums its splat's gradient
/// over the group's pixels in registers (in row-major pixel order, as the CPU does over a tile)
/// and then does one atomic add per component into `grad2d`.
///
/// Generic over the slot type `A` (see [`AtomicAddF32`]): `f32` where the runtime has float
/// atomic add, `u32` (exchange emulation) otherwise. A type parameter rather than a comptime flag
/// because the buffer's declared type itself (`array<atomic<f32>>`) is invalid where float
/// atomics are missing, used or not.
#[cube(launch)]
#[allow(clippy::too_many_arguments)]
pub(crate) fn rasterize_backward_kernel<A: AtomicAddF32>(
    splats: &[f32],
    colors: &[f32],
    gid_from_isect: &[u32],
    tile_offsets: &[u32],
    final_t: &[f32],
    last_contrib: &[u32],
    d_image: &[f32],
    grad2d: &[Atomic<A>],
    width: u32,
    height: u32,
    tiles_x: u32,
    num_gaussians: u32,
    #[comptime] channels: u32,
    #[comptime] smooth: bool,
    #[comptime] group_pixels: u32,
) {
    // `CUBE_POS_Z` counts the pixel groups of view 0's tile, then view 1's, …
    let groups = comptime!(TILE_PIXELS / group_pixels);
    let view = CUBE_POS_Z / groups;
    let tile = view * tiles_x * CUBE_COUNT_Y + CUBE_POS_Y * tiles_x + CUBE_POS_X;
    let first_pixel_of_view = view * width * height;
    let x0 = CUBE_POS_X * TILE_SIDE;
    let y0 = CUBE_POS_Y * TILE_SIDE;
    let first = (CUBE_POS_Z % groups) * group_pixels;
    let lane = UNIT_POS;
    let group_len = comptime!(group_pixels as usize);

    // The tile's start in `gid_from_isect`, and the largest last contributor over the group's
    // pixels. Per-pixel arrays are indexed by the pixel's place `q` in the group.
    let mut range = Shared::<[u32]>::new_slice(1usize);
    let max_last = Shared::<[Atomic<u32>]>::new_slice(1usize);
    let mut trans = Shared::<[f32]>::new_slice(group_len);
    let mut behind = Shared::<[f32]>::new_slice(comptime!(FEATURE_LANES * group_len));
    let mut d_pix = Shared::<[f32]>::new_slice(comptime!(FEATURE_LANES * group_len));
    let mut last = Shared::<[u32]>::new_slice(group_len);
    if lane == 0u32 {
        range[0] = tile_offsets[tile as usize];
        max_last[0].store(0u32);
    }
    sync_cube();
    let mut local_max = 0u32;
    for r in 0..group_pixels / BWD_BATCH {
        let q = r * BWD_BATCH + lane;
        let p = first + q;
        let px = x0 + p % TILE_SIDE;
        let py = y0 + p / TILE_SIDE;
        let pu = q as usize;
        for ch in 0..FEATURE_LANES {
            behind[FEATURE_LANES * pu + ch] = 0.0;
            d_pix[FEATURE_LANES * pu + ch] = 0.0;
        }
        if px < width && py < height {
            let pix = first_pixel_of_view + py * width + px;
            trans[pu] = final_t[pix as usize];
            last[pu] = last_contrib[pix as usize];
            for ch in 0..channels {
                d_pix[FEATURE_LANES * pu + ch as usize] = d_image[(pix * channels + ch) as usize];
            }
        } else {
            trans[pu] = 1.0;
            last[pu] = 0u32;
        }
        local_max = max(local_max, last[pu]);
    }
    max_last[0].fetch_max(local_max);
    let start = workgroup_uniform_load(&range[0]);
    let count = workgroup_uniform_load_atomic(&max_last[0]);

    let num_batches = (count + BWD_BATCH - 1u32) / BWD_BATCH;
    for batch in 0..num_batches {
        // Entries [top − 32, top) of the tile list, thread 0 on the backmost.
        let top = count - batch * BWD_BATCH;
        let valid = lane < top;
        let k = select(valid, top - 1u32 - lane, 0u32);
        let gid = gid_from_isect[(start + k) as usize];
        let sp = load_splat(splats, gid);
        let mut f = Array::<f32>::new(FEATURE_LANES);
        for ch in 0..FEATURE_LANES {
            f[ch] = feature(colors, gid % num_gaussians, sp.depth, ch as u32);
        }
        let mut g = Array::<f32>::new(GRAD_LANES);
        for c in 0..GRAD_LANES {
            g[c] = 0.0;
        }
        for step in 0..group_pixels + BWD_BATCH - 1u32 {
            if valid && step >= lane && step - lane < group_pixels {
                let q = step - lane;
                let p = first + q;
                let pu = q as usize;
                if k < last[pu] {
                    let dx = sp.x - f32::cast_from(x0 + p % TILE_SIDE);
                    let dy = sp.y - f32::cast_from(y0 + p / TILE_SIDE);
                    let qa = sp.conic_a;
                    let qb = sp.conic_b;
                    let qc = sp.conic_c;
                    let e = eval_alpha(qa, qb, qc, sp.opacity, sp.log_cutoff, dx, dy, smooth);
                    if e.hit {
                        let t_i = trans[pu] / (1.0 - e.alpha);
                        let weight = e.alpha * t_i;
                        let mut d_alpha = 0.0f32;
                        for ch in 0..channels {
                            let at = FEATURE_LANES * pu + ch as usize;
                            d_alpha += d_pix[at] * (f[ch as usize] - behind[at]);
                            behind[at] = f[ch as usize] * e.alpha + (1.0 - e.alpha) * behind[at];
                        }
                        d_alpha *= t_i;
                        trans[pu] = t_i;
                        for ch in 0..COLOR_CHANNELS {
                            g[GRAD_COLOR + ch as usize] +=
                                weight * d_pix[FEATURE_LANES * pu + ch as usize];
                        }
                        if channels > DEPTH_CHANNEL {
                            g[GRAD_DEPTH] += weight * d_pix[FEATURE_LANES * pu + DEPTH_LANE];
                        }
                        let d_raw = d_alpha * e.dcap;
                        g[GRAD_OPACITY] += d_raw * e.g;
                        let d_power = d_raw * sp.opacity * e.g;
                        g[GRAD_X] += -d_power * (qa * dx + qb * dy);
                        g[GRAD_Y] += -d_power * (qc * dy + qb * dx);
                        g[GRAD_CONIC_A] += -0.5f32 * d_power * dx * dx;
                        g[GRAD_CONIC_B] += -d_power * dx * dy;
                        g[GRAD_CONIC_C] += -0.5f32 * d_power * dy * dy;
                    }
                }
            }
            sync_cube();
        }
        if valid {
            let base = GRAD_LANES * gid as usize;
            for c in 0..GRAD_LANES {
                let value = g[c];
                if value != 0.0 {
                    A::atomic_add_f32(&grad2d[base + c], value);
                }
            }
        }
    }
}
