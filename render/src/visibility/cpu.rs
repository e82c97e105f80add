//! The CPU reference of the triangle-ID z-buffer: which face is nearest at each pixel, for
//! visibility only (design.md §6.7).
//!
//! The official code rasterises the posed high-res mesh with nvdiffrast per source view and calls
//! a vertex visible if any face containing it owns at least one pixel. This module does the same
//! on the CPU, without gradients; the GPU kernels (`super::cube`) follow it step by step in `f32`.
//!
//! # Pipeline
//!
//! 1. World → camera space (OpenCV axes, [`Camera::world_to_camera`]).
//! 2. Near-plane clipping at `z = 1e-3` (Sutherland–Hodgman against one plane): a triangle fully
//!    in front is kept, one fully behind is dropped, one crossing the plane becomes a triangle or
//!    a quad (fanned into 2 triangles). The far plane is not clipped.
//! 3. Projection with the camera's pixel convention: pixel `(i, j)` is sampled at its centre
//!    `(i + ½, j + ½)`, the same points the Gaussian rasterizer samples.
//! 4. Coverage by edge functions in `f64`, then a depth test on perspective-correct depth: `1/z`
//!    is affine in screen space, so it is interpolated with the screen-space barycentrics.
//!    Nearer wins; equal depths go to the lower face id.
//!
//! # Watertightness
//!
//! A pixel centre on an edge shared by two triangles must be covered by exactly one of them, or
//! closed meshes get cracks (and spurious visibility through them). Two things guarantee it:
//!
//! - Each edge function is evaluated from the edge's endpoints in a *canonical* order (smaller
//!   screen point first) and only then negated to face the triangle's interior. Both triangles
//!   sharing an edge therefore compute bit-identical values of opposite sign, so `E > 0` holds in
//!   at most one of them. Clipped vertices are computed from the inside endpoint towards the
//!   outside one, so neighbours that share a clipped edge also share its new endpoint exactly.
//! - When `E == 0` exactly, a tie rule picks one side: the oriented edge owns the sample iff its
//!   direction `(dx, dy)` has `dy > 0`, or `dy == 0 && dx < 0`. Exactly one of `d` and `−d`
//!   passes. This equals moving the sample by an infinitesimal `(−ε, −ε²)`, so it also resolves
//!   samples that fall exactly on a shared vertex (one triangle of the fan owns it).
//!
//! Zero-area triangles (and degenerate faces with a repeated index) cover nothing.
//!
//! # Parallelism and determinism
//!
//! Rows are split into bands of [`BAND_ROWS`]; each triangle is binned into the bands its rows
//! touch, and rayon processes bands in parallel, each writing only its own rows. Every pixel
//! keeps the lexicographic minimum of `(depth, face id)` over the triangles covering it, which
//! does not depend on processing order, so the output is identical for any thread count.

use glam::{DVec2, DVec3, Vec3};
use rayon::prelude::*;

use crate::camera::Camera;
use crate::error::{RenderError, Result};

/// Near clipping plane in camera space, as the reference's OpenGL-style projection uses.
pub const NEAR: f64 = 1e-3;

/// Rows per work item. Small enough to balance across threads, large enough that binning
/// overhead stays small.
pub const BAND_ROWS: u32 = 16;

/// Nearest face id and its depth per pixel, row-major (`j * width + i`).
#[derive(Debug, Clone, PartialEq)]
pub struct TriangleIdBuffer {
    /// Image width in pixels.
    pub width: u32,
    /// Image height in pixels.
    pub height: u32,
    /// Face id owning each pixel, `-1` where no face covers it.
    pub face_ids: Vec<i32>,
    /// Camera-space depth `z` of the owning face at the pixel centre, `+inf` where empty.
    pub depth: Vec<f32>,
}

impl TriangleIdBuffer {
    /// The face owning pixel `(i, j)`, if any.
    pub fn face_at(&self, i: u32, j: u32) -> Option<u32> {
        let id = self.face_ids[j as usize * self.width as usize + i as usize];
        (id >= 0).then_some(id as u32)
    }
}

/// Rasterises `faces` over world-space `vertices` into a triangle-ID buffer of the camera's size.
///
/// Fails with [`RenderError::NonFinite`] on a non-finite vertex (flat index into `vertices` as
/// `[V, 3]`), with [`RenderError::InvalidInput`] on a face index past the vertex list or more
/// faces than an `i32` id can name, and with [`RenderError::InvalidCamera`] on an invalid camera.
pub fn rasterize_triangle_ids(
    vertices: &[Vec3],
    faces: &[[u32; 3]],
    camera: &Camera,
) -> Result<TriangleIdBuffer> {
    let _span = tracing::trace_span!(
        "rasterize_triangle_ids",
        faces = faces.len(),
        width = camera.width,
        height = camera.height
    )
    .entered();
    camera.validate()?;
    if let Some(v) = vertices.iter().position(|v| !v.is_finite()) {
        let k = vertices[v]
            .to_array()
            .iter()
            .position(|x| !x.is_finite())
            .unwrap_or(0);
        return Err(RenderError::NonFinite {
            tensor: "vertices",
            index: 3 * v + k,
        });
    }
    if faces.len() > i32::MAX as usize {
        return Err(RenderError::InvalidInput {
            what: "faces",
            reason: format!("{} faces do not fit i32 face ids", faces.len()),
        });
    }
    for (f, face) in faces.iter().enumerate() {
        if let Some(corner) = face.iter().position(|&v| v as usize >= vertices.len()) {
            return Err(RenderError::InvalidInput {
                what: "faces",
                reason: format!(
                    "face {f} corner {corner} has vertex index {}, but there are {} vertices",
                    face[corner],
                    vertices.len()
                ),
            });
        }
    }

    Ok(rasterize_unchecked(vertices, faces, camera))
}

/// [`rasterize_triangle_ids`] without the input checks, for callers that cannot return an error
/// (the Burn op): a face with a vertex index past the list or a non-finite corner covers
/// nothing. The camera must be valid.
pub(crate) fn rasterize_unchecked(
    vertices: &[Vec3],
    faces: &[[u32; 3]],
    camera: &Camera,
) -> TriangleIdBuffer {
    let (width, height) = (camera.width, camera.height);
    let cam: Vec<DVec3> = vertices
        .par_iter()
        .map(|&v| camera.world_to_camera(v).as_dvec3())
        .collect();
    let projector = Projector::new(camera);
    let tris: Vec<ScreenTri> = faces
        .par_iter()
        .enumerate()
        .filter_map(|(f, face)| {
            let corners = face.map(|v| cam.get(v as usize).copied());
            match corners {
                [Some(a), Some(b), Some(c)] if a.is_finite() && b.is_finite() && c.is_finite() => {
                    Some((f, [a, b, c]))
                }
                _ => None,
            }
        })
        .flat_map_iter(|(f, corners)| clip_and_project(f as u32, corners, &projector))
        .collect();

    let num_bands = height.div_ceil(BAND_ROWS) as usize;
    let mut bins: Vec<Vec<u32>> = vec![Vec::new(); num_bands];
    for (t, tri) in tris.iter().enumerate() {
        for band in (tri.rows.0 / BAND_ROWS)..=(tri.rows.1 / BAND_ROWS) {
            bins[band as usize].push(t as u32);
        }
    }

    let mut face_ids = vec![-1i32; width as usize * height as usize];
    let mut depth = vec![f32::INFINITY; width as usize * height as usize];
    let band_len = BAND_ROWS as usize * width as usize;
    face_ids
        .par_chunks_mut(band_len)
        .zip(depth.par_chunks_mut(band_len))
        .zip(&bins)
        .enumerate()
        .for_each(|(band, ((ids, depths), bin))| {
            let rows = (
                band as u32 * BAND_ROWS,
                ((band as u32 + 1) * BAND_ROWS).min(height) - 1,
            );
            for &t in bin {
                raster_into_band(&tris[t as usize], rows, width, ids, depths);
            }
        });
    TriangleIdBuffer {
        width,
        height,
        face_ids,
        depth,
    }
}

/// Faces that own at least one pixel of `buffer`. Ids `≥ num_faces` are ignored.
pub fn visible_faces(buffer: &TriangleIdBuffer, num_faces: usize) -> Vec<bool> {
    let mut visible = vec![false; num_faces];
    for &id in &buffer.face_ids {
        if id >= 0 && (id as usize) < num_faces {
            visible[id as usize] = true;
        }
    }
    visible
}

/// Vertices of at least one face that owns a pixel of `buffer` (design.md §6.7). For a subdivided
/// mesh, the first `V↓` entries are the low-res visibility.
///
/// # Panics
///
/// If a face that owns a pixel has an index `≥ num_vertices` (the faces must be the ones that
/// were rasterised).
pub fn visible_vertices(
    buffer: &TriangleIdBuffer,
    faces: &[[u32; 3]],
    num_vertices: usize,
) -> Vec<bool> {
    let mut visible = vec![false; num_vertices];
    for (f, _) in visible_faces(buffer, faces.len())
        .iter()
        .enumerate()
        .filter(|(_, v)| **v)
    {
        for &v in &faces[f] {
            assert!(
                (v as usize) < num_vertices,
                "visible_vertices: face {f} has vertex index {v}, but num_vertices is {num_vertices}"
            );
            visible[v as usize] = true;
        }
    }
    visible
}

/// Camera-space → pixel coordinates, in `f64`.
struct Projector {
    f: DVec2,
    c: DVec2,
    width: u32,
    height: u32,
}

impl Projector {
    fn new(camera: &Camera) -> Self {
        let k = &camera.intrinsics;
        Self {
            f: DVec2::new(k.fx as f64, k.fy as f64),
            c: DVec2::new(k.cx as f64, k.cy as f64),
            width: camera.width,
            height: camera.height,
        }
    }

    fn project(&self, p: DVec3) -> DVec2 {
        self.f * DVec2::new(p.x, p.y) / p.z + self.c
    }
}

/// A projected (possibly clipped) triangle: screen corners, their `1/z`, the face it came from,
/// and the inclusive range of pixel rows whose centres its bounding box spans.
struct ScreenTri {
    p: [DVec2; 3],
    inv_z: [f64; 3],
    face: u32,
    rows: (u32, u32),
    cols: (u32, u32),
}

/// Clips one camera-space triangle against the near plane and projects what is left: 0, 1 or 2
/// screen triangles, all tagged with `face`.
fn clip_and_project(
    face: u32,
    corners: [DVec3; 3],
    proj: &Projector,
) -> impl Iterator<Item = ScreenTri> {
    // At most 4 vertices survive clipping one triangle against one plane.
    let mut poly = [DVec3::ZERO; 4];
    let mut n = 0;
    for k in 0..3 {
        let (cur, next) = (corners[k], corners[(k + 1) % 3]);
        let (cur_in, next_in) = (cur.z >= NEAR, next.z >= NEAR);
        if cur_in {
            poly[n] = cur;
            n += 1;
        }
        if cur_in != next_in {
            // Always from the inside endpoint to the outside one, so a neighbour sharing this
            // edge (traversed the other way) computes the bit-identical point.
            let (inside, outside) = if cur_in { (cur, next) } else { (next, cur) };
            let t = (inside.z - NEAR) / (inside.z - outside.z);
            let mut p = inside + (outside - inside) * t;
            p.z = NEAR;
            poly[n] = p;
            n += 1;
        }
    }
    let screen = poly.map(|p| (proj.project(p), 1.0 / p.z));
    let fan: [Option<[usize; 3]>; 2] = match n {
        3 => [Some([0, 1, 2]), None],
        4 => [Some([0, 1, 2]), Some([0, 2, 3])],
        _ => [None, None],
    };
    let (w, h) = (proj.width, proj.height);
    fan.into_iter().flatten().filter_map(move |idx| {
        let p = idx.map(|i| screen[i].0);
        let inv_z = idx.map(|i| screen[i].1);
        let cols = pixel_range(
            p[0].x.min(p[1].x).min(p[2].x),
            p[0].x.max(p[1].x).max(p[2].x),
            w,
        )?;
        let rows = pixel_range(
            p[0].y.min(p[1].y).min(p[2].y),
            p[0].y.max(p[1].y).max(p[2].y),
            h,
        )?;
        Some(ScreenTri {
            p,
            inv_z,
            face,
            rows,
            cols,
        })
    })
}

/// Inclusive range of pixels (along one axis) whose centres `i + ½` lie in `[lo, hi]`, clamped to
/// the image; `None` if empty.
fn pixel_range(lo: f64, hi: f64, size: u32) -> Option<(u32, u32)> {
    // Float-to-int `as` saturates, so far-off (clipped, huge) coordinates clamp safely.
    let first = (lo - 0.5).ceil().max(0.0);
    let last = (hi - 0.5).floor().min(size as f64 - 1.0);
    (first <= last).then_some((first as u32, last as u32))
}

/// One edge as `E(x) = dx·(x.y − a.y) − dy·(x.x − a.x)`, evaluated from canonically ordered
/// endpoints and multiplied by `sign` so that the interior is positive (module docs).
struct Edge {
    a: DVec2,
    d: DVec2,
    sign: f64,
    owns_ties: bool,
}

impl Edge {
    /// The edge from `p` to `q`, oriented so that `opposite` is on its positive side. `None` if
    /// `opposite` is on the line (zero-area triangle).
    fn new(p: DVec2, q: DVec2, opposite: DVec2) -> Option<Self> {
        let (a, b) = if (p.x, p.y) <= (q.x, q.y) {
            (p, q)
        } else {
            (q, p)
        };
        let mut edge = Edge {
            a,
            d: b - a,
            sign: 1.0,
            owns_ties: false,
        };
        let s = edge.raw(opposite);
        if s == 0.0 || !s.is_finite() {
            return None;
        }
        edge.sign = s.signum();
        let d = edge.d * edge.sign;
        edge.owns_ties = d.y > 0.0 || (d.y == 0.0 && d.x < 0.0);
        Some(edge)
    }

    fn raw(&self, x: DVec2) -> f64 {
        self.d.x * (x.y - self.a.y) - self.d.y * (x.x - self.a.x)
    }

    fn eval(&self, x: DVec2) -> f64 {
        self.sign * self.raw(x)
    }

    fn covers(&self, e: f64) -> bool {
        e > 0.0 || (e == 0.0 && self.owns_ties)
    }
}

/// Depth-tests `tri` into the rows `rows` (inclusive) of one band. `ids`/`depths` hold exactly
/// those rows.
fn raster_into_band(
    tri: &ScreenTri,
    rows: (u32, u32),
    width: u32,
    ids: &mut [i32],
    depths: &mut [f32],
) {
    let [p0, p1, p2] = tri.p;
    // Edge k is opposite corner k, so its value is proportional to corner k's barycentric.
    let (Some(e0), Some(e1), Some(e2)) = (
        Edge::new(p1, p2, p0),
        Edge::new(p2, p0, p1),
        Edge::new(p0, p1, p2),
    ) else {
        return;
    };
    let face = tri.face as i32;
    let (j0, j1) = (tri.rows.0.max(rows.0), tri.rows.1.min(rows.1));
    for j in j0..=j1 {
        let y = j as f64 + 0.5;
        let row = (j - rows.0) as usize * width as usize;
        for i in tri.cols.0..=tri.cols.1 {
            let x = DVec2::new(i as f64 + 0.5, y);
            let (w0, w1, w2) = (e0.eval(x), e1.eval(x), e2.eval(x));
            if !(e0.covers(w0) && e1.covers(w1) && e2.covers(w2)) {
                continue;
            }
            // All three are ≥ 0 here, so the sum is 0 only on a zero-area remnant.
            let sum = w0 + w1 + w2;
            if sum <= 0.0 {
                continue;
            }
            let inv_z = (w0 * tri.inv_z[0] + w1 * tri.inv_z[1] + w2 * tri.inv_z[2]) / sum;
            let z = (1.0 / inv_z) as f32;
            let slot = row + i as usize;
            if z < depths[slot] || (z == depths[slot] && face < ids[slot]) {
                depths[slot] = z;
                ids[slot] = face;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use glam::Affine3A;

    use super::*;
    use crate::camera::Intrinsics;
    use crate::subdivision::Subdivision;
    use crate::testing::{octahedron, pixel_camera};

    /// The corners at pixel coordinates `uv` and depth `z`, for [`pixel_camera`].
    fn at_depth(uv: [(f32, f32); 3], z: f32) -> Vec<Vec3> {
        uv.iter()
            .map(|&(u, v)| Vec3::new(u * z, v * z, z))
            .collect()
    }

    /// Independent inside test: strictly inside by barycentric signs (tests avoid exact ties).
    fn inside(p: [(f64, f64); 3], x: f64, y: f64) -> bool {
        let cross =
            |a: (f64, f64), b: (f64, f64)| (b.0 - a.0) * (y - a.1) - (b.1 - a.1) * (x - a.0);
        let s = [cross(p[0], p[1]), cross(p[1], p[2]), cross(p[2], p[0])];
        s.iter().all(|&v| v > 0.0) || s.iter().all(|&v| v < 0.0)
    }

    fn count(buf: &TriangleIdBuffer, face: i32) -> usize {
        buf.face_ids.iter().filter(|&&f| f == face).count()
    }

    #[test]
    fn single_triangle_covers_exactly_the_centres_inside() {
        let (w, h) = (37, 29);
        let uv = [(2.3, 1.7), (33.1, 9.2), (11.4, 26.9)];
        for (z, winding) in [(1.0, [0, 1, 2]), (2.5, [0, 2, 1])] {
            let verts = at_depth(uv, z);
            let buf = rasterize_triangle_ids(&verts, &[winding], &pixel_camera(w, h)).unwrap();
            let p = uv.map(|(u, v)| (u as f64, v as f64));
            let mut n = 0;
            for j in 0..h {
                for i in 0..w {
                    let want = inside(p, i as f64 + 0.5, j as f64 + 0.5);
                    assert_eq!(buf.face_at(i, j).is_some(), want, "pixel ({i}, {j})");
                    if want {
                        n += 1;
                        let d = buf.depth[(j * w + i) as usize];
                        assert!((d - z).abs() < 1e-5 * z, "{d} vs {z}");
                    }
                }
            }
            assert!(n > 100, "{n}");
            assert_eq!(count(&buf, 0), n);
        }
    }

    #[test]
    fn nearer_triangle_wins_and_depth_is_perspective_correct() {
        let big = [(0.0, 0.0), (40.0, 0.0), (0.0, 40.0)];
        let mut verts = at_depth(big, 3.0);
        verts.extend(at_depth([(1.0, 1.0), (20.0, 1.0), (1.0, 20.0)], 2.0));
        // Face 0 is the far one; face 1 (near) must win where they overlap.
        let buf =
            rasterize_triangle_ids(&verts, &[[0, 1, 2], [3, 4, 5]], &pixel_camera(32, 32)).unwrap();
        assert_eq!(buf.face_at(5, 5), Some(1));
        assert_eq!(buf.face_at(25, 2), Some(0));
        // Same triangles, near one listed first: same answer (order independent).
        let buf2 =
            rasterize_triangle_ids(&verts, &[[3, 4, 5], [0, 1, 2]], &pixel_camera(32, 32)).unwrap();
        assert_eq!(buf2.face_at(5, 5), Some(0));
        assert_eq!(count(&buf2, 0), count(&buf, 1));

        // A slanted triangle: the z-buffer depth must be the ray's hit depth, not linear-in-screen z.
        let slanted = vec![
            Vec3::new(-1.0, -1.0, 1.0),
            Vec3::new(4.0, -1.0, 4.0),
            Vec3::new(-1.0, 3.0, 1.0),
        ];
        let cam = Camera::new(
            Intrinsics {
                fx: 10.0,
                fy: 10.0,
                cx: 16.0,
                cy: 16.0,
            },
            Affine3A::IDENTITY,
            32,
            32,
        )
        .unwrap();
        let buf = rasterize_triangle_ids(&slanted, &[[0, 1, 2]], &cam).unwrap();
        let n = (slanted[1] - slanted[0]).cross(slanted[2] - slanted[0]);
        let mut checked = 0;
        for j in 0..32u32 {
            for i in 0..32u32 {
                if buf.face_at(i, j).is_some() {
                    let ray = Vec3::new(
                        (i as f32 + 0.5 - 16.0) / 10.0,
                        (j as f32 + 0.5 - 16.0) / 10.0,
                        1.0,
                    );
                    let t = n.dot(slanted[0]) / n.dot(ray);
                    let d = buf.depth[(j * 32 + i) as usize];
                    assert!((d - t).abs() < 1e-4 * t, "({i},{j}): {d} vs {t}");
                    checked += 1;
                }
            }
        }
        assert!(checked > 50);
    }

    #[test]
    fn equal_depth_ties_go_to_the_lower_face_id() {
        let verts = at_depth([(0.0, 0.0), (16.0, 0.0), (0.0, 16.0)], 1.0);
        let buf = rasterize_triangle_ids(
            &verts,
            &[[0, 1, 2], [0, 2, 1], [2, 1, 0]],
            &pixel_camera(16, 16),
        )
        .unwrap();
        assert!(count(&buf, 0) > 0);
        assert_eq!(count(&buf, 1) + count(&buf, 2), 0);
    }

    #[test]
    fn split_quad_covers_every_pixel_exactly_once() {
        // Diagonals through pixel centres and corners on purpose: ties happen on the shared edge
        // and at shared vertices. Each triangle rendered alone, then counts compared.
        let quads: [[(f32, f32); 4]; 3] = [
            [(0.0, 0.0), (16.0, 0.0), (16.0, 16.0), (0.0, 16.0)],
            [(0.5, 0.5), (12.5, 2.5), (14.5, 14.5), (2.5, 12.5)],
            [(-3.0, 1.25), (17.75, -2.0), (19.0, 18.5), (0.5, 15.0)],
        ];
        for quad in quads {
            let verts: Vec<Vec3> = quad.iter().map(|&(u, v)| Vec3::new(u, v, 1.0)).collect();
            let cam = pixel_camera(16, 16);
            let halves = [[0u32, 1, 2], [0, 2, 3]];
            let mut hits = vec![0u32; 256];
            for half in halves {
                let buf = rasterize_triangle_ids(&verts, &[half], &cam).unwrap();
                for (k, &f) in buf.face_ids.iter().enumerate() {
                    hits[k] += u32::from(f >= 0);
                }
            }
            let q = quad.map(|(u, v)| (u as f64, v as f64));
            for j in 0..16 {
                for i in 0..16 {
                    let k = (j * 16 + i) as usize;
                    assert!(
                        hits[k] <= 1,
                        "pixel ({i},{j}) covered {} times for {quad:?}",
                        hits[k]
                    );
                    // Strictly inside the outer boundary (the diagonal included): exactly once.
                    if inside_quad_strict(q, i as f64 + 0.5, j as f64 + 0.5) {
                        assert_eq!(hits[k], 1, "crack at pixel ({i},{j}) for {quad:?}");
                    }
                }
            }
        }
    }

    fn inside_quad_strict(q: [(f64, f64); 4], x: f64, y: f64) -> bool {
        let s: Vec<f64> = (0..4)
            .map(|k| {
                let (a, b) = (q[k], q[(k + 1) % 4]);
                (b.0 - a.0) * (y - a.1) - (b.1 - a.1) * (x - a.0)
            })
            .collect();
        s.iter().all(|&v| v > 0.0) || s.iter().all(|&v| v < 0.0)
    }

    #[test]
    fn jittered_grid_mesh_is_watertight() {
        // A 6×6-cell grid over [-2, 26]², corners jittered off-grid or snapped to pixel centres
        // and corners (ties), each cell split along an alternating diagonal. Rendering each face
        // alone and summing must cover every pixel exactly once.
        let mut state = 0x2545_f491_4f6c_dd1du64;
        let mut rand = move || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            (state >> 11) as f64 / (1u64 << 53) as f64
        };
        let n = 6;
        let mut verts = Vec::new();
        for y in 0..=n {
            for x in 0..=n {
                let border = |k: i32| k == 0 || k == n;
                let mut u = -2.0 + 28.0 * x as f64 / n as f64;
                let mut v = -2.0 + 28.0 * y as f64 / n as f64;
                if !border(x) {
                    u += rand() * 2.0 - 1.0;
                }
                if !border(y) {
                    v += rand() * 2.0 - 1.0;
                }
                if rand() < 0.5 {
                    // Snap to a multiple of ½: edges then pass through pixel centres/corners.
                    u = (u * 2.0).round() / 2.0;
                    v = (v * 2.0).round() / 2.0;
                }
                verts.push(Vec3::new(u as f32, v as f32, 1.0));
            }
        }
        let id = |x: i32, y: i32| (y * (n + 1) + x) as u32;
        let mut faces = Vec::new();
        for y in 0..n {
            for x in 0..n {
                let (a, b, c, d) = (id(x, y), id(x + 1, y), id(x + 1, y + 1), id(x, y + 1));
                if (x + y) % 2 == 0 {
                    faces.extend([[a, b, c], [a, c, d]]);
                } else {
                    faces.extend([[a, b, d], [b, c, d]]);
                }
            }
        }
        let cam = pixel_camera(24, 24);
        let mut hits = vec![0u32; 24 * 24];
        for face in &faces {
            let buf = rasterize_triangle_ids(&verts, &[*face], &cam).unwrap();
            for (k, &f) in buf.face_ids.iter().enumerate() {
                hits[k] += u32::from(f >= 0);
            }
        }
        for (k, &h) in hits.iter().enumerate() {
            assert_eq!(h, 1, "pixel ({}, {}) covered {h} times", k % 24, k / 24);
        }
        // All faces at once: every pixel owned.
        let buf = rasterize_triangle_ids(&verts, &faces, &cam).unwrap();
        assert_eq!(count(&buf, -1), 0);
    }

    #[test]
    fn fan_around_a_vertex_on_a_pixel_centre_covers_it_once() {
        // 8 triangles around (8.5, 8.5), the centre of pixel (8, 8); spokes hit other centres too.
        let c = Vec3::new(8.5, 8.5, 1.0);
        let ring: Vec<Vec3> = (0..8)
            .map(|k| {
                let a = k as f32 * std::f32::consts::FRAC_PI_4;
                Vec3::new(
                    8.5 + 6.0 * a.cos().round(),
                    8.5 + 6.0 * a.sin().round(),
                    1.0,
                )
            })
            .collect();
        let mut verts = vec![c];
        verts.extend(ring);
        let faces: Vec<[u32; 3]> = (0..8).map(|k| [0, 1 + k, 1 + (k + 1) % 8]).collect();
        let cam = pixel_camera(17, 17);
        let mut hits = vec![0u32; 17 * 17];
        for face in &faces {
            let buf = rasterize_triangle_ids(&verts, &[*face], &cam).unwrap();
            for (k, &f) in buf.face_ids.iter().enumerate() {
                hits[k] += u32::from(f >= 0);
            }
        }
        assert_eq!(hits[8 * 17 + 8], 1);
        // Pixels strictly inside the square ring [2.5, 14.5]²: exactly once.
        for j in 3..14 {
            for i in 3..14 {
                assert_eq!(hits[j * 17 + i], 1, "pixel ({i},{j})");
            }
        }
    }

    #[test]
    fn triangle_crossing_the_near_plane_is_clipped() {
        let cam = Camera::new(
            Intrinsics {
                fx: 20.0,
                fy: 20.0,
                cx: 16.0,
                cy: 16.0,
            },
            Affine3A::IDENTITY,
            32,
            32,
        )
        .unwrap();
        // One corner well behind the camera, two in front.
        let verts = vec![
            Vec3::new(-1.0, -0.5, 2.0),
            Vec3::new(1.0, -0.5, 2.0),
            Vec3::new(0.0, 0.5, -3.0),
        ];
        let buf = rasterize_triangle_ids(&verts, &[[0, 1, 2]], &cam).unwrap();
        let n = count(&buf, 0);
        assert!(n > 0, "the in-front part must be drawn");
        for (k, &f) in buf.face_ids.iter().enumerate() {
            if f >= 0 {
                let d = buf.depth[k];
                assert!(
                    d.is_finite() && d >= NEAR as f32 && d <= 2.0 + 1e-4,
                    "depth {d}"
                );
            }
        }
        // Two corners behind: the clipped piece is a triangle.
        let verts2 = vec![
            Vec3::new(-1.0, 0.5, -2.0),
            Vec3::new(1.0, 0.5, -2.0),
            Vec3::new(0.0, 0.2, 1.0),
        ];
        let buf2 = rasterize_triangle_ids(&verts2, &[[0, 1, 2]], &cam).unwrap();
        assert!(count(&buf2, 0) > 0);
        assert!(
            buf2.face_ids
                .iter()
                .zip(&buf2.depth)
                .all(|(&f, d)| f < 0 || (d.is_finite() && *d <= 1.0 + 1e-4))
        );
        // A plane through the camera centre is seen edge-on: nothing, and no panic.
        let verts4 = vec![
            Vec3::new(-1.0, -0.5, 2.0),
            Vec3::new(1.0, -0.5, 2.0),
            Vec3::ZERO,
        ];
        assert_eq!(
            count(
                &rasterize_triangle_ids(&verts4, &[[0, 1, 2]], &cam).unwrap(),
                0
            ),
            0
        );
        // A corner exactly on the camera plane z = 0 must not produce inf/NaN either.
        let verts3 = vec![
            Vec3::new(-1.0, -0.5, 2.0),
            Vec3::new(1.0, -0.5, 2.0),
            Vec3::new(0.0, 1.0, 0.0),
        ];
        let buf3 = rasterize_triangle_ids(&verts3, &[[0, 1, 2]], &cam).unwrap();
        assert!(count(&buf3, 0) > 0);
        assert!(
            buf3.face_ids
                .iter()
                .zip(&buf3.depth)
                .all(|(&f, d)| f < 0 || d.is_finite())
        );
    }

    #[test]
    fn triangle_fully_behind_covers_nothing() {
        let cam = pixel_camera(8, 8);
        let verts = at_depth([(1.0, 1.0), (6.0, 1.0), (1.0, 6.0)], -1.0);
        let buf = rasterize_triangle_ids(&verts, &[[0, 1, 2]], &cam).unwrap();
        assert_eq!(count(&buf, -1), 64);
        // Degenerate faces (repeated index, or collinear) cover nothing.
        let verts = at_depth([(1.0, 1.0), (6.0, 1.0), (3.5, 1.0)], 1.0);
        let buf = rasterize_triangle_ids(&verts, &[[0, 1, 2], [0, 0, 1]], &cam).unwrap();
        assert_eq!(count(&buf, -1), 64);
    }

    #[test]
    fn closed_mesh_hides_its_back_vertex() {
        let (mesh, verts) = octahedron();
        let faces = mesh.faces.clone();
        // Slightly off-axis so the silhouette vertices (±x, ±y) are seen at a grazing angle but
        // still own pixels; non-square image with an off-centre principal point.
        let intr = Intrinsics {
            fx: 60.0,
            fy: 60.0,
            cx: 30.0,
            cy: 22.0,
        };
        let cam = Camera::look_at(
            Vec3::new(0.2, 0.1, 4.0),
            Vec3::new(0.05, 0.0, 0.0),
            Vec3::Y,
            intr,
            64,
            40,
        )
        .unwrap();
        let buf = rasterize_triangle_ids(&verts, &faces, &cam).unwrap();
        let vis = visible_vertices(&buf, &faces, verts.len());
        assert_eq!(vis, vec![true, true, true, true, true, false]);
        let fvis = visible_faces(&buf, faces.len());
        assert_eq!(
            fvis,
            vec![true, true, true, true, false, false, false, false]
        );

        // Subdivided: low-res visibility is the prefix; no high-res vertex behind the equator
        // (z < 0) is visible, and the front pole region is.
        let sub = Subdivision::new(&mesh, 2).unwrap();
        let hv = sub.highres_vertices_cpu(&verts);
        let buf = rasterize_triangle_ids(&hv, &sub.highres.faces, &cam).unwrap();
        let vis = visible_vertices(&buf, &sub.highres.faces, hv.len());
        assert_eq!(&vis[..6], &[true, true, true, true, true, false]);
        for (v, p) in hv.iter().enumerate() {
            if p.z < -1e-6 {
                assert!(!vis[v], "back vertex {v} at {p} is visible");
            }
            if p.z > 0.3 {
                assert!(vis[v], "front vertex {v} at {p} is hidden");
            }
        }
        // No cracks: the mesh silhouette is convex, so every covered pixel is owned by a
        // front face and the image contains no hole inside the silhouette.
        for j in 0..40 {
            let row = &buf.face_ids[j * 64..(j + 1) * 64];
            if let (Some(a), Some(b)) = (
                row.iter().position(|&f| f >= 0),
                row.iter().rposition(|&f| f >= 0),
            ) {
                assert!(row[a..=b].iter().all(|&f| f >= 0), "hole in row {j}");
                assert!(
                    row[a..=b].iter().all(|&f| sub.parent_face(f as usize) < 4),
                    "back face seen in row {j}"
                );
            }
        }
    }

    #[test]
    fn off_centre_principal_point_and_non_square_image() {
        let cam = Camera::new(
            Intrinsics {
                fx: 50.0,
                fy: 40.0,
                cx: 51.0,
                cy: 7.0,
            },
            Affine3A::IDENTITY,
            60,
            20,
        )
        .unwrap();
        // A small triangle around the point that projects to (55.2, 12.6).
        let z = 2.0;
        let world = |u: f32, v: f32| Vec3::new((u - 51.0) / 50.0 * z, (v - 7.0) / 40.0 * z, z);
        let verts = vec![world(53.1, 10.2), world(58.9, 11.3), world(55.0, 16.7)];
        let buf = rasterize_triangle_ids(&verts, &[[0, 1, 2]], &cam).unwrap();
        let p = [(53.1, 10.2), (58.9, 11.3), (55.0, 16.7)];
        for j in 0..20 {
            for i in 0..60 {
                let (x, y) = (i as f64 + 0.5, j as f64 + 0.5);
                // Coordinates go through f32 world space, so only test away from edges.
                let margin = 0.05;
                let strictly = [
                    (0.0, 0.0),
                    (margin, 0.0),
                    (-margin, 0.0),
                    (0.0, margin),
                    (0.0, -margin),
                ]
                .iter()
                .map(|(dx, dy)| inside(p, x + dx, y + dy))
                .collect::<Vec<_>>();
                if strictly.iter().all(|&b| b) {
                    assert_eq!(buf.face_at(i, j), Some(0), "({i},{j})");
                } else if strictly.iter().all(|&b| !b) {
                    assert_eq!(buf.face_at(i, j), None, "({i},{j})");
                }
            }
        }
        assert!(count(&buf, 0) > 5);
        assert_eq!(buf.face_ids.len(), 60 * 20);
    }

    #[test]
    fn one_by_one_image() {
        let cam = pixel_camera(1, 1);
        let covering = at_depth([(-1.0, -1.0), (3.0, -1.0), (-1.0, 3.0)], 1.5);
        let buf = rasterize_triangle_ids(&covering, &[[0, 1, 2]], &cam).unwrap();
        assert_eq!(buf.face_ids, vec![0]);
        assert!((buf.depth[0] - 1.5).abs() < 1e-6);
        let missing = at_depth([(0.6, 0.6), (3.0, 0.6), (0.6, 3.0)], 1.5);
        let buf = rasterize_triangle_ids(&missing, &[[0, 1, 2]], &cam).unwrap();
        assert_eq!(buf.face_ids, vec![-1]);
        assert_eq!(buf.depth, vec![f32::INFINITY]);
    }

    #[test]
    fn output_is_deterministic_across_thread_counts() {
        let (mesh, verts) = octahedron();
        let sub = Subdivision::new(&mesh, 3).unwrap();
        let hv = sub.highres_vertices_cpu(&verts);
        let cam = Camera::look_at(
            Vec3::new(1.5, 2.0, 3.0),
            Vec3::ZERO,
            Vec3::Y,
            Intrinsics {
                fx: 80.0,
                fy: 80.0,
                cx: 40.0,
                cy: 40.0,
            },
            80,
            80,
        )
        .unwrap();
        let run = |threads| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap()
                .install(|| rasterize_triangle_ids(&hv, &sub.highres.faces, &cam).unwrap())
        };
        let one = run(1);
        assert_eq!(one, run(4));
        assert!(count(&one, -1) < 80 * 80);
    }

    #[test]
    fn bad_inputs_are_reported() {
        let cam = pixel_camera(4, 4);
        let verts = vec![Vec3::ZERO, Vec3::new(1.0, f32::NAN, 1.0), Vec3::ONE];
        match rasterize_triangle_ids(&verts, &[[0, 1, 2]], &cam) {
            Err(RenderError::NonFinite {
                tensor: "vertices",
                index: 4,
            }) => {}
            other => panic!("{other:?}"),
        }
        let verts = vec![Vec3::ONE; 3];
        let err = rasterize_triangle_ids(&verts, &[[0, 1, 2], [0, 3, 1]], &cam)
            .unwrap_err()
            .to_string();
        assert!(err.contains("face 1 corner 1"), "{err}");
    }
}
