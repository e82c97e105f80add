//! The GoM geometry op on Burn's CubeCL backend (wgpu, and any other CubeCL runtime).
//!
//! Two kernels, one thread per face, mirroring [`super::cpu`] formula by formula in `f32`:
//!
//! - `gom_forward_kernel`: interpolate the three corners from the low-res vertices, build the
//!   Steiner frame and `exp(r̂)`, write mean ‖ covariance (`[F, 9]`);
//! - `gom_backward_kernel`: recompute the same, then write the face's `so3`, scale and offset
//!   gradients and, for each of its 9 corner-table entries, the weighted corner gradient
//!   `w·dL/dp_k` as a row of `[F*9, 3]`.
//!
//! - `gom_vertex_sum_kernel`: one thread per low-res vertex and axis sums that vertex's rows along
//!   its run of the inverted corner table (`vertex_corner_offsets`, `corner_from_vertex_order`),
//!   in increasing row order from `+0.0`.
//!
//! The vertex sum is a gather, not a scatter: no float atomics (which WGSL lacks), the same
//! bits on every run, and the same additions in the same order as scattering the rows one by
//! one. It replaced Burn's `float_select_assign` with `Add`, which runs one thread per output
//! column walking every row in order: three threads for the `[V, 3]` gradient, over
//! 9 · 438,720 rows at two subdivisions of the full template, which made the backward take a
//! second on an H200 (BENCHMARKS.md, "On a GPU").

use burn::backend::TensorMetadata;
use burn::backend::tensor::{FloatTensor, IntTensor};
use burn_cubecl::CubeBackend;
use burn_cubecl::cubecl;
use burn_cubecl::cubecl::prelude::*;

use super::cpu::{
    CORNER_LANES, DEGENERATE_ABS, DEGENERATE_REL, NORMAL_EPS2, OUT_LANES, SO3_THETA2_MIN,
};
use super::op::{GomGeometryOps, GomInputs, GomKernels};
use crate::cube::host::{
    ComputeClient, THREADS_1D, arg, cast_to, count_1d, prepare, prepare_i32, tensor_arg, tensor_f32,
};
use crate::steiner::NORMAL_SCALE;

const THETA2_MIN: f32 = SO3_THETA2_MIN as f32;
const EPS2: f32 = NORMAL_EPS2 as f32;
const DEG_REL: f32 = DEGENERATE_REL as f32;
const DEG_ABS: f32 = DEGENERATE_ABS as f32;
/// `2√3`, the divisor of `f2`, as `steiner_frames` rounds it.
const TWO_SQRT3: f32 = 3.464_101_6;

/// A 3-vector.
#[derive(CubeType, Clone, Copy)]
#[expand(derive(Clone))]
struct V3 {
    x: f32,
    y: f32,
    z: f32,
}

/// A 3×3 matrix by columns.
#[derive(CubeType, Clone, Copy)]
#[expand(derive(Clone))]
struct M3 {
    c0: V3,
    c1: V3,
    c2: V3,
}

#[cube]
fn v3(x: f32, y: f32, z: f32) -> V3 {
    V3 { x, y, z }
}

#[cube]
fn add(a: &V3, b: &V3) -> V3 {
    v3(a.x + b.x, a.y + b.y, a.z + b.z)
}

#[cube]
fn sub(a: &V3, b: &V3) -> V3 {
    v3(a.x - b.x, a.y - b.y, a.z - b.z)
}

#[cube]
fn scale(a: &V3, s: f32) -> V3 {
    v3(a.x * s, a.y * s, a.z * s)
}

#[cube]
fn div(a: &V3, s: f32) -> V3 {
    v3(a.x / s, a.y / s, a.z / s)
}

/// `a·s + b·t`.
#[cube]
fn lin2(a: &V3, s: f32, b: &V3, t: f32) -> V3 {
    v3(a.x * s + b.x * t, a.y * s + b.y * t, a.z * s + b.z * t)
}

#[cube]
fn dot(a: &V3, b: &V3) -> f32 {
    a.x * b.x + a.y * b.y + a.z * b.z
}

#[cube]
fn cross(a: &V3, b: &V3) -> V3 {
    v3(
        a.y * b.z - a.z * b.y,
        a.z * b.x - a.x * b.z,
        a.x * b.y - a.y * b.x,
    )
}

#[cube]
fn load3(values: &[f32], i: usize) -> V3 {
    v3(values[3 * i], values[3 * i + 1], values[3 * i + 2])
}

#[cube]
fn store3(values: &mut [f32], i: usize, v: &V3) {
    values[3 * i] = v.x;
    values[3 * i + 1] = v.y;
    values[3 * i + 2] = v.z;
}

#[cube]
fn cols(c0: V3, c1: V3, c2: V3) -> M3 {
    M3 { c0, c1, c2 }
}

/// `m·v`.
#[cube]
fn mul_v(m: &M3, v: &V3) -> V3 {
    v3(
        m.c0.x * v.x + m.c1.x * v.y + m.c2.x * v.z,
        m.c0.y * v.x + m.c1.y * v.y + m.c2.y * v.z,
        m.c0.z * v.x + m.c1.z * v.y + m.c2.z * v.z,
    )
}

/// `mᵀ·v`.
#[cube]
fn mul_tv(m: &M3, v: &V3) -> V3 {
    v3(dot(&m.c0, v), dot(&m.c1, v), dot(&m.c2, v))
}

/// `a·b`.
#[cube]
fn mul(a: &M3, b: &M3) -> M3 {
    cols(mul_v(a, &b.c0), mul_v(a, &b.c1), mul_v(a, &b.c2))
}

/// `aᵀ·b`.
#[cube]
fn mul_t_left(a: &M3, b: &M3) -> M3 {
    cols(mul_tv(a, &b.c0), mul_tv(a, &b.c1), mul_tv(a, &b.c2))
}

#[cube]
fn transpose(m: &M3) -> M3 {
    cols(
        v3(m.c0.x, m.c1.x, m.c2.x),
        v3(m.c0.y, m.c1.y, m.c2.y),
        v3(m.c0.z, m.c1.z, m.c2.z),
    )
}

/// `m·diag(s)`: column j scaled by `s_j`.
#[cube]
fn scale_cols(m: &M3, s: &V3) -> M3 {
    cols(scale(&m.c0, s.x), scale(&m.c1, s.y), scale(&m.c2, s.z))
}

/// `Σ_ij a_ij b_ij`.
#[cube]
fn frobenius(a: &M3, b: &M3) -> f32 {
    dot(&a.c0, &b.c0) + dot(&a.c1, &b.c1) + dot(&a.c2, &b.c2)
}

/// Corner `k` of face `f`: `Σ_m w·v[idx]` over its table slots; out-of-range slots add nothing.
#[cube]
fn corner(
    vertices: &[f32],
    corner_index: &[i32],
    corner_weight: &[f32],
    f: usize,
    k: usize,
    num_vertices: u32,
) -> V3 {
    let mut x = 0.0f32;
    let mut y = 0.0f32;
    let mut z = 0.0f32;
    let nv = i32::cast_from(num_vertices);
    for m in 0..3usize {
        let e = CORNER_LANES * f + 3 * k + m;
        let idx = corner_index[e];
        if idx >= 0 && idx < nv {
            let w = corner_weight[e];
            let b = 3 * usize::cast_from(idx);
            x += w * vertices[b];
            y += w * vertices[b + 1];
            z += w * vertices[b + 2];
        }
    }
    v3(x, y, z)
}

/// The Steiner frame (`cpu::steiner`) with the intermediates its backward needs.
#[derive(CubeType, Clone, Copy)]
#[expand(derive(Clone))]
struct Frame {
    c: V3,
    f1: V3,
    f2: V3,
    x_s: f32,
    y: f32,
    cs: f32,
    sn: f32,
    a0: V3,
    a1: V3,
    n: V3,
    nrm: f32,
    a: M3,
}

#[cube]
fn steiner(p0: &V3, p1: &V3, p2: &V3) -> Frame {
    let c = scale(&add(&add(p0, p1), p2), 1.0 / 3.0);
    let f1 = scale(&sub(p2, &c), 0.5);
    let f2 = div(&sub(p1, p0), TWO_SQRT3);
    let f11 = dot(&f1, &f1);
    let f22 = dot(&f2, &f2);
    let y = 2.0 * dot(&f1, &f2);
    let x = f11 - f22;
    let size2 = (f11 + f22) * (f11 + f22);
    let degenerate = x * x + y * y <= size2 * DEG_REL + DEG_ABS;
    let x_s = select(degenerate, x + 1.0, x);
    let t0 = 0.5 * y.atan2(x_s);
    let cs = t0.cos();
    let sn = t0.sin();
    let a0 = lin2(&f1, cs, &f2, sn);
    let a1 = lin2(&f2, cs, &f1, -sn);
    let n = cross(&a0, &a1);
    let nrm = (dot(&n, &n) + EPS2).sqrt();
    let a = cols(
        scale(&a0, 2.0),
        scale(&a1, 2.0),
        scale(&n, NORMAL_SCALE / nrm),
    );
    Frame {
        c,
        f1,
        f2,
        x_s,
        y,
        cs,
        sn,
        a0,
        a1,
        n,
        nrm,
        a,
    }
}

/// `exp(hat(r))` (`cpu::so3_exp`) with the intermediates its backward needs.
#[derive(CubeType, Clone, Copy)]
#[expand(derive(Clone))]
struct Rotation {
    nrm2: f32,
    theta: f32,
    fac1: f32,
    fac2: f32,
    k: M3,
    k2: M3,
    r: M3,
}

#[cube]
fn so3_exp(r: &V3) -> Rotation {
    let nrm2 = dot(r, r);
    let theta = max(nrm2, THETA2_MIN).sqrt();
    let fac1 = theta.sin() / theta;
    let fac2 = (1.0 - theta.cos()) / (theta * theta);
    let k = cols(v3(0.0, r.z, -r.y), v3(-r.z, 0.0, r.x), v3(r.y, -r.x, 0.0));
    let k2 = cols(
        v3(r.x * r.x - nrm2, r.y * r.x, r.z * r.x),
        v3(r.x * r.y, r.y * r.y - nrm2, r.z * r.y),
        v3(r.x * r.z, r.y * r.z, r.z * r.z - nrm2),
    );
    let rot = cols(
        v3(
            1.0 + fac2 * k2.c0.x,
            fac1 * k.c0.y + fac2 * k2.c0.y,
            fac1 * k.c0.z + fac2 * k2.c0.z,
        ),
        v3(
            fac1 * k.c1.x + fac2 * k2.c1.x,
            1.0 + fac2 * k2.c1.y,
            fac1 * k.c1.z + fac2 * k2.c1.z,
        ),
        v3(
            fac1 * k.c2.x + fac2 * k2.c2.x,
            fac1 * k.c2.y + fac2 * k2.c2.y,
            1.0 + fac2 * k2.c2.z,
        ),
    );
    Rotation {
        nrm2,
        theta,
        fac1,
        fac2,
        k,
        k2,
        r: rot,
    }
}

/// The Steiner frame of high-res face `f`, its corners interpolated from the low-res vertices.
#[cube]
fn face_frame(
    vertices: &[f32],
    corner_index: &[i32],
    corner_weight: &[f32],
    f: usize,
    num_vertices: u32,
) -> Frame {
    let p0 = corner(
        vertices,
        corner_index,
        corner_weight,
        f,
        0usize,
        num_vertices,
    );
    let p1 = corner(
        vertices,
        corner_index,
        corner_weight,
        f,
        1usize,
        num_vertices,
    );
    let p2 = corner(
        vertices,
        corner_index,
        corner_weight,
        f,
        2usize,
        num_vertices,
    );
    steiner(&p0, &p1, &p2)
}

/// One thread per face: mean ‖ covariance (`cpu::face_forward`).
#[cube(launch)]
#[allow(clippy::too_many_arguments)]
fn gom_forward_kernel(
    vertices: &[f32],
    so3: &[f32],
    scales: &[f32],
    offsets: &[f32],
    corner_index: &[i32],
    corner_weight: &[f32],
    out: &mut [f32],
    num_faces: u32,
    num_vertices: u32,
) {
    let face = ABSOLUTE_POS as u32;
    if face < num_faces {
        let f = face as usize;
        let frame = face_frame(vertices, corner_index, corner_weight, f, num_vertices);
        let rot = so3_exp(&load3(so3, f));
        let m = mul(&frame.a, &scale_cols(&rot.r, &load3(scales, f)));
        let mean = add(&frame.c, &mul_v(&frame.a, &load3(offsets, f)));
        // Rows of M: Σ_ij = row_i · row_j.
        let mt = transpose(&m);
        let o = OUT_LANES * f;
        out[o] = mean.x;
        out[o + 1] = mean.y;
        out[o + 2] = mean.z;
        out[o + 3] = dot(&mt.c0, &mt.c0);
        out[o + 4] = dot(&mt.c0, &mt.c1);
        out[o + 5] = dot(&mt.c0, &mt.c2);
        out[o + 6] = dot(&mt.c1, &mt.c1);
        out[o + 7] = dot(&mt.c1, &mt.c2);
        out[o + 8] = dot(&mt.c2, &mt.c2);
    }
}

/// `dL/dr` from `dL/dR` (`cpu::so3_exp_backward`).
#[cube]
fn so3_exp_backward(r: &V3, rot: &Rotation, g_r: &M3) -> V3 {
    let g_fac1 = frobenius(g_r, &rot.k);
    let g_fac2 = frobenius(g_r, &rot.k2);
    let f1 = rot.fac1;
    let f2 = rot.fac2;
    // hat(r): x sits at (2,1) and −(1,2), y at (0,2) and −(2,0), z at (1,0) and −(0,1).
    let from_k = v3(
        f1 * (g_r.c1.z - g_r.c2.y),
        f1 * (g_r.c2.x - g_r.c0.z),
        f1 * (g_r.c0.y - g_r.c1.x),
    );
    // (G + Gᵀ)·r with G = fac2·dL/dR.
    let from_k2 = scale(&add(&mul_v(g_r, r), &mul_tv(g_r, r)), f2);
    let trace = g_r.c0.x + g_r.c1.y + g_r.c2.z;
    let th = rot.theta;
    let st = th.sin();
    let ct = th.cos();
    let d_fac1 = (th * ct - st) / (th * th);
    let d_fac2 = (th * st - 2.0 * (1.0 - ct)) / (th * th * th);
    // The clamp passes the gradient where |r|² ≥ the floor (Burn's `clamp_min` backward).
    let through_theta = select(
        rot.nrm2 >= THETA2_MIN,
        (g_fac1 * d_fac1 + g_fac2 * d_fac2) / (2.0 * th),
        0.0f32,
    );
    let g_nrm2 = through_theta - f2 * trace;
    add(&add(&from_k, &from_k2), &scale(r, 2.0 * g_nrm2))
}

/// One thread per face: the face's parameter gradients and its 9 weighted corner-gradient rows
/// (`cpu::face_backward`; the vertex scatter is left to the host).
#[cube(launch)]
#[allow(clippy::too_many_arguments)]
fn gom_backward_kernel(
    vertices: &[f32],
    so3: &[f32],
    scales: &[f32],
    offsets: &[f32],
    corner_index: &[i32],
    corner_weight: &[f32],
    grad_out: &[f32],
    d_so3: &mut [f32],
    d_scales: &mut [f32],
    d_offsets: &mut [f32],
    d_rows: &mut [f32],
    num_faces: u32,
    num_vertices: u32,
) {
    let face = ABSOLUTE_POS as u32;
    if face < num_faces {
        let f = face as usize;
        let fr = face_frame(vertices, corner_index, corner_weight, f, num_vertices);
        let r = load3(so3, f);
        let s = load3(scales, f);
        let o = load3(offsets, f);
        let rot = so3_exp(&r);
        let rs = scale_cols(&rot.r, &s);
        let m = mul(&fr.a, &rs);

        let b = OUT_LANES * f;
        let g_mean = v3(grad_out[b], grad_out[b + 1], grad_out[b + 2]);
        let gxx = grad_out[b + 3];
        let gxy = grad_out[b + 4];
        let gxz = grad_out[b + 5];
        let gyy = grad_out[b + 6];
        let gyz = grad_out[b + 7];
        let gzz = grad_out[b + 8];
        let g_sym = cols(
            v3(2.0 * gxx, gxy, gxz),
            v3(gxy, 2.0 * gyy, gyz),
            v3(gxz, gyz, 2.0 * gzz),
        );
        let g_m = mul(&g_sym, &m);
        let g_rs = mul_t_left(&fr.a, &g_m);
        // dL/dA = dL/dM·(RS)ᵀ + g_mean ⊗ o.
        let g_a = mul(&g_m, &transpose(&rs));
        let g_a0c = add(&g_a.c0, &scale(&g_mean, o.x));
        let g_a1c = add(&g_a.c1, &scale(&g_mean, o.y));
        let g_nh = add(&g_a.c2, &scale(&g_mean, o.z));

        let g_r = scale_cols(&g_rs, &s);
        store3(
            d_scales,
            f,
            &v3(
                dot(&g_rs.c0, &rot.r.c0),
                dot(&g_rs.c1, &rot.r.c1),
                dot(&g_rs.c2, &rot.r.c2),
            ),
        );
        store3(d_so3, f, &so3_exp_backward(&r, &rot, &g_r));
        store3(d_offsets, f, &mul_tv(&fr.a, &g_mean));

        // The frame's backward (`cpu::steiner_backward`).
        let nrm3 = fr.nrm * fr.nrm * fr.nrm;
        let g_n = scale(
            &lin2(&g_nh, 1.0 / fr.nrm, &fr.n, -dot(&fr.n, &g_nh) / nrm3),
            NORMAL_SCALE,
        );
        let g_a0 = add(&scale(&g_a0c, 2.0), &cross(&fr.a1, &g_n));
        let g_a1 = add(&scale(&g_a1c, 2.0), &cross(&g_n, &fr.a0));
        let g_cs = dot(&g_a0, &fr.f1) + dot(&g_a1, &fr.f2);
        let g_sn = dot(&g_a0, &fr.f2) - dot(&g_a1, &fr.f1);
        let g_t0 = g_sn * fr.cs - g_cs * fr.sn;
        let den = fr.x_s * fr.x_s + fr.y * fr.y;
        let g_y2 = g_t0 * fr.x_s / den;
        let g_x2 = -g_t0 * fr.y / den;
        // 2·g_y and 2·g_x are g_y2 and g_x2 (t0 = ½·atan2).
        let g_f1 = add(
            &lin2(&g_a0, fr.cs, &g_a1, -fr.sn),
            &lin2(&fr.f2, g_y2, &fr.f1, g_x2),
        );
        let g_f2 = add(
            &lin2(&g_a0, fr.sn, &g_a1, fr.cs),
            &lin2(&fr.f1, g_y2, &fr.f2, -g_x2),
        );
        let g_c = scale(&sub(&g_mean, &scale(&g_f1, 0.5)), 1.0 / 3.0);
        let g_f2s = div(&g_f2, TWO_SQRT3);
        let g_p0 = sub(&g_c, &g_f2s);
        let g_p1 = add(&g_c, &g_f2s);
        let g_p2 = add(&g_c, &scale(&g_f1, 0.5));

        let nv = i32::cast_from(num_vertices);
        for k in 0..3usize {
            let g_p = select_v3(k == 0, &g_p0, k == 1, &g_p1, &g_p2);
            for slot in 0..3usize {
                let e = CORNER_LANES * f + 3 * k + slot;
                let idx = corner_index[e];
                let w = select(idx >= 0 && idx < nv, corner_weight[e], 0.0f32);
                store3(d_rows, e, &scale(&g_p, w));
            }
        }
    }
}

/// `if first { x } else if second { y } else { z }`, field by field (struct values cannot be
/// reassigned in branches of a kernel).
#[cube]
fn select_v3(first: bool, x: &V3, second: bool, y: &V3, z: &V3) -> V3 {
    v3(
        select(first, x.x, select(second, y.x, z.x)),
        select(first, x.y, select(second, y.y, z.y)),
        select(first, x.z, select(second, y.z, z.z)),
    )
}

/// One thread per low-res vertex and axis: the sum of the vertex's corner-gradient rows
/// (`rows`, `[E, 3]`), taken along its run `corner_from_vertex_order[offsets[v]..offsets[v+1]]`
/// in increasing row order from `+0.0`.
#[cube(launch)]
#[allow(clippy::needless_range_loop)] // CubeCL kernels loop over index ranges, not iterators
fn gom_vertex_sum_kernel(
    rows: &[f32],
    vertex_corner_offsets: &[i32],
    corner_from_vertex_order: &[i32],
    out: &mut [f32],
    num_vertices: u32,
) {
    let unit = ABSOLUTE_POS as u32;
    if unit < 3 * num_vertices {
        let v = (unit / 3) as usize;
        let axis = (unit % 3) as usize;
        let start = vertex_corner_offsets[v] as usize;
        let end = vertex_corner_offsets[v + 1] as usize;
        let mut sum = 0.0f32;
        for k in start..end {
            let row = corner_from_vertex_order[k] as usize;
            sum += rows[3 * row + axis];
        }
        out[unit as usize] = sum;
    }
}

/// The prepared (f32 / i32, contiguous) inputs and their sizes.
struct Prepared {
    inputs: GomInputs<CubeBackend>,
    corner_index_i32: burn_cubecl::tensor::CubeTensor,
    num_faces: usize,
    num_vertices: usize,
}

fn prepared(inputs: GomInputs<CubeBackend>) -> Prepared {
    let corner_index_i32 = prepare_i32(inputs.corner_index.clone());
    let inputs = GomInputs {
        vertices: prepare(inputs.vertices),
        so3: prepare(inputs.so3),
        scales: prepare(inputs.scales),
        offsets: prepare(inputs.offsets),
        corner_index: inputs.corner_index,
        corner_weight: prepare(inputs.corner_weight),
        vertex_corner_offsets: prepare_i32(inputs.vertex_corner_offsets),
        corner_from_vertex_order: prepare_i32(inputs.corner_from_vertex_order),
    };
    let num_faces = TensorMetadata::shape(&inputs.so3).num_elements() / 3;
    let num_vertices = TensorMetadata::shape(&inputs.vertices).num_elements() / 3;
    Prepared {
        inputs,
        corner_index_i32,
        num_faces,
        num_vertices,
    }
}

fn forward(inputs: GomInputs<CubeBackend>) -> FloatTensor<CubeBackend> {
    let _span = tracing::trace_span!("cube_gom_forward").entered();
    let dtype = inputs.vertices.dtype();
    let p = prepared(inputs);
    let (f, v) = (p.num_faces, p.num_vertices);
    let client = p.inputs.vertices.client.clone();
    let device = p.inputs.vertices.device.clone();
    let out = client.empty(4 * (OUT_LANES * f).max(1));
    if f > 0 {
        gom_forward_kernel::launch(
            &client,
            count_1d(f),
            CubeDim::new_1d(THREADS_1D),
            vertices_arg(&p),
            tensor_arg(&p.inputs.so3),
            tensor_arg(&p.inputs.scales),
            tensor_arg(&p.inputs.offsets),
            tensor_arg(&p.corner_index_i32),
            tensor_arg(&p.inputs.corner_weight),
            arg(&out, OUT_LANES * f),
            f as u32,
            v as u32,
        );
    }
    cast_to(tensor_f32(&client, &device, out, &[f, OUT_LANES]), dtype)
}

/// The vertex buffer, or (with no vertices, when no table index is in range and the kernels
/// never read it) a one-element stand-in, since zero-sized bindings are invalid.
fn vertices_arg(p: &Prepared) -> BufferArg {
    if p.num_vertices > 0 {
        tensor_arg(&p.inputs.vertices)
    } else {
        tensor_arg(&p.inputs.corner_weight)
    }
}

fn backward(
    inputs: GomInputs<CubeBackend>,
    grad: FloatTensor<CubeBackend>,
) -> [FloatTensor<CubeBackend>; 4] {
    let _span = tracing::trace_span!("cube_gom_backward").entered();
    let dtypes = [
        inputs.vertices.dtype(),
        inputs.so3.dtype(),
        inputs.scales.dtype(),
        inputs.offsets.dtype(),
    ];
    let p = prepared(inputs);
    let (f, v) = (p.num_faces, p.num_vertices);
    let client = p.inputs.vertices.client.clone();
    let device = p.inputs.vertices.device.clone();
    let d_so3 = client.empty(4 * (3 * f).max(1));
    let d_scales = client.empty(4 * (3 * f).max(1));
    let d_offsets = client.empty(4 * (3 * f).max(1));
    let d_vertices = client.empty(4 * (3 * v).max(1));
    let rows_len = CORNER_LANES * f * 3;
    let rows = client.empty(4 * rows_len.max(1));
    if f > 0 {
        let grad = prepare(grad);
        gom_backward_kernel::launch(
            &client,
            count_1d(f),
            CubeDim::new_1d(THREADS_1D),
            vertices_arg(&p),
            tensor_arg(&p.inputs.so3),
            tensor_arg(&p.inputs.scales),
            tensor_arg(&p.inputs.offsets),
            tensor_arg(&p.corner_index_i32),
            tensor_arg(&p.inputs.corner_weight),
            tensor_arg(&grad),
            arg(&d_so3, 3 * f),
            arg(&d_scales, 3 * f),
            arg(&d_offsets, 3 * f),
            arg(&rows, rows_len),
            f as u32,
            v as u32,
        );
    }
    if v > 0 {
        // With no faces every run is empty (the offsets are all zero): the sums are +0.0 and
        // the one-element stand-in for `rows` is never read.
        gom_vertex_sum_kernel::launch(
            &client,
            count_1d(3 * v),
            CubeDim::new_1d(THREADS_1D),
            arg(&rows, rows_len),
            tensor_arg(&p.inputs.vertex_corner_offsets),
            runs_arg(&p, &client),
            arg(&d_vertices, 3 * v),
            v as u32,
        );
    }
    let per_face = |handle| tensor_f32(&client, &device, handle, &[f, 3]);
    [
        cast_to(tensor_f32(&client, &device, d_vertices, &[v, 3]), dtypes[0]),
        cast_to(per_face(d_so3), dtypes[1]),
        cast_to(per_face(d_scales), dtypes[2]),
        cast_to(per_face(d_offsets), dtypes[3]),
    ]
}

/// The inverted table's runs, or (when no entry is in range, so no run is ever read) a
/// one-element stand-in, since zero-sized bindings are invalid.
fn runs_arg(p: &Prepared, client: &ComputeClient) -> BufferArg {
    if TensorMetadata::shape(&p.inputs.corner_from_vertex_order).num_elements() > 0 {
        tensor_arg(&p.inputs.corner_from_vertex_order)
    } else {
        arg(&client.empty(4), 1)
    }
}

impl GomGeometryOps for CubeBackend {
    fn gom_geometry(
        vertices: FloatTensor<Self>,
        so3: FloatTensor<Self>,
        scales: FloatTensor<Self>,
        offsets: FloatTensor<Self>,
        corner_index: IntTensor<Self>,
        corner_weight: FloatTensor<Self>,
        vertex_corner_offsets: IntTensor<Self>,
        corner_from_vertex_order: IntTensor<Self>,
    ) -> FloatTensor<Self> {
        forward(GomInputs {
            vertices,
            so3,
            scales,
            offsets,
            corner_index,
            corner_weight,
            vertex_corner_offsets,
            corner_from_vertex_order,
        })
    }
}

impl GomKernels for CubeBackend {
    fn gom_forward(inputs: GomInputs<Self>) -> FloatTensor<Self> {
        forward(inputs)
    }

    fn gom_backward(inputs: GomInputs<Self>, grad: FloatTensor<Self>) -> [FloatTensor<Self>; 4] {
        backward(inputs, grad)
    }
}
