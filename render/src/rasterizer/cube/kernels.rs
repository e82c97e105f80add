//! The rasterizer's CubeCL kernels. Each mirrors a piece of [`crate::rasterizer::cpu`] line by
//! line (same formulas, same evaluation order), so the two agree to rounding.
//!
//! Buffers are flat `f32`/`u32` slices:
//! - `view`: 16 floats, the row-major 3×4 `[R | t]` then `fx, fy, cx, cy`.
//! - `splats`: `[N, SPLAT_LANES]`: `x, y, conic A, B, C, opacity, depth, log_cutoff` (the
//!   CPU's `Splat2d`).
//! - `grad2d`: `[N, GRAD_LANES]`: `x, y, conic A, B, C, opacity, r, g, b, depth` (the CPU's slot).
//!
//! Guards are worded so that NaN fails them (`!(x <= MAX)` is true for NaN and ±Inf), matching
//! the CPU's `is_finite` checks without relying on NaN-aware builtins.

// `!(a <= b)` is the deliberate NaN-failing guard form (as in `cpu.rs`); `(a + b - 1) / b` stays
// spelled out because `#[cube]` traces the arithmetic operators, not `u32::div_ceil`.
#![allow(clippy::neg_cmp_op_on_partial_ord, clippy::manual_div_ceil)]

use burn_cubecl::cubecl;
use burn_cubecl::cubecl::prelude::*;

use super::super::cpu::{
    ALPHA_MAX, ALPHA_MIN, DILATION, FOV_CLAMP, NEAR_Z, SMOOTH_HI, SMOOTH_LO, T_MIN,
};

/// Floats per projected splat.
pub(crate) const SPLAT_LANES: u32 = 8;
/// Floats per per-Gaussian 2D gradient.
pub(crate) const GRAD_LANES: u32 = 10;
/// Tile side in pixels (the CPU's `TILE`).
pub(crate) const TILE_SIDE: u32 = 16;
/// Pixels per tile: the forward's cube size and shared-memory batch length.
pub(crate) const TILE_PIXELS: u32 = 256;
/// Splats per backward batch: the backward's cube size.
pub(crate) const BWD_BATCH: u32 = 32;
/// Key of a culled Gaussian in the depth sort: sorts after every positive float's bits.
pub(crate) const CULLED_KEY: u32 = 0xffff_ffff;
/// Largest finite f32; `!(|x| <= BIG)` catches NaN and ±Inf.
const BIG: f32 = f32::MAX;

/// The dilated 2D covariance and EWA Jacobian of a Gaussian at view-space `t`.
#[derive(CubeType, Clone, Copy)]
pub(crate) struct Ewa {
    /// Rows of `T = J·R`.
    t0x: f32,
    t0y: f32,
    t0z: f32,
    t1x: f32,
    t1y: f32,
    t1z: f32,
    /// Whether x/z and y/z were clamped.
    clamped_x: bool,
    clamped_y: bool,
}

#[cube]
fn ewa(view: &[f32], width: u32, height: u32, tx: f32, ty: f32, tz: f32) -> Ewa {
    let fx = view[12];
    let fy = view[13];
    let limx = FOV_CLAMP * f32::cast_from(width) / (2.0 * fx);
    let limy = FOV_CLAMP * f32::cast_from(height) / (2.0 * fy);
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
        t0x: j00 * view[0] + j02 * view[8],
        t0y: j00 * view[1] + j02 * view[9],
        t0z: j00 * view[2] + j02 * view[10],
        t1x: j11 * view[4] + j12 * view[8],
        t1y: j11 * view[5] + j12 * view[9],
        t1z: j11 * view[6] + j12 * view[10],
        clamped_x,
        clamped_y,
    }
}

/// `Σ·v` for the symmetric Σ stored as (xx, xy, xz, yy, yz, zz) at `covs[base..]`; one lane.
#[cube]
fn sym_row(covs: &[f32], base: usize, row: u32, vx: f32, vy: f32, vz: f32) -> f32 {
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
    view: &[f32],
    splats: &mut [f32],
    rects: &mut [u32],
    tile_counts: &mut [u32],
    depth_keys: &mut [u32],
    num_gaussians: u32,
    width: u32,
    height: u32,
    #[comptime] smooth: bool,
) {
    let gid = ABSOLUTE_POS as u32;
    if gid < num_gaussians {
        let g = gid as usize;
        let mut visible = true;
        let cr = colors[3 * g];
        let cg = colors[3 * g + 1];
        let cb = colors[3 * g + 2];
        if !(cr.abs() <= BIG && cg.abs() <= BIG && cb.abs() <= BIG) {
            visible = false;
        }
        let mx = means[3 * g];
        let my = means[3 * g + 1];
        let mz = means[3 * g + 2];
        let tx = view[0] * mx + view[1] * my + view[2] * mz + view[3];
        let ty = view[4] * mx + view[5] * my + view[6] * mz + view[7];
        let tz = view[8] * mx + view[9] * my + view[10] * mz + view[11];
        if !(tz > NEAR_Z && tz <= BIG && tx.abs() <= BIG && ty.abs() <= BIG) {
            visible = false;
        }
        let thr = if smooth { SMOOTH_LO } else { ALPHA_MIN };
        let opacity = opacities[g];
        if !(opacity > thr && opacity <= BIG) {
            visible = false;
        }
        // Keep the arithmetic below on finite values even for culled Gaussians.
        let sx = select(visible, tx, 0.0f32);
        let sy = select(visible, ty, 0.0f32);
        let sz = select(visible, tz, 1.0f32);
        let e = ewa(view, width, height, sx, sy, sz);
        let base = 6 * g;
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
        if !(det > 0.0 && a > 0.0 && det <= BIG) {
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
        let x = view[12] * sx / sz + view[14] - 0.5;
        let y = view[13] * sy / sz + view[15] - 0.5;
        let log_cutoff = -0.5f32 * k2;
        let inv_det = 1.0 / (qa * qc - qb * qb);
        let kk = -2.0f32 * log_cutoff;
        let ex = (kk * qc * inv_det).sqrt() * 1.001 + 1e-3;
        let ey = (kk * qa * inv_det).sqrt() * 1.001 + 1e-3;
        if !(x.abs() <= BIG
            && y.abs() <= BIG
            && radius.abs() <= BIG
            && ex.abs() <= BIG
            && ey.abs() <= BIG)
        {
            visible = false;
        }
        let gx = f32::cast_from((width + TILE_SIDE - 1) / TILE_SIDE);
        let gy = f32::cast_from((height + TILE_SIDE - 1) / TILE_SIDE);
        let t = f32::cast_from(TILE_SIDE);
        // The clamps also make the casts below well defined for culled (possibly NaN) values.
        let x0 = u32::cast_from(min(max(((x - radius) / t).floor(), 0.0f32), gx));
        let y0 = u32::cast_from(min(max(((y - radius) / t).floor(), 0.0f32), gy));
        let x1 = u32::cast_from(min(max(((x + radius + t - 1.0) / t).floor(), 0.0f32), gx));
        let y1 = u32::cast_from(min(max(((y + radius + t - 1.0) / t).floor(), 0.0f32), gy));
        if !(x1 > x0 && y1 > y0) {
            visible = false;
        }
        let r = 4 * g;
        let s = (SPLAT_LANES * gid) as usize;
        if visible {
            splats[s] = x;
            splats[s + 1] = y;
            splats[s + 2] = qa;
            splats[s + 3] = qb;
            splats[s + 4] = qc;
            splats[s + 5] = opacity;
            splats[s + 6] = tz;
            splats[s + 7] = log_cutoff;
            rects[r] = x0;
            rects[r + 1] = y0;
            rects[r + 2] = x1;
            rects[r + 3] = y1;
            tile_counts[g] = (x1 - x0) * (y1 - y0);
            // Depth is > NEAR_Z > 0, so its bit pattern orders like the float.
            depth_keys[g] = u32::reinterpret(tz);
        } else {
            for k in 0..SPLAT_LANES {
                splats[s + k as usize] = 0.0;
            }
            rects[r] = 0u32;
            rects[r + 1] = 0u32;
            rects[r + 2] = 0u32;
            rects[r + 3] = 0u32;
            tile_counts[g] = 0u32;
            depth_keys[g] = CULLED_KEY;
        }
    }
}

/// `out[i] = values[index[i]]` for `i < n`, and `out[n] = 0` (so an exclusive scan of `out`
/// ends with the total).
#[cube(launch)]
pub(crate) fn gather_counts(index: &[u32], values: &[u32], out: &mut [u32], n: u32) {
    let i = ABSOLUTE_POS as u32;
    if i < n {
        out[i as usize] = values[index[i as usize] as usize];
    } else if i == n {
        out[i as usize] = 0u32;
    }
}

/// `out[0] = data[at]`: isolates one value for a 4-byte readback.
#[cube(launch)]
pub(crate) fn copy_one(data: &[u32], out: &mut [u32], at: u32) {
    if ABSOLUTE_POS == 0usize {
        out[0] = data[at as usize];
    }
}

/// One thread per Gaussian in depth order: writes `(tile id, gid)` for every tile of its
/// rectangle at its scanned offset. Tiles within a Gaussian go in row-major order; the stable
/// tile sort that follows keeps the depth order between Gaussians.
#[cube(launch)]
pub(crate) fn map_intersections(
    gid_from_depth_rank: &[u32],
    rects: &[u32],
    isect_offsets: &[u32],
    tile_keys: &mut [u32],
    gid_from_isect: &mut [u32],
    num_gaussians: u32,
    tiles_x: u32,
) {
    let rank = ABSOLUTE_POS as u32;
    if rank < num_gaussians {
        let gid = gid_from_depth_rank[rank as usize];
        let r = (4 * gid) as usize;
        let mut at = isect_offsets[rank as usize];
        for ty in rects[r + 1]..rects[r + 3] {
            for tx in rects[r]..rects[r + 2] {
                tile_keys[at as usize] = ty * tiles_x + tx;
                gid_from_isect[at as usize] = gid;
                at += 1u32;
            }
        }
    }
}

/// One thread per intersection of the tile-sorted list: writes `tile_offsets[t]` (the first
/// intersection of tile `t`) for every tile whose range starts here, including empty tiles
/// between two keys and the `num_tiles + 1` end sentinel.
#[cube(launch)]
pub(crate) fn tile_offsets_kernel(
    tile_keys: &[u32],
    tile_offsets: &mut [u32],
    num_isects: u32,
    num_tiles: u32,
) {
    let i = ABSOLUTE_POS as u32;
    if i < num_isects {
        let key = tile_keys[i as usize];
        let mut first = 0u32;
        if i > 0u32 {
            first = tile_keys[(i - 1) as usize] + 1u32;
        }
        for t in first..key + 1u32 {
            tile_offsets[t as usize] = i;
        }
        if i + 1u32 == num_isects {
            for t in key + 1u32..num_tiles + 1u32 {
                tile_offsets[t as usize] = num_isects;
            }
        }
    }
}

/// Alpha of a splat at offset `(dx, dy)` and the factors the backward needs (`cpu::eval_alpha`).
#[derive(CubeType, Clone, Copy)]
pub(crate) struct AlphaEval {
    alpha: f32,
    /// d(final alpha)/d(o·G).
    dcap: f32,
    /// G itself.
    g: f32,
    /// Whether the pixel blends this splat at all.
    hit: bool,
}

#[cube]
fn eval_alpha(
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

/// The Gaussian's feature: `[r, g, b, 1, depth]`.
#[cube]
fn feature(colors: &[f32], gid: u32, depth: f32, ch: u32) -> f32 {
    let mut f = depth;
    if ch < 3u32 {
        f = colors[(3 * gid + ch) as usize];
    } else if ch == 3u32 {
        f = 1.0;
    }
    f
}

/// One 16×16 cube per tile, one thread per pixel. The tile's list is consumed in batches of 256
/// splats that the threads load together into shared memory; each pixel blends front to back
/// and stops at `T < T_MIN`; the whole tile stops early once every pixel has (a shared counter
/// read with a uniform load, so the loop exit is provably uniform for WGSL's barrier rules).
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
    #[comptime] channels: u32,
    #[comptime] smooth: bool,
) {
    let tile = CUBE_POS_Y * tiles_x + CUBE_POS_X;
    let px = CUBE_POS_X * TILE_SIDE + UNIT_POS_X;
    let py = CUBE_POS_Y * TILE_SIDE + UNIT_POS_Y;
    let lane = UNIT_POS;
    let inside = px < width && py < height;

    let mut range = Shared::<[u32]>::new_slice(2usize);
    let finished = Shared::<[Atomic<u32>]>::new_slice(1usize);
    let mut batch_xy = Shared::<[f32]>::new_slice(512usize);
    let mut batch_conic = Shared::<[f32]>::new_slice(768usize);
    let mut batch_opacity = Shared::<[f32]>::new_slice(256usize);
    let mut batch_cutoff = Shared::<[f32]>::new_slice(256usize);
    let mut batch_feature = Shared::<[f32]>::new_slice(1024usize);
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
    let mut acc = Array::<f32>::new(5usize);
    for ch in 0..5u32 {
        acc[ch as usize] = 0.0;
    }
    let mut last = 0u32;
    let mut done = !inside;
    if done {
        finished[0].fetch_add(1u32);
    }

    let num_batches = (end - start + TILE_PIXELS - 1u32) / TILE_PIXELS;
    for batch in 0..num_batches {
        // The uniform load is also the barrier that keeps this batch's loads from overwriting
        // splats a slower thread is still blending.
        let done_count = workgroup_uniform_load_atomic(&finished[0]);
        if done_count >= TILE_PIXELS {
            break;
        }
        let batch_start = start + batch * TILE_PIXELS;
        let at = batch_start + lane;
        if at < end {
            let gid = gid_from_isect[at as usize];
            let s = (SPLAT_LANES * gid) as usize;
            let l = lane as usize;
            batch_xy[2 * l] = splats[s];
            batch_xy[2 * l + 1] = splats[s + 1];
            batch_conic[3 * l] = splats[s + 2];
            batch_conic[3 * l + 1] = splats[s + 3];
            batch_conic[3 * l + 2] = splats[s + 4];
            batch_opacity[l] = splats[s + 5];
            batch_cutoff[l] = splats[s + 7];
            batch_feature[4 * l] = colors[(3 * gid) as usize];
            batch_feature[4 * l + 1] = colors[(3 * gid + 1) as usize];
            batch_feature[4 * l + 2] = colors[(3 * gid + 2) as usize];
            batch_feature[4 * l + 3] = splats[s + 6];
        }
        sync_cube();
        let batch_len = min(TILE_PIXELS, end - batch_start);
        for j in 0..batch_len {
            if done {
                break;
            }
            let k = j as usize;
            let e = eval_alpha(
                batch_conic[3 * k],
                batch_conic[3 * k + 1],
                batch_conic[3 * k + 2],
                batch_opacity[k],
                batch_cutoff[k],
                batch_xy[2 * k] - fpx,
                batch_xy[2 * k + 1] - fpy,
                smooth,
            );
            if e.hit {
                let t_next = trans * (1.0 - e.alpha);
                if t_next < T_MIN {
                    done = true;
                    finished[0].fetch_add(1u32);
                } else {
                    for ch in 0..channels {
                        let mut f = 1.0f32;
                        if ch < 3u32 {
                            f = batch_feature[4 * k + ch as usize];
                        } else if ch == 4u32 {
                            f = batch_feature[4 * k + 3];
                        }
                        acc[ch as usize] += f * e.alpha * trans;
                    }
                    trans = t_next;
                    last = batch * TILE_PIXELS + j + 1u32;
                }
            }
        }
    }

    if inside {
        let pix = py * width + px;
        for ch in 0..channels {
            image[(pix * channels + ch) as usize] = acc[ch as usize];
        }
        final_t[pix as usize] = trans;
        last_contrib[pix as usize] = last;
    }
}

/// `*slot += value` for an `f32` held in an atomic slot of type `Self`: `f32` slots use the
/// native float atomic add; `u32` slots hold the bit pattern and emulate it with atomic
/// exchanges, for runtimes without float atomics (WGSL has none).
#[cube]
pub(crate) trait AtomicAddF32: CubePrimitive {
    /// Adds `value` to `slot`.
    fn atomic_add_f32(slot: &Atomic<Self>, value: f32);
}

#[cube]
impl AtomicAddF32 for f32 {
    fn atomic_add_f32(slot: &Atomic<Self>, value: f32) {
        slot.fetch_add(value);
    }
}

/// The emulation takes the slot's value (leaving `+0.0`), adds its own and puts the sum back.
/// The put returns whatever another thread deposited in the meantime; that amount goes round
/// again until a put lands on an empty slot. No addend is ever dropped. The textbook
/// compare-and-swap loop is not safe here: WGSL only has a *weak* compare-exchange, which may
/// fail spuriously, and CubeCL returns only its old value, not the `exchanged` flag, so a
/// spurious failure would look like success and lose the addend (Metal, through naga, really
/// is weak).
#[cube]
impl AtomicAddF32 for u32 {
    fn atomic_add_f32(slot: &Atomic<Self>, value: f32) {
        let mut pending = value;
        loop {
            let taken = slot.exchange(0u32);
            let sum = f32::reinterpret(taken) + pending;
            let back = slot.exchange(u32::reinterpret(sum));
            if back == 0u32 {
                break;
            }
            pending = f32::reinterpret(back);
        }
    }
}

/// Backward of the blend, one 32-thread cube per tile and one thread per splat.
///
/// The tile's list is replayed back to front in batches of 32 splats, thread `t` holding the
/// `t`-th splat from the back of the batch in registers. Per-pixel state (transmittance, colour
/// of everything behind, `dL/dpixel`, last contributor) lives in shared memory. Work follows a
/// diagonal: at step `s` thread `t` handles pixel `s − t`, so every pixel meets the batch's
/// splats strictly back to front (thread 0 first) and no two threads touch one pixel in one
/// step. Each thread sums its splat's gradient over the tile's pixels in registers (in
/// row-major pixel order, as the CPU does) and then does one atomic add per component into
/// `grad2d`.
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
    #[comptime] channels: u32,
    #[comptime] smooth: bool,
) {
    let tile = CUBE_POS_Y * tiles_x + CUBE_POS_X;
    let x0 = CUBE_POS_X * TILE_SIDE;
    let y0 = CUBE_POS_Y * TILE_SIDE;
    let lane = UNIT_POS;

    let mut range = Shared::<[u32]>::new_slice(1usize);
    let max_last = Shared::<[Atomic<u32>]>::new_slice(1usize);
    let mut trans = Shared::<[f32]>::new_slice(256usize);
    let mut behind = Shared::<[f32]>::new_slice(1280usize);
    let mut d_pix = Shared::<[f32]>::new_slice(1280usize);
    let mut last = Shared::<[u32]>::new_slice(256usize);
    if lane == 0u32 {
        range[0] = tile_offsets[tile as usize];
        max_last[0].store(0u32);
    }
    sync_cube();
    let mut local_max = 0u32;
    for r in 0..TILE_PIXELS / BWD_BATCH {
        let p = r * BWD_BATCH + lane;
        let px = x0 + p % TILE_SIDE;
        let py = y0 + p / TILE_SIDE;
        let pu = p as usize;
        for ch in 0..5u32 {
            behind[5 * pu + ch as usize] = 0.0;
            d_pix[5 * pu + ch as usize] = 0.0;
        }
        if px < width && py < height {
            let pix = py * width + px;
            trans[pu] = final_t[pix as usize];
            last[pu] = last_contrib[pix as usize];
            for ch in 0..channels {
                d_pix[5 * pu + ch as usize] = d_image[(pix * channels + ch) as usize];
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
        let s = (SPLAT_LANES * gid) as usize;
        let sx = splats[s];
        let sy = splats[s + 1];
        let qa = splats[s + 2];
        let qb = splats[s + 3];
        let qc = splats[s + 4];
        let opacity = splats[s + 5];
        let depth = splats[s + 6];
        let log_cutoff = splats[s + 7];
        let mut f = Array::<f32>::new(5usize);
        for ch in 0..5u32 {
            f[ch as usize] = feature(colors, gid, depth, ch);
        }
        let mut g = Array::<f32>::new(10usize);
        for c in 0..GRAD_LANES {
            g[c as usize] = 0.0;
        }
        for step in 0..TILE_PIXELS + BWD_BATCH - 1u32 {
            if valid && step >= lane && step - lane < TILE_PIXELS {
                let p = step - lane;
                let pu = p as usize;
                if k < last[pu] {
                    let dx = sx - f32::cast_from(x0 + p % TILE_SIDE);
                    let dy = sy - f32::cast_from(y0 + p / TILE_SIDE);
                    let e = eval_alpha(qa, qb, qc, opacity, log_cutoff, dx, dy, smooth);
                    if e.hit {
                        let t_i = trans[pu] / (1.0 - e.alpha);
                        let weight = e.alpha * t_i;
                        let mut d_alpha = 0.0f32;
                        for ch in 0..channels {
                            let at = 5 * pu + ch as usize;
                            d_alpha += d_pix[at] * (f[ch as usize] - behind[at]);
                            behind[at] = f[ch as usize] * e.alpha + (1.0 - e.alpha) * behind[at];
                        }
                        d_alpha *= t_i;
                        trans[pu] = t_i;
                        for ch in 0..3u32 {
                            g[(6 + ch) as usize] += weight * d_pix[5 * pu + ch as usize];
                        }
                        if channels == 5u32 {
                            g[9] += weight * d_pix[5 * pu + 4];
                        }
                        let d_raw = d_alpha * e.dcap;
                        g[5] += d_raw * e.g;
                        let d_power = d_raw * opacity * e.g;
                        g[0] += -d_power * (qa * dx + qb * dy);
                        g[1] += -d_power * (qc * dy + qb * dx);
                        g[2] += -0.5f32 * d_power * dx * dx;
                        g[3] += -d_power * dx * dy;
                        g[4] += -0.5f32 * d_power * dy * dy;
                    }
                }
            }
            sync_cube();
        }
        if valid {
            let base = GRAD_LANES * gid;
            for c in 0..GRAD_LANES {
                let value = g[c as usize];
                if value != 0.0 {
                    A::atomic_add_f32(&grad2d[(base + c) as usize], value);
                }
            }
        }
    }
}

/// One thread per Gaussian: chains the 2D gradients back through the conic, the EWA Jacobian
/// and the view transform to the mean and the 6 covariance entries (`cpu::project_backward`),
/// and copies out the colour and opacity gradients. Culled Gaussians get zeros.
#[cube(launch)]
#[allow(clippy::too_many_arguments)]
pub(crate) fn project_backward_kernel(
    means: &[f32],
    covs: &[f32],
    view: &[f32],
    splats: &[f32],
    tile_counts: &[u32],
    grad2d: &[f32],
    d_means: &mut [f32],
    d_covs: &mut [f32],
    d_colors: &mut [f32],
    d_opacities: &mut [f32],
    num_gaussians: u32,
    width: u32,
    height: u32,
) {
    let gid = ABSOLUTE_POS as u32;
    if gid < num_gaussians {
        let i = gid as usize;
        if tile_counts[i] == 0u32 {
            for c in 0..3u32 {
                d_means[3 * i + c as usize] = 0.0;
                d_colors[3 * i + c as usize] = 0.0;
            }
            for c in 0..6u32 {
                d_covs[6 * i + c as usize] = 0.0;
            }
            d_opacities[i] = 0.0;
        } else {
            let gb = (GRAD_LANES * gid) as usize;
            d_colors[3 * i] = grad2d[gb + 6];
            d_colors[3 * i + 1] = grad2d[gb + 7];
            d_colors[3 * i + 2] = grad2d[gb + 8];
            d_opacities[i] = grad2d[gb + 5];
            let dxy0 = grad2d[gb];
            let dxy1 = grad2d[gb + 1];
            let dq0 = grad2d[gb + 2];
            let dq1 = grad2d[gb + 3];
            let dq2 = grad2d[gb + 4];
            let d_depth = grad2d[gb + 9];

            let mx = means[3 * i];
            let my = means[3 * i + 1];
            let mz = means[3 * i + 2];
            let x = view[0] * mx + view[1] * my + view[2] * mz + view[3];
            let y = view[4] * mx + view[5] * my + view[6] * mz + view[7];
            let z = view[8] * mx + view[9] * my + view[10] * mz + view[11];
            let fx = view[12];
            let fy = view[13];
            let e = ewa(view, width, height, x, y, z);

            // Conic → 2D covariance: dL/dM = −Q·G·Q, G the symmetric gradient of Q.
            let s = (SPLAT_LANES * gid) as usize;
            let qa = splats[s + 2];
            let qb = splats[s + 3];
            let qc = splats[s + 4];
            let h = 0.5 * dq1;
            let qg00 = qa * dq0 + qb * h;
            let qg01 = qa * h + qb * dq2;
            let qg10 = qb * dq0 + qc * h;
            let qg11 = qb * h + qc * dq2;
            let gm00 = -(qg00 * qa + qg01 * qb);
            let gm01 = -(qg00 * qb + qg01 * qc);
            let gm10 = -(qg10 * qa + qg11 * qb);
            let gm11 = -(qg10 * qb + qg11 * qc);

            // dL/dΣ = Tᵀ·dL/dM·T, entry (a, b) with u = T row 0, v = T row 1.
            let mut u = Array::<f32>::new(3usize);
            let mut v = Array::<f32>::new(3usize);
            u[0] = e.t0x;
            u[1] = e.t0y;
            u[2] = e.t0z;
            v[0] = e.t1x;
            v[1] = e.t1y;
            v[2] = e.t1z;
            let mut ds = Array::<f32>::new(9usize);
            for a in 0..3u32 {
                for b in 0..3u32 {
                    let ua = u[a as usize];
                    let va = v[a as usize];
                    let ub = u[b as usize];
                    let vb = v[b as usize];
                    ds[(3 * a + b) as usize] =
                        ua * gm00 * ub + ua * gm01 * vb + va * gm10 * ub + va * gm11 * vb;
                }
            }
            let cb = 6 * i;
            d_covs[cb] = ds[0];
            d_covs[cb + 1] = ds[1] + ds[3];
            d_covs[cb + 2] = ds[2] + ds[6];
            d_covs[cb + 3] = ds[4];
            d_covs[cb + 4] = ds[5] + ds[7];
            d_covs[cb + 5] = ds[8];

            // dL/dT = 2·dL/dM·T·Σ.
            let mut ts0 = Array::<f32>::new(3usize);
            let mut ts1 = Array::<f32>::new(3usize);
            for a in 0..3u32 {
                ts0[a as usize] = sym_row(covs, cb, a, e.t0x, e.t0y, e.t0z);
                ts1[a as usize] = sym_row(covs, cb, a, e.t1x, e.t1y, e.t1z);
            }
            let mut d_j00 = 0.0f32;
            let mut d_j02 = 0.0f32;
            let mut d_j11 = 0.0f32;
            let mut d_j12 = 0.0f32;
            for a in 0..3u32 {
                let au = a as usize;
                let dt0 = 2.0 * (gm00 * ts0[au] + gm01 * ts1[au]);
                let dt1 = 2.0 * (gm10 * ts0[au] + gm11 * ts1[au]);
                d_j00 += dt0 * view[au];
                d_j02 += dt0 * view[8 + au];
                d_j11 += dt1 * view[4 + au];
                d_j12 += dt1 * view[8 + au];
            }

            let z2 = z * z;
            let z3 = z * z * z;
            let mut dvx = 0.0f32;
            let mut dvy = 0.0f32;
            let mut dvz = -fx / z2 * d_j00 - fy / z2 * d_j11;
            if e.clamped_x {
                // J02 = −fx·(±lim)/z: only z moves it.
                let lim = select(x / z >= 0.0, 1.0f32, -1.0f32) * FOV_CLAMP * f32::cast_from(width)
                    / (2.0 * fx);
                dvz += fx * lim / z2 * d_j02;
            } else {
                dvx += -fx / z2 * d_j02;
                dvz += 2.0 * fx * x / z3 * d_j02;
            }
            if e.clamped_y {
                let lim =
                    select(y / z >= 0.0, 1.0f32, -1.0f32) * FOV_CLAMP * f32::cast_from(height)
                        / (2.0 * fy);
                dvz += fy * lim / z2 * d_j12;
            } else {
                dvy += -fy / z2 * d_j12;
                dvz += 2.0 * fy * y / z3 * d_j12;
            }
            dvx += fx / z * dxy0;
            dvy += fy / z * dxy1;
            dvz += -fx * x / z2 * dxy0 - fy * y / z2 * dxy1 + d_depth;
            d_means[3 * i] = view[0] * dvx + view[4] * dvy + view[8] * dvz;
            d_means[3 * i + 1] = view[1] * dvx + view[5] * dvy + view[9] * dvz;
            d_means[3 * i + 2] = view[2] * dvx + view[6] * dvy + view[10] * dvz;
        }
    }
}
