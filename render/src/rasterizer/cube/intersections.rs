//! Stages 3–6 of the forward, **binning**: from per-Gaussian tile counts to one depth-ordered
//! list of Gaussians per tile.
//!
//! 3. **Offsets** ([`gather_counts`], then [`super::sort::exclusive_scan`]): tile counts gathered
//!    in depth order and scanned, so the Gaussian of depth rank `k` owns the intersections
//!    `[offsets[k], offsets[k + 1])`. The last entry is the number of intersections;
//!    [`copy_one`] isolates it for a 4-byte read-back (the forward's only GPU→CPU sync,
//!    needed because buffer sizes depend on it).
//! 4. **Map** ([`map_intersections`]): each Gaussian writes `(tile id, gid)` pairs at its
//!    offset.
//! 5. **Tile sort** ([`super::sort::radix_sort_pairs`]): stable radix sort on the tile id, only
//!    as many bits as the largest tile id needs. Stability keeps every tile's list in depth
//!    order: no 64-bit combined key.
//! 6. **Tile offsets** ([`tile_offsets_kernel`]): each tile's `[start, end)` in the sorted
//!    list.

use burn_cubecl::cubecl;
use burn_cubecl::cubecl::prelude::*;

use super::common::{RECT_LANES, RECT_X0, RECT_X1, RECT_Y0, RECT_Y1};

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

/// One thread per splat in depth order: writes `(tile id, gid)` for every tile of its
/// rectangle at its scanned offset. Tiles within a splat go in row-major order; the stable
/// tile sort that follows keeps the depth order between splats. With several views, splat
/// `gid` is Gaussian `gid % per_view` seen in view `gid / per_view`, whose tiles are numbered
/// after the earlier views' `tiles_per_view`.
#[cube(launch)]
#[allow(clippy::too_many_arguments)]
pub(crate) fn map_intersections(
    gid_from_depth_rank: &[u32],
    rects: &[u32],
    isect_offsets: &[u32],
    tile_keys: &mut [u32],
    gid_from_isect: &mut [u32],
    num_splats: u32,
    per_view: u32,
    tiles_x: u32,
    tiles_per_view: u32,
) {
    let rank = ABSOLUTE_POS as u32;
    if rank < num_splats {
        let gid = gid_from_depth_rank[rank as usize];
        let r = RECT_LANES * gid as usize;
        let first_tile = (gid / per_view) * tiles_per_view;
        let mut at = isect_offsets[rank as usize];
        for ty in rects[r + RECT_Y0]..rects[r + RECT_Y1] {
            for tx in rects[r + RECT_X0]..rects[r + RECT_X1] {
                tile_keys[at as usize] = first_tile + ty * tiles_x + tx;
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
