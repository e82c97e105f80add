//! The triangle-ID rasterizer on Burn's CubeCL backend (wgpu).
//!
//! # Algorithm
//!
//! The depth and ID buffers start at `+inf` and "no face" (`start_views_kernel`, one launch);
//! then one thread per face, two passes over the same traversal (`raster_faces_kernel`, the pass is
//! a comptime flag), then a per-pixel resolve. Several views run in the same launches
//! (`visibility_in_views`): one thread per (view, face), each view's camera from a table and its
//! pixels after the earlier views'; their buffers start with the visible-vertex flags
//! (`start_views_kernel`), the raw ID buffer marks the vertices (`mark_views_kernel`) and one
//! more launch writes the flags the model reads (`view_flags_kernel`):
//!
//! 1. **Depth pass**: transform the corners to camera space, clip against `z = NEAR`, project,
//!    and walk the pixel centres of the (one or two) screen triangles' bounding box. A covered
//!    pixel does `atomic_min(depth_bits, bits(z))`: depths are positive floats, whose bit
//!    patterns order like the values.
//! 2. **ID pass**: the same walk; a covered pixel whose depth equals the pass-1 minimum does
//!    `atomic_min(ids, face)`.
//! 3. **Resolve** (`resolve_kernel`): empty pixels become `-1` / `+inf`.
//!
//! The result is the lexicographic minimum of `(depth, face id)` per pixel — the CPU's rule —
//! with no 64-bit atomics (WGSL has none) and independent of thread scheduling. The second pass
//! compares with `≤` so that a pixel can never end up with a depth and no face even if the
//! compiler were to round the two passes' depths differently.
//!
//! Everything else mirrors [`super::cpu`] line by line, in `f32`: the Sutherland–Hodgman clip
//! (new points computed from the inside endpoint), the canonical edge order and tie rule that
//! make shared edges watertight, and perspective-correct `1/z` interpolation.
//!
//! # Cost
//!
//! Work per thread is the face's bounding box. Posed body meshes at the resolutions we render
//! have faces of a few pixels, which this suits; a face covering much of the image (a mesh
//! crossing the near plane) serialises its pixels on one thread: slow, still correct.

// `!(a <= b)` is the deliberate NaN-failing guard form (as in the rasterizer kernels).
#![allow(clippy::neg_cmp_op_on_partial_ord)]

use burn::backend::TensorMetadata;
use burn::backend::tensor::{FloatTensor, IntTensor};
use burn::tensor::DType;
use burn_cubecl::CubeBackend;
use burn_cubecl::cubecl;
use burn_cubecl::cubecl::prelude::*;
use burn_cubecl::cubecl::server::Handle;

use burn_cubecl::tensor::CubeTensor;

use super::ViewSet;
use super::op::TriangleIdOps;
use crate::camera::{Camera, ViewParams};
use crate::cube::float::finite;
use crate::cube::host::{
    ComputeClient, THREADS_1D, arg, count_1d, empty_u32, prepare, prepare_i32, tensor_of,
};
use crate::cube::view::{CAMERA_FLOATS, ViewArgs, camera_of, camera_table};

/// `ids` entry of a pixel no face covers.
const EMPTY_ID: u32 = u32::MAX;
/// Bit pattern of `+inf`, the depth of an empty pixel; above every finite positive depth.
const INF_BITS: u32 = 0x7f80_0000;
/// The CPU's near plane, in `f32`.
const NEAR: f32 = super::cpu::NEAR as f32;

/// A point: camera space `(x, y, z)`, or screen space with `z` holding `1/z`.
#[derive(CubeType, Clone, Copy)]
#[expand(derive(Clone))]
struct P3 {
    x: f32,
    y: f32,
    z: f32,
}

/// One edge function, as `cpu::Edge`.
#[derive(CubeType, Clone, Copy)]
#[expand(derive(Clone))]
struct Edge {
    ax: f32,
    ay: f32,
    dx: f32,
    dy: f32,
    sign: f32,
    owns_ties: bool,
    /// `false` when the opposite corner is on the line (zero area) or anything is non-finite.
    valid: bool,
}

#[cube]
fn edge_raw(ax: f32, ay: f32, dx: f32, dy: f32, x: f32, y: f32) -> f32 {
    dx * (y - ay) - dy * (x - ax)
}

/// The edge from `p` to `q`, evaluated from its canonically ordered endpoints (smaller
/// `(x, y)` first) and signed so that `opp` is on its positive side.
#[cube]
fn edge_new(p: &P3, q: &P3, opp: &P3) -> Edge {
    let p_first = p.x < q.x || (p.x == q.x && p.y <= q.y);
    let ax = select(p_first, p.x, q.x);
    let ay = select(p_first, p.y, q.y);
    let dx = select(p_first, q.x, p.x) - ax;
    let dy = select(p_first, q.y, p.y) - ay;
    let s = edge_raw(ax, ay, dx, dy, opp.x, opp.y);
    let valid = finite(s) && s != 0.0;
    let sign = select(s > 0.0, 1.0f32, -1.0f32);
    let sdx = dx * sign;
    let sdy = dy * sign;
    Edge {
        ax,
        ay,
        dx,
        dy,
        sign,
        owns_ties: sdy > 0.0 || (sdy == 0.0 && sdx < 0.0),
        valid,
    }
}

#[cube]
fn edge_value(e: &Edge, x: f32, y: f32) -> f32 {
    e.sign * edge_raw(e.ax, e.ay, e.dx, e.dy, x, y)
}

#[cube]
fn covered(e: &Edge, w: f32) -> bool {
    w > 0.0 || (w == 0.0 && e.owns_ties)
}

/// Camera-space position of vertex `v` (`[R | t]` applied to it), whose coordinates start at
/// `v·stride + offset` of `vertices` (`stride = 3`, `offset = 0` for one view's `[V, 3]`).
#[cube]
fn to_camera(view: &ViewArgs, vertices: &[f32], v: u32, stride: u32, offset: u32) -> P3 {
    let b = (v * stride + offset) as usize;
    let x = vertices[b];
    let y = vertices[b + 1];
    let z = vertices[b + 2];
    P3 {
        x: view.camera_x(x, y, z),
        y: view.camera_y(x, y, z),
        z: view.camera_z(x, y, z),
    }
}

/// The near-plane crossing of the segment, always computed from its inside endpoint.
#[cube]
fn clip_point(inside: &P3, outside: &P3) -> P3 {
    let t = (inside.z - NEAR) / (inside.z - outside.z);
    P3 {
        x: inside.x + (outside.x - inside.x) * t,
        y: inside.y + (outside.y - inside.y) * t,
        z: NEAR,
    }
}

/// Pixel coordinates and `1/z` of a camera-space point.
#[cube]
fn project(view: &ViewArgs, p: &P3) -> P3 {
    P3 {
        x: view.fx * p.x / p.z + view.cx,
        y: view.fy * p.y / p.z + view.cy,
        z: 1.0 / p.z,
    }
}

/// The first pixel (along one axis) whose centre `i + ½` is at or after `lo`, clamped at 0.
/// With [`last_pixel_plus_one`] this is the CPU's `pixel_range`; the range is empty when the
/// first is not below the end.
#[cube]
fn first_pixel(lo: f32) -> u32 {
    u32::cast_from(max((lo - 0.5).ceil(), 0.0f32))
}

/// One past the last pixel whose centre is at or before `hi`, clamped to the image.
#[cube]
fn last_pixel_plus_one(hi: f32, size: u32) -> u32 {
    // `min` keeps the cast defined for coordinates far off-screen.
    let last = min((hi - 0.5).floor(), f32::cast_from(size) - 1.0);
    select(last < 0.0, 0u32, u32::cast_from(last) + 1)
}

/// Depth-tests one screen triangle into the buffers (pass 1: depths; pass 2: ids).
#[cube]
#[allow(clippy::too_many_arguments)]
fn raster_screen_tri(
    p0: &P3,
    p1: &P3,
    p2: &P3,
    face: u32,
    depth_bits: &[Atomic<u32>],
    ids: &[Atomic<u32>],
    width: u32,
    height: u32,
    first_pixel_of_view: u32,
    #[comptime] ids_pass: bool,
) {
    let e0 = edge_new(p1, p2, p0);
    let e1 = edge_new(p2, p0, p1);
    let e2 = edge_new(p0, p1, p2);
    let all_finite = finite(p0.x)
        && finite(p0.y)
        && finite(p1.x)
        && finite(p1.y)
        && finite(p2.x)
        && finite(p2.y);
    if all_finite && e0.valid && e1.valid && e2.valid {
        let i0 = first_pixel(min(min(p0.x, p1.x), p2.x));
        let i1 = last_pixel_plus_one(max(max(p0.x, p1.x), p2.x), width);
        let j0 = first_pixel(min(min(p0.y, p1.y), p2.y));
        let j1 = last_pixel_plus_one(max(max(p0.y, p1.y), p2.y), height);
        for j in j0..j1 {
            let y = f32::cast_from(j) + 0.5;
            for i in i0..i1 {
                let x = f32::cast_from(i) + 0.5;
                let w0 = edge_value(&e0, x, y);
                let w1 = edge_value(&e1, x, y);
                let w2 = edge_value(&e2, x, y);
                let sum = w0 + w1 + w2;
                if covered(&e0, w0) && covered(&e1, w1) && covered(&e2, w2) && sum > 0.0 {
                    let inv_z = (w0 * p0.z + w1 * p1.z + w2 * p2.z) / sum;
                    let z = 1.0 / inv_z;
                    if finite(z) && z > 0.0 {
                        let bits = u32::reinterpret(z);
                        let pix = (first_pixel_of_view + j * width + i) as usize;
                        if ids_pass {
                            if bits <= depth_bits[pix].load() {
                                ids[pix].fetch_min(face);
                            }
                        } else {
                            depth_bits[pix].fetch_min(bits);
                        }
                    }
                }
            }
        }
    }
}

/// One thread per (view, face): clip, project and rasterize the face in its view (see the
/// module docs for the passes). View `k`'s vertex `v` is at `[v·3n + 3k]` of `vertices`, its
/// camera row `k` of `cameras`, its pixels at `[k·H·W, (k + 1)·H·W)` of the buffers.
#[cube(launch)]
#[allow(clippy::too_many_arguments)]
fn raster_faces_kernel(
    vertices: &[f32],
    faces: &[i32],
    cameras: &[f32],
    depth_bits: &[Atomic<u32>],
    ids: &[Atomic<u32>],
    num_vertices: u32,
    num_faces: u32,
    views: u32,
    #[comptime] ids_pass: bool,
) {
    let face = ABSOLUTE_POS as u32 % num_faces;
    let k = ABSOLUTE_POS as u32 / num_faces;
    if k < views {
        let view = camera_of(cameras, k);
        let width = view.width;
        let height = view.height;
        let first_pixel_of_view = k * width * height;
        let stride = 3 * views;
        let offset = 3 * k;
        let f = (3 * face) as usize;
        let ia = faces[f];
        let ib = faces[f + 1];
        let ic = faces[f + 2];
        let nv = i32::cast_from(num_vertices);
        if ia >= 0 && ib >= 0 && ic >= 0 && ia < nv && ib < nv && ic < nv {
            let a = to_camera(&view, vertices, u32::cast_from(ia), stride, offset);
            let b = to_camera(&view, vertices, u32::cast_from(ib), stride, offset);
            let c = to_camera(&view, vertices, u32::cast_from(ic), stride, offset);
            let all_finite = finite(a.x)
                && finite(a.y)
                && finite(a.z)
                && finite(b.x)
                && finite(b.y)
                && finite(b.z)
                && finite(c.x)
                && finite(c.y)
                && finite(c.z);
            let a_in = a.z >= NEAR;
            let b_in = b.z >= NEAR;
            let c_in = c.z >= NEAR;
            let n_in = u32::cast_from(a_in) + u32::cast_from(b_in) + u32::cast_from(c_in);
            if all_finite && n_in == 3 {
                let sa = project(&view, &a);
                let sb = project(&view, &b);
                let sc = project(&view, &c);
                raster_screen_tri(
                    &sa,
                    &sb,
                    &sc,
                    face,
                    depth_bits,
                    ids,
                    width,
                    height,
                    first_pixel_of_view,
                    ids_pass,
                );
            } else if all_finite && n_in == 2 {
                // Rotate (keeping the winding) so that `r` is the corner behind the plane; the
                // clipped polygon is the quad `p, q, qr, pr`, fanned from `p`.
                let p = choose(!a_in, &b, !b_in, &c, &a);
                let q = choose(!a_in, &c, !b_in, &a, &b);
                let r = choose(!a_in, &a, !b_in, &b, &c);
                let qr = clip_point(&q, &r);
                let pr = clip_point(&p, &r);
                let sp = project(&view, &p);
                let sq = project(&view, &q);
                let sqr = project(&view, &qr);
                let spr = project(&view, &pr);
                raster_screen_tri(
                    &sp,
                    &sq,
                    &sqr,
                    face,
                    depth_bits,
                    ids,
                    width,
                    height,
                    first_pixel_of_view,
                    ids_pass,
                );
                raster_screen_tri(
                    &sp,
                    &sqr,
                    &spr,
                    face,
                    depth_bits,
                    ids,
                    width,
                    height,
                    first_pixel_of_view,
                    ids_pass,
                );
            } else if all_finite && n_in == 1 {
                // Rotate so that `p` is the corner in front; the clipped polygon is a triangle.
                let p = choose(b_in, &b, c_in, &c, &a);
                let q = choose(b_in, &c, c_in, &a, &b);
                let r = choose(b_in, &a, c_in, &b, &c);
                let pq = clip_point(&p, &q);
                let pr = clip_point(&p, &r);
                let sp = project(&view, &p);
                let spq = project(&view, &pq);
                let spr = project(&view, &pr);
                raster_screen_tri(
                    &sp,
                    &spq,
                    &spr,
                    face,
                    depth_bits,
                    ids,
                    width,
                    height,
                    first_pixel_of_view,
                    ids_pass,
                );
            }
        }
    }
}

/// `if first { x } else if second { y } else { z }`, field by field (struct values cannot be
/// reassigned in branches of a kernel).
#[cube]
fn choose(first: bool, x: &P3, second: bool, y: &P3, z: &P3) -> P3 {
    P3 {
        x: select(first, x.x, select(second, y.x, z.x)),
        y: select(first, x.y, select(second, y.y, z.y)),
        z: select(first, x.z, select(second, y.z, z.z)),
    }
}

/// `data[i] = value` for `i < n`.
#[cube(launch)]
fn fill_kernel(data: &mut [u32], value: u32, n: u32) {
    let i = ABSOLUTE_POS as u32;
    if i < n {
        data[i as usize] = value;
    }
}

/// Per pixel: the public `-1` / `+inf` encoding of empty pixels.
#[cube(launch)]
fn resolve_kernel(
    depth_bits: &[u32],
    ids: &[u32],
    face_ids: &mut [i32],
    depth: &mut [f32],
    num_pixels: u32,
) {
    let p = ABSOLUTE_POS as u32;
    if p < num_pixels {
        let id = ids[p as usize];
        if id == EMPTY_ID {
            face_ids[p as usize] = -1i32;
            depth[p as usize] = f32::reinterpret(INF_BITS);
        } else {
            face_ids[p as usize] = i32::cast_from(id);
            depth[p as usize] = f32::reinterpret(depth_bits[p as usize]);
        }
    }
}

/// Per pixel: marks the three vertices of the owning face. Every writer stores the same 1, so
/// the (atomic) stores need no ordering.
#[cube(launch)]
fn mark_visible_kernel(
    face_ids: &[i32],
    faces: &[i32],
    visible: &[Atomic<u32>],
    num_pixels: u32,
    num_faces: u32,
    num_vertices: u32,
) {
    let p = ABSOLUTE_POS as u32;
    if p < num_pixels {
        let id = face_ids[p as usize];
        if id >= 0 && id < i32::cast_from(num_faces) {
            for k in 0..3u32 {
                let v = faces[(3 * u32::cast_from(id) + k) as usize];
                if v >= 0 && v < i32::cast_from(num_vertices) {
                    visible[v as usize].store(1u32);
                }
            }
        }
    }
}

/// The buffers' start: `depth_bits` and `ids` (`pixels` each) at `+inf` and "no face", and
/// `visible` (`vertices`) at 0, in one launch over the longer.
#[cube(launch)]
fn start_views_kernel(
    depth_bits: &mut [u32],
    ids: &mut [u32],
    visible: &mut [u32],
    pixels: u32,
    vertices: u32,
) {
    let i = ABSOLUTE_POS as u32;
    if i < pixels {
        depth_bits[i as usize] = INF_BITS;
        ids[i as usize] = EMPTY_ID;
    }
    if i < vertices {
        visible[i as usize] = 0u32;
    }
}

/// Per pixel of every view (view `k`'s pixels at `[k·pixels_per_view, …)`): marks the three
/// vertices of the owning face in the view's row of `visible` (`[views, num_vertices]`), reading
/// the raw ID buffer (`EMPTY_ID` where no face). Every writer stores the same 1.
#[cube(launch)]
#[allow(clippy::too_many_arguments)]
fn mark_views_kernel(
    ids: &[u32],
    faces: &[i32],
    visible: &[Atomic<u32>],
    pixels_per_view: u32,
    views: u32,
    num_faces: u32,
    num_vertices: u32,
) {
    let p = ABSOLUTE_POS as u32;
    if p < pixels_per_view * views {
        let id = ids[p as usize];
        if id < num_faces {
            let row = (p / pixels_per_view) * num_vertices;
            for k in 0..3u32 {
                let v = faces[(3 * id + k) as usize];
                if v >= 0 && v < i32::cast_from(num_vertices) {
                    visible[(row + u32::cast_from(v)) as usize].store(1u32);
                }
            }
        }
    }
}

/// One thread per (row, view), `[row, view]` at `row·views + view`: the first `lowres` vertices'
/// flags and every face's (1 when its three corners are visible in the view; 0 for a corner
/// outside the vertices), as floats.
#[cube(launch)]
#[allow(clippy::too_many_arguments)]
fn view_flags_kernel(
    visible: &[u32],
    faces: &[i32],
    vertex_flags: &mut [f32],
    face_flags: &mut [f32],
    lowres: u32,
    num_faces: u32,
    num_vertices: u32,
    views: u32,
) {
    let row = ABSOLUTE_POS as u32 / views;
    let k = ABSOLUTE_POS as u32 % views;
    let out = (row * views + k) as usize;
    let visible_row = k * num_vertices;
    if row < lowres {
        vertex_flags[out] = f32::cast_from(visible[(visible_row + row) as usize]);
    }
    if row < num_faces {
        let mut all = 1u32;
        for c in 0..3u32 {
            let v = faces[(3 * row + c) as usize];
            if v >= 0 && v < i32::cast_from(num_vertices) {
                all = min(all, visible[(visible_row + u32::cast_from(v)) as usize]);
            } else {
                all = 0u32;
            }
        }
        face_flags[out] = f32::cast_from(all);
    }
}

/// [`start_views_kernel`] over `pixels` depth and ID slots and `vertices` vertex flags.
fn start_views(
    client: &ComputeClient,
    depth_bits: &Handle,
    ids: &Handle,
    visible: &Handle,
    pixels: usize,
    vertices: usize,
) {
    start_views_kernel::launch(
        client,
        count_1d(pixels.max(vertices)),
        CubeDim::new_1d(THREADS_1D),
        arg(depth_bits, pixels),
        arg(ids, pixels),
        arg(visible, vertices),
        pixels as u32,
        vertices as u32,
    );
}

/// Both passes of [`raster_faces_kernel`] over `views` views of `pixels` pixels each.
#[allow(clippy::too_many_arguments)]
fn raster_views(
    client: &ComputeClient,
    vertices: &CubeTensor,
    faces: &CubeTensor,
    cameras: &Handle,
    depth_bits: &Handle,
    ids: &Handle,
    num_vertices: usize,
    views: usize,
    pixels: usize,
) {
    let num_faces = faces.shape().num_elements() / 3;
    if num_faces == 0 || num_vertices == 0 || views == 0 {
        return;
    }
    for ids_pass in [false, true] {
        raster_faces_kernel::launch(
            client,
            count_1d(num_faces * views),
            CubeDim::new_1d(THREADS_1D),
            vertices.clone().into_buffer_arg(),
            faces.clone().into_buffer_arg(),
            arg(cameras, CAMERA_FLOATS * views),
            arg(depth_bits, pixels * views),
            arg(ids, pixels * views),
            num_vertices as u32,
            num_faces as u32,
            views as u32,
            ids_pass,
        );
    }
}

fn fill(client: &ComputeClient, handle: &Handle, value: u32, len: usize) {
    fill_kernel::launch(
        client,
        count_1d(len),
        CubeDim::new_1d(THREADS_1D),
        arg(handle, len),
        value,
        len as u32,
    );
}

impl TriangleIdOps for CubeBackend {
    fn rasterize_triangle_ids(
        vertices: FloatTensor<Self>,
        faces: IntTensor<Self>,
        camera: Camera,
    ) -> (IntTensor<Self>, FloatTensor<Self>) {
        let _span = tracing::trace_span!("cube_triangle_ids").entered();
        let vertices = prepare(vertices);
        let faces = prepare_i32(faces);
        let client = vertices.client.clone();
        let device = vertices.device.clone();
        let num_vertices = vertices.shape().num_elements() / 3;
        let (width, height) = (camera.width, camera.height);
        let pixels = width as usize * height as usize;

        let cameras = camera_table(&client, &[camera.view_params()]);
        let depth_bits = empty_u32(&client, pixels);
        let ids = empty_u32(&client, pixels);
        // No vertex flags here: a one-element stand-in the start kernel leaves alone.
        start_views(
            &client,
            &depth_bits,
            &ids,
            &empty_u32(&client, 1),
            pixels,
            0,
        );
        raster_views(
            &client,
            &vertices,
            &faces,
            &cameras,
            &depth_bits,
            &ids,
            num_vertices,
            1,
            pixels,
        );
        let face_ids = empty_u32(&client, pixels);
        let depth = empty_u32(&client, pixels);
        resolve_kernel::launch(
            &client,
            count_1d(pixels),
            CubeDim::new_1d(THREADS_1D),
            arg(&depth_bits, pixels),
            arg(&ids, pixels),
            arg(&face_ids, pixels),
            arg(&depth, pixels),
            pixels as u32,
        );
        let shape = [height as usize, width as usize];
        (
            tensor_of(&client, &device, face_ids, &shape, DType::I32),
            tensor_of(&client, &device, depth, &shape, DType::F32),
        )
    }

    fn visible_vertices(
        face_ids: IntTensor<Self>,
        faces: IntTensor<Self>,
        num_vertices: usize,
    ) -> IntTensor<Self> {
        let _span = tracing::trace_span!("cube_visible_vertices").entered();
        let face_ids = prepare_i32(face_ids);
        let faces = prepare_i32(faces);
        let client = faces.client.clone();
        let device = faces.device.clone();
        let pixels = face_ids.shape().num_elements();
        let num_faces = faces.shape().num_elements() / 3;
        let visible = empty_u32(&client, num_vertices);
        fill(&client, &visible, 0, num_vertices);
        if pixels > 0 && num_faces > 0 && num_vertices > 0 {
            mark_visible_kernel::launch(
                &client,
                count_1d(pixels),
                CubeDim::new_1d(THREADS_1D),
                face_ids.into_buffer_arg(),
                faces.into_buffer_arg(),
                arg(&visible, num_vertices),
                pixels as u32,
                num_faces as u32,
                num_vertices as u32,
            );
        }
        tensor_of(&client, &device, visible, &[num_vertices], DType::I32)
    }

    fn visibility_in_views(
        vertices: FloatTensor<Self>,
        faces: IntTensor<Self>,
        views: ViewSet,
    ) -> (FloatTensor<Self>, FloatTensor<Self>) {
        let _span = tracing::trace_span!("cube_visibility_in_views").entered();
        let vertices = prepare(vertices);
        let faces = prepare_i32(faces);
        let client = vertices.client.clone();
        let device = vertices.device.clone();
        let n = views.cameras.len();
        let num_vertices = vertices.shape().num_elements() / (3 * n).max(1);
        let num_faces = faces.shape().num_elements() / 3;
        let pixels = views
            .cameras
            .first()
            .map_or(0, |c| c.width as usize * c.height as usize);
        let (all_pixels, all_vertices) = (pixels * n, num_vertices * n);

        let params: Vec<ViewParams> = views.cameras.iter().map(Camera::view_params).collect();
        let cameras = camera_table(&client, &params);
        let depth_bits = empty_u32(&client, all_pixels);
        let ids = empty_u32(&client, all_pixels);
        let visible = empty_u32(&client, all_vertices);
        start_views(
            &client,
            &depth_bits,
            &ids,
            &visible,
            all_pixels,
            all_vertices,
        );
        raster_views(
            &client,
            &vertices,
            &faces,
            &cameras,
            &depth_bits,
            &ids,
            num_vertices,
            n,
            pixels,
        );
        if all_pixels > 0 && num_faces > 0 && num_vertices > 0 {
            mark_views_kernel::launch(
                &client,
                count_1d(all_pixels),
                CubeDim::new_1d(THREADS_1D),
                arg(&ids, all_pixels),
                faces.clone().into_buffer_arg(),
                arg(&visible, all_vertices),
                pixels as u32,
                n as u32,
                num_faces as u32,
                num_vertices as u32,
            );
        }
        let lowres = views.lowres.min(num_vertices);
        let vertex_flags = empty_u32(&client, lowres * n);
        let face_flags = empty_u32(&client, num_faces * n);
        if n > 0 && lowres.max(num_faces) > 0 {
            view_flags_kernel::launch(
                &client,
                count_1d(lowres.max(num_faces) * n),
                CubeDim::new_1d(THREADS_1D),
                arg(&visible, all_vertices),
                faces.into_buffer_arg(),
                arg(&vertex_flags, lowres * n),
                arg(&face_flags, num_faces * n),
                lowres as u32,
                num_faces as u32,
                num_vertices as u32,
                n as u32,
            );
        }
        (
            tensor_of(&client, &device, vertex_flags, &[lowres, n], DType::F32),
            tensor_of(&client, &device, face_flags, &[num_faces, n], DType::F32),
        )
    }
}
