//! The pyramid sampling op on Burn's CubeCL backend (design.md §7.2): the same map as the CPU
//! slice code ([`super::bilinear`]), formula by formula in `f32`, as four kernels.
//!
//! - `sample_forward_kernel`: one thread per output element `(point, view, channel)`. It finds the
//!   channel's level, computes that level's map coordinates and four-corner footprint (once, as
//!   every kernel here that loops over channels) and writes the weighted corner sum (on the last
//!   level, the sum of every channel's sample times the tail's column).
//! - `sample_uv_backward_kernel`: one thread per point and view, summing over the levels the slope of
//!   the weights times `⟨g, corner row⟩`, times `W_l / width`.
//! - `sample_rows_backward_kernel`: one thread per `(point, view, level channel)`, adding `w·g` into the
//!   four corner rows with float atomic adds (`lifegom_render::cube::atomic`): a corner row is
//!   shared by every point that falls near it, so this is a scatter.
//! - `sample_tail_factors_kernel`: one thread per point and view, writing the last level's sample and
//!   the tail's output gradient as two contiguous row blocks; the tail's gradient is then one
//!   product `sampleᵀ·g` (Burn's matmul).
//!
//! The levels' geometry (where each starts in the flat maps and in an output row, its size and
//! its coordinate scale) travels as a small table ([`LevelGeom`] per level). On the GPU this op
//! replaced about forty tensor ops per level and call (coordinates, footprint, row gather,
//! weighted sum, then the tail's product and the concatenation), each its own kernel launch, and
//! their backward (BENCHMARKS.md, "Kernel launches per training step").
//!
//! The atomic adds make the rows' gradient sums' order, and so their last bits, depend on thread
//! scheduling, as in the rasterizer's backward.

use burn::backend::TensorMetadata;
use burn::backend::ops::FloatTensorOps;
use burn::backend::tensor::FloatTensor;
use burn_cubecl::CubeBackend;
use burn_cubecl::cubecl;
use burn_cubecl::cubecl::prelude::*;
use burn_cubecl::cubecl::server::Handle;
use burn_cubecl::tensor::CubeTensor;
use lifegom_render::cube::atomic::{AtomicAddF32, use_native_float_atomics};
use lifegom_render::cube::host::{
    ComputeClient, THREADS_1D, arg, cast_to, count_1d, prepare, tensor_arg, tensor_f32, u32_bytes,
    zeros_f32,
};

use super::op::{
    BilinearKernels, BilinearSampleOps, PyramidLayout, SampleGrads, SampleInputs, Wanted,
};

/// u32 fields per level in the level table: rows_from, height, width, channels, out_from.
const LEVEL_FIELDS: usize = 5;

/// One level's geometry, read from the level table.
#[derive(CubeType, Clone, Copy)]
#[expand(derive(Clone))]
struct LevelGeom {
    /// First element of the level in the flat maps.
    rows_from: usize,
    height: usize,
    width: usize,
    channels: usize,
    /// First channel of the level in an output row (and in the level-channel index of the
    /// rows' backward: they coincide, as only the last level's width changes through the tail).
    out_from: usize,
    /// `W_l / width`.
    scale_x: f32,
    /// `H_l / height`.
    scale_y: f32,
}

#[cube]
fn level_geom(table: &[u32], scales: &[f32], level: usize) -> LevelGeom {
    let t = level * LEVEL_FIELDS;
    LevelGeom {
        rows_from: table[t] as usize,
        height: table[t + 1] as usize,
        width: table[t + 2] as usize,
        channels: table[t + 3] as usize,
        out_from: table[t + 4] as usize,
        scale_x: scales[2 * level],
        scale_y: scales[2 * level + 1],
    }
}

/// The level whose channels hold `channel` (levels are in increasing `out_from`).
#[cube]
fn level_of(table: &[u32], levels: usize, channel: usize) -> usize {
    let mut level = 0usize;
    for l in 1..levels {
        if channel >= table[l * LEVEL_FIELDS + 4] as usize {
            level = l;
        }
    }
    level
}

/// Image coordinate `u` → map coordinate (NaN parked at −2, clamped to `[−2, size + 1]`), as
/// `bilinear::map_coordinate`.
#[cube]
fn map_coordinate(u: f32, scale: f32, size: usize) -> f32 {
    let x = u * scale - 0.5f32;
    let hi = f32::cast_from(size) + 1.0f32;
    let mut out = x;
    if u.is_nan() || x < -2.0f32 {
        out = -2.0f32;
    } else if x > hi {
        out = hi;
    }
    out
}

/// A point's map coordinates on one level.
#[derive(CubeType, Clone, Copy)]
#[expand(derive(Clone))]
struct MapPoint {
    x: f32,
    y: f32,
}

/// Point `k` of `uv` (`[N·P, 2]` image pixels) on level `geom`.
#[cube]
fn map_point(uv: &[f32], k: usize, geom: &LevelGeom) -> MapPoint {
    MapPoint {
        x: map_coordinate(uv[2 * k], geom.scale_x, geom.width),
        y: map_coordinate(uv[2 * k + 1], geom.scale_y, geom.height),
    }
}

/// What a thread of a per-channel kernel works on: element `unit` of a `[P, N, stride]` layout
/// whose channels run over the levels in order (`stride` is the output width or the level
/// channels `Σ_l C_l`; both start each level at its `out_from`).
#[derive(CubeType, Clone, Copy)]
struct ChannelSite {
    view: usize,
    point: usize,
    level: usize,
    /// The channel within its level.
    channel: usize,
    geom: LevelGeom,
    at: MapPoint,
}

#[cube]
#[allow(clippy::too_many_arguments)]
fn channel_site(
    uv: &[f32],
    table: &[u32],
    scales: &[f32],
    unit: usize,
    stride: usize,
    views: usize,
    points: usize,
    levels: usize,
) -> ChannelSite {
    let channel = unit % stride;
    let pv = unit / stride;
    let view = pv % views;
    let point = pv / views;
    let level = level_of(table, levels, channel);
    let geom = level_geom(table, scales, level);
    let at = map_point(uv, view * points + point, &geom);
    let within = channel - geom.out_from;
    ChannelSite {
        view,
        point,
        level,
        channel: within,
        geom,
        at,
    }
}

/// One corner of a bilinear footprint.
#[derive(CubeType, Clone, Copy)]
struct Corner {
    inside: bool,
    /// Row of the corner in the level's maps (meaningful when `inside`).
    row: usize,
    /// `w_x·w_y`, 0 outside.
    weight: f32,
    /// `∂(w_x·w_y)/∂x`.
    d_dx: f32,
    /// `∂(w_x·w_y)/∂y`.
    d_dy: f32,
}

/// Corner `k` of the footprint of map point `(x, y)` of `view`, in the order
/// `(x₀, y₀), (x₀+1, y₀), (x₀, y₀+1), (x₀+1, y₀+1)`, as `bilinear`'s `footprint`.
#[cube]
fn corner(geom: &LevelGeom, view: usize, x: f32, y: f32, k: u32) -> Corner {
    let x0 = x.floor();
    let y0 = y.floor();
    let fx = x - x0;
    let fy = y - y0;
    let a = k & 1;
    let b = k >> 1;
    let i = i32::cast_from(x0) + a as i32;
    let j = i32::cast_from(y0) + b as i32;
    let in_x = i >= 0 && i < geom.width as i32;
    let in_y = j >= 0 && j < geom.height as i32;
    let mut wx = 0.0f32;
    let mut sx = 0.0f32;
    if in_x {
        if a == 0 {
            wx = 1.0f32 - fx;
            sx = -1.0f32;
        } else {
            wx = fx;
            sx = 1.0f32;
        }
    }
    let mut wy = 0.0f32;
    let mut sy = 0.0f32;
    if in_y {
        if b == 0 {
            wy = 1.0f32 - fy;
            sy = -1.0f32;
        } else {
            wy = fy;
            sy = 1.0f32;
        }
    }
    let inside = in_x && in_y;
    let mut row = 0usize;
    if inside {
        row = (view * geom.height + j as usize) * geom.width + i as usize;
    }
    Corner {
        inside,
        row,
        weight: wx * wy,
        d_dx: sx * wy,
        d_dy: wx * sy,
    }
}

/// The four corners of a map point's footprint, computed once per thread where a loop over
/// channels reads them (the last level's channels, the tail's inputs). Computed per channel
/// instead, a tail column cost `4·C_last` corner evaluations; the forward kernel then took 81 ms
/// of device time in a paper-setting reconstruction on an H200 (BENCHMARKS.md, "On a GPU
/// (NVIDIA H200, 2026-11-27)").
#[derive(CubeType, Clone, Copy)]
struct Footprint {
    c00: Corner,
    c10: Corner,
    c01: Corner,
    c11: Corner,
}

#[cube]
fn footprint(geom: &LevelGeom, view: usize, x: f32, y: f32) -> Footprint {
    Footprint {
        c00: corner(geom, view, x, y, 0u32),
        c10: corner(geom, view, x, y, 1u32),
        c01: corner(geom, view, x, y, 2u32),
        c11: corner(geom, view, x, y, 3u32),
    }
}

/// The sample of channel `c` of a level at a footprint: `Σ_corners w·rows[corner][c]`, summed
/// in corner order as the CPU code does.
#[cube]
fn footprint_sum(rows: &[f32], geom: &LevelGeom, fp: &Footprint, c: usize) -> f32 {
    corner_product(rows, geom, &fp.c00, c, fp.c00.weight)
        + corner_product(rows, geom, &fp.c10, c, fp.c10.weight)
        + corner_product(rows, geom, &fp.c01, c, fp.c01.weight)
        + corner_product(rows, geom, &fp.c11, c, fp.c11.weight)
}

/// `factor·rows[corner][c]`, or 0 outside the map (where the row is not read).
#[cube]
fn corner_product(rows: &[f32], geom: &LevelGeom, cr: &Corner, c: usize, factor: f32) -> f32 {
    let mut term = 0.0f32;
    if cr.inside {
        term = factor * rows[geom.rows_from + cr.row * geom.channels + c];
    }
    term
}

/// A corner's contribution `(∂w/∂x·dot, ∂w/∂y·dot)` to a point's coordinate gradient.
#[cube]
fn corner_slope(cr: &Corner, dot: f32) -> MapPoint {
    let mut x = 0.0f32;
    let mut y = 0.0f32;
    if cr.inside {
        x = cr.d_dx * dot;
        y = cr.d_dy * dot;
    }
    MapPoint { x, y }
}

/// The last level's sample gradient for its channel `c`: the output gradient `g_out` (at
/// `grad[g_from..g_from + tail_out]`) taken back through the tail, `Σ_j g_out[j]·tail[c][j]`.
#[cube]
fn tail_back(grad: &[f32], g_from: usize, tail: &[f32], c: usize, tail_out: usize) -> f32 {
    let mut acc = 0.0f32;
    for j in 0..tail_out {
        acc += grad[g_from + j] * tail[c * tail_out + j];
    }
    acc
}

/// One thread per output element of `[P, N, width]`.
#[cube(launch)]
#[allow(clippy::too_many_arguments)]
fn sample_forward_kernel(
    rows: &[f32],
    uv: &[f32],
    tail: &[f32],
    table: &[u32],
    scales: &[f32],
    out: &mut [f32],
    units: usize,
    views: usize,
    points: usize,
    levels: usize,
    width: usize,
    tail_out: usize,
) {
    let unit = ABSOLUTE_POS;
    if unit < units {
        let site = channel_site(uv, table, scales, unit, width, views, points, levels);
        let (geom, at) = (site.geom, site.at);
        let fp = footprint(&geom, site.view, at.x, at.y);
        if site.level == levels - 1 {
            let mut value = 0.0f32;
            for c in 0..geom.channels {
                value += footprint_sum(rows, &geom, &fp, c) * tail[c * tail_out + site.channel];
            }
            out[unit] = value;
        } else {
            out[unit] = footprint_sum(rows, &geom, &fp, site.channel);
        }
    }
}

/// One thread per point and view, in `uv`'s `[N, P]` order: `∂L/∂(u, v)`.
#[cube(launch)]
#[allow(clippy::too_many_arguments)]
fn sample_uv_backward_kernel(
    rows: &[f32],
    uv: &[f32],
    tail: &[f32],
    grad: &[f32],
    table: &[u32],
    scales: &[f32],
    out: &mut [f32],
    units: usize,
    views: usize,
    points: usize,
    levels: usize,
    width: usize,
    tail_out: usize,
) {
    let k = ABSOLUTE_POS;
    if k < units {
        let view = k / points;
        let point = k % points;
        let g_row = (point * views + view) * width;
        let mut gu = 0.0f32;
        let mut gv = 0.0f32;
        for level in 0..levels {
            let geom = level_geom(table, scales, level);
            let at = map_point(uv, k, &geom);
            let g_from = g_row + geom.out_from;
            let is_tail = level == levels - 1;
            // One pass over the channels for all four corners: the tail's gradient of a
            // channel is a loop over the tail's outputs, computed once instead of per corner.
            let fp = footprint(&geom, view, at.x, at.y);
            let mut dot00 = 0.0f32;
            let mut dot10 = 0.0f32;
            let mut dot01 = 0.0f32;
            let mut dot11 = 0.0f32;
            for c in 0..geom.channels {
                let g = if is_tail {
                    tail_back(grad, g_from, tail, c, tail_out)
                } else {
                    grad[g_from + c]
                };
                dot00 += corner_product(rows, &geom, &fp.c00, c, g);
                dot10 += corner_product(rows, &geom, &fp.c10, c, g);
                dot01 += corner_product(rows, &geom, &fp.c01, c, g);
                dot11 += corner_product(rows, &geom, &fp.c11, c, g);
            }
            let s00 = corner_slope(&fp.c00, dot00);
            let s10 = corner_slope(&fp.c10, dot10);
            let s01 = corner_slope(&fp.c01, dot01);
            let s11 = corner_slope(&fp.c11, dot11);
            let gx = s00.x + s10.x + s01.x + s11.x;
            let gy = s00.y + s10.y + s01.y + s11.y;
            gu += gx * geom.scale_x;
            gv += gy * geom.scale_y;
        }
        out[2 * k] = gu;
        out[2 * k + 1] = gv;
    }
}

/// One thread per `(point, view, level channel)` (`in_width = Σ_l C_l` level channels per
/// point and view): scatters `w·g` into the four corner rows.
#[cube(launch)]
#[allow(clippy::too_many_arguments)]
fn sample_rows_backward_kernel<A: AtomicAddF32>(
    uv: &[f32],
    tail: &[f32],
    grad: &[f32],
    table: &[u32],
    scales: &[f32],
    out: &[Atomic<A>],
    units: usize,
    views: usize,
    points: usize,
    levels: usize,
    width: usize,
    in_width: usize,
    tail_out: usize,
) {
    let unit = ABSOLUTE_POS;
    if unit < units {
        let site = channel_site(uv, table, scales, unit, in_width, views, points, levels);
        let (geom, c) = (site.geom, site.channel);
        let g_from = (site.point * views + site.view) * width + geom.out_from;
        let g = if site.level == levels - 1 {
            tail_back(grad, g_from, tail, c, tail_out)
        } else {
            grad[g_from + c]
        };
        if g != 0.0f32 {
            for corner_index in 0..4u32 {
                let cr = corner(&geom, site.view, site.at.x, site.at.y, corner_index);
                if cr.inside && cr.weight != 0.0f32 {
                    A::atomic_add_f32(
                        &out[geom.rows_from + cr.row * geom.channels + c],
                        cr.weight * g,
                    );
                }
            }
        }
    }
}

/// One thread per point and view, in the output's `[P, N]` order: the last level's sample
/// (`samples`, `[P·N, C_last]`) and the tail's output gradient (`g_out`, `[P·N, tail_out]`).
#[cube(launch)]
#[allow(clippy::too_many_arguments)]
fn sample_tail_factors_kernel(
    rows: &[f32],
    uv: &[f32],
    grad: &[f32],
    table: &[u32],
    scales: &[f32],
    samples: &mut [f32],
    g_out: &mut [f32],
    units: usize,
    views: usize,
    points: usize,
    levels: usize,
    width: usize,
    tail_out: usize,
) {
    let pv = ABSOLUTE_POS;
    if pv < units {
        let view = pv % views;
        let point = pv / views;
        let k = view * points + point;
        let geom = level_geom(table, scales, levels - 1);
        let at = map_point(uv, k, &geom);
        let fp = footprint(&geom, view, at.x, at.y);
        for c in 0..geom.channels {
            samples[pv * geom.channels + c] = footprint_sum(rows, &geom, &fp, c);
        }
        let g_from = pv * width + geom.out_from;
        for j in 0..tail_out {
            g_out[pv * tail_out + j] = grad[g_from + j];
        }
    }
}

/// The op's sizes and its level table on the device.
struct Launch {
    client: ComputeClient,
    table: Handle,
    scales: Handle,
    levels: usize,
    views: usize,
    points: usize,
    /// Output channels per point and view.
    width: usize,
    /// Level channels per point and view (`Σ_l C_l`).
    in_width: usize,
    c_last: usize,
    tail_out: usize,
}

impl Launch {
    fn new(client: &ComputeClient, layout: &PyramidLayout, points: usize, tail_len: usize) -> Self {
        let (mut table, mut scales) = (Vec::new(), Vec::new());
        let (mut rows_from, mut out_from) = (0usize, 0usize);
        for level in &layout.levels {
            let field = |v: usize| u32::try_from(v).expect("sampling sizes fit in u32");
            table.extend([
                field(rows_from),
                field(level.height),
                field(level.width),
                field(level.channels),
                field(out_from),
            ]);
            // The same f64 quotient, rounded once, as the CPU code's scale.
            scales.push((level.width as f64 / layout.image.0 as f64) as f32);
            scales.push((level.height as f64 / layout.image.1 as f64) as f32);
            rows_from += layout.views * level.height * level.width * level.channels;
            out_from += level.channels;
        }
        let c_last = layout.levels.last().map_or(1, |l| l.channels);
        let tail_out = tail_len / c_last.max(1);
        let in_width = out_from;
        let scale_bits: Vec<u32> = scales.iter().map(|s: &f32| s.to_bits()).collect();
        Self {
            client: client.clone(),
            table: client.create_from_slice(&u32_bytes(&table)),
            scales: client.create_from_slice(&u32_bytes(&scale_bits)),
            levels: layout.levels.len(),
            views: layout.views,
            points,
            width: in_width - c_last + tail_out,
            in_width,
            c_last,
            tail_out,
        }
    }

    fn table_arg(&self) -> BufferArg {
        arg(&self.table, self.levels * LEVEL_FIELDS)
    }

    fn scales_arg(&self) -> BufferArg {
        arg(&self.scales, self.levels * 2)
    }
}

/// The prepared (f32, contiguous) inputs and the launch of one call.
struct Prepared {
    rows: CubeTensor,
    uv: CubeTensor,
    tail: CubeTensor,
    launch: Launch,
}

fn prepare_inputs(inputs: SampleInputs<CubeBackend>) -> Prepared {
    let points = inputs.uv.shape()[1];
    let client = inputs.rows.client.clone();
    let tail_len = inputs.tail.shape().num_elements();
    let launch = Launch::new(&client, &inputs.layout, points, tail_len);
    Prepared {
        rows: prepare(inputs.rows),
        uv: prepare(inputs.uv),
        tail: prepare(inputs.tail),
        launch,
    }
}

fn cube_forward(inputs: SampleInputs<CubeBackend>) -> FloatTensor<CubeBackend> {
    let _span = tracing::trace_span!("cube_bilinear_forward").entered();
    let dtype = inputs.rows.dtype();
    let device = inputs.rows.device.clone();
    let p = prepare_inputs(inputs);
    let l = &p.launch;
    let units = l.points * l.views * l.width;
    let out = l.client.empty(4 * units.max(1));
    if units > 0 {
        sample_forward_kernel::launch(
            &l.client,
            count_1d(units),
            CubeDim::new_1d(THREADS_1D),
            tensor_arg(&p.rows),
            tensor_arg(&p.uv),
            tensor_arg(&p.tail),
            l.table_arg(),
            l.scales_arg(),
            arg(&out, units),
            units,
            l.views,
            l.points,
            l.levels,
            l.width,
            l.tail_out,
        );
    }
    let shape = [l.points, l.views, l.width];
    cast_to(tensor_f32(&l.client, &device, out, &shape), dtype)
}

fn cube_backward(
    inputs: SampleInputs<CubeBackend>,
    grad: FloatTensor<CubeBackend>,
    wanted: Wanted,
) -> SampleGrads<CubeBackend> {
    let _span = tracing::trace_span!("cube_bilinear_backward").entered();
    let shapes = [inputs.rows.shape(), inputs.uv.shape(), inputs.tail.shape()];
    let dtypes = [inputs.rows.dtype(), inputs.uv.dtype(), inputs.tail.dtype()];
    let device = inputs.rows.device.clone();
    let grad = prepare(grad);
    let p = prepare_inputs(inputs);
    let l = &p.launch;
    let client = &l.client;
    let pv = l.points * l.views;

    let uv_len = 2 * pv;
    let uv_grad = client.empty(4 * uv_len.max(1));
    if pv > 0 {
        sample_uv_backward_kernel::launch(
            client,
            count_1d(pv),
            CubeDim::new_1d(THREADS_1D),
            tensor_arg(&p.rows),
            tensor_arg(&p.uv),
            tensor_arg(&p.tail),
            tensor_arg(&grad),
            l.table_arg(),
            l.scales_arg(),
            arg(&uv_grad, uv_len),
            pv,
            l.views,
            l.points,
            l.levels,
            l.width,
            l.tail_out,
        );
    }
    let as_input = |values: CubeTensor, i: usize| cast_to(values, dtypes[i]);

    let rows_grad = wanted.rows.then(|| {
        let len = shapes[0].num_elements();
        let out = zeros_f32(client, &device, len);
        let units = pv * l.in_width;
        if units > 0 && len > 0 {
            macro_rules! launch {
                ($slot:ty) => {
                    sample_rows_backward_kernel::launch::<$slot>(
                        client,
                        count_1d(units),
                        CubeDim::new_1d(THREADS_1D),
                        tensor_arg(&p.uv),
                        tensor_arg(&p.tail),
                        tensor_arg(&grad),
                        l.table_arg(),
                        l.scales_arg(),
                        arg(&out, len),
                        units,
                        l.views,
                        l.points,
                        l.levels,
                        l.width,
                        l.in_width,
                        l.tail_out,
                    )
                };
            }
            if use_native_float_atomics(client) {
                launch!(f32);
            } else {
                launch!(u32);
            }
        }
        as_input(tensor_f32(client, &device, out, &shapes[0]), 0)
    });

    let tail_grad = wanted.tail.then(|| {
        let samples = client.empty(4 * (pv * l.c_last).max(1));
        let g_out = client.empty(4 * (pv * l.tail_out).max(1));
        if pv > 0 {
            sample_tail_factors_kernel::launch(
                client,
                count_1d(pv),
                CubeDim::new_1d(THREADS_1D),
                tensor_arg(&p.rows),
                tensor_arg(&p.uv),
                tensor_arg(&grad),
                l.table_arg(),
                l.scales_arg(),
                arg(&samples, pv * l.c_last),
                arg(&g_out, pv * l.tail_out),
                pv,
                l.views,
                l.points,
                l.levels,
                l.width,
                l.tail_out,
            );
        }
        // `Σ_points sampleᵀ·g_out`, `[C_last, tail_out]`.
        let samples = tensor_f32(client, &device, samples, &[pv.max(1), l.c_last]);
        let g_out = tensor_f32(client, &device, g_out, &[pv.max(1), l.tail_out]);
        let product = if pv > 0 {
            CubeBackend::float_matmul(CubeBackend::float_transpose(samples), g_out)
        } else {
            tensor_f32(
                client,
                &device,
                zeros_f32(client, &device, l.c_last * l.tail_out),
                &[l.c_last, l.tail_out],
            )
        };
        as_input(product, 2)
    });

    let uv_grad = as_input(tensor_f32(client, &device, uv_grad, &shapes[1]), 1);
    (rows_grad, uv_grad, tail_grad)
}

impl BilinearSampleOps for CubeBackend {
    fn bilinear_sample(
        rows: FloatTensor<Self>,
        uv: FloatTensor<Self>,
        tail: FloatTensor<Self>,
        layout: PyramidLayout,
    ) -> FloatTensor<Self> {
        cube_forward(SampleInputs {
            rows,
            uv,
            tail,
            layout,
        })
    }
}

impl BilinearKernels for CubeBackend {
    fn bilinear_forward(inputs: SampleInputs<Self>) -> FloatTensor<Self> {
        cube_forward(inputs)
    }

    fn bilinear_backward(
        inputs: SampleInputs<Self>,
        grad: FloatTensor<Self>,
        wanted: Wanted,
    ) -> SampleGrads<Self> {
        cube_backward(inputs, grad, wanted)
    }
}
