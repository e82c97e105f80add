//! A textured triangle-mesh rasterizer for the synthetic ground truth (not the Gaussian
//! renderer: the ground truth must come from a different image formation than the model's).
//!
//! # Algorithm
//!
//! 1. Vertices to camera space (OpenCV axes) and to pixels with the camera's convention (pixel
//!    `(i, j)` covers `[i, i+1) × [j, j+1)` and is sampled at its centre).
//! 2. Triangles with a corner closer than [`NEAR`] are dropped: the synthetic cameras stand 2 m
//!    from a body, so no clipping is needed; dropping is the safe failure mode.
//! 3. Per triangle, over its pixel bounding box: edge functions in f64 decide coverage (a
//!    top-left-style tie rule, so a pixel centre on a shared edge belongs to exactly one of the
//!    two triangles: no cracks, no double coverage), then a z-test on perspective-correct depth.
//! 4. The z-buffer keeps, per pixel, the face and its **perspective-correct barycentrics**
//!    (screen barycentrics weighted by `1/z` and renormalised), so any per-vertex attribute is
//!    interpolated as it would be on the 3D surface.
//!
//! Shading is a separate pass over the buffer ([`Fragment`]s), done by the caller: this module
//! only answers "which surface point is seen at this pixel centre". Supersampling is done by the
//! caller too, by rasterising at `s×` the resolution with a scaled camera.
//!
//! Determinism: ties in depth go to the lower face id, so the result does not depend on the
//! triangle order or on threads (rows are independent; triangles are visited in order).

use glam::{DVec2, Vec3};
use lifegom_render::camera::Camera;

/// Corners closer than this (metres, camera z) drop their triangle.
pub const NEAR: f32 = 1e-2;

/// What is seen at one pixel centre.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Fragment {
    /// The face.
    pub face: u32,
    /// Perspective-correct barycentrics of its three corners (sum 1).
    pub bary: [f32; 3],
    /// Camera-space depth.
    pub depth: f32,
}

/// Rasterises `faces` over `vertices` (world space) for `camera`: one optional fragment per
/// pixel, row-major (`j * width + i`).
pub fn rasterize(vertices: &[Vec3], faces: &[[u32; 3]], camera: &Camera) -> Vec<Option<Fragment>> {
    let (w, h) = (camera.width as usize, camera.height as usize);
    let k = camera.intrinsics;
    let projected: Vec<(DVec2, f64)> = vertices
        .iter()
        .map(|&p| {
            let c = camera.world_to_camera(p);
            let z = c.z as f64;
            let uv = DVec2::new(
                k.fx as f64 * c.x as f64 / z + k.cx as f64,
                k.fy as f64 * c.y as f64 / z + k.cy as f64,
            );
            (uv, z)
        })
        .collect();
    let mut out: Vec<Option<Fragment>> = vec![None; w * h];
    for (f, face) in faces.iter().enumerate() {
        let Some(corners) = face
            .iter()
            .map(|&v| projected.get(v as usize).copied())
            .collect::<Option<Vec<_>>>()
        else {
            continue; // out-of-range index: callers validate topology, so never in practice
        };
        if corners
            .iter()
            .any(|c| c.1.is_nan() || c.1 < NEAR as f64 || !c.0.is_finite())
        {
            continue;
        }
        let p = [corners[0].0, corners[1].0, corners[2].0];
        let inv_z = [1.0 / corners[0].1, 1.0 / corners[1].1, 1.0 / corners[2].1];
        let area = edge(p[0], p[1], p[2]);
        if area == 0.0 || !area.is_finite() {
            continue;
        }
        // Orient so the interior is positive whatever the winding (no backface culling: the
        // z-buffer resolves visibility, and garment offsets can flip thin regions).
        let sign = area.signum();
        let lo = p[0].min(p[1]).min(p[2]);
        let hi = p[0].max(p[1]).max(p[2]);
        let Some((i0, i1)) = pixel_range(lo.x, hi.x, w) else {
            continue;
        };
        let Some((j0, j1)) = pixel_range(lo.y, hi.y, h) else {
            continue;
        };
        for j in j0..=j1 {
            for i in i0..=i1 {
                let x = DVec2::new(i as f64 + 0.5, j as f64 + 0.5);
                let e = [
                    sign * edge(p[1], p[2], x),
                    sign * edge(p[2], p[0], x),
                    sign * edge(p[0], p[1], x),
                ];
                let owns = |k: usize, a: DVec2, b: DVec2| {
                    e[k] > 0.0 || (e[k] == 0.0 && top_left(sign * (b.y - a.y), sign * (b.x - a.x)))
                };
                if !(owns(0, p[1], p[2]) && owns(1, p[2], p[0]) && owns(2, p[0], p[1])) {
                    continue;
                }
                let sum = e[0] + e[1] + e[2];
                if sum <= 0.0 {
                    continue;
                }
                // Screen barycentrics → perspective-correct ones via 1/z.
                let wz = [e[0] * inv_z[0], e[1] * inv_z[1], e[2] * inv_z[2]];
                let wsum = wz[0] + wz[1] + wz[2];
                let depth = (sum / wsum) as f32;
                let slot = &mut out[j * w + i];
                let nearer = match slot {
                    None => true,
                    Some(old) => depth < old.depth || (depth == old.depth && (f as u32) < old.face),
                };
                if nearer {
                    *slot = Some(Fragment {
                        face: f as u32,
                        bary: [
                            (wz[0] / wsum) as f32,
                            (wz[1] / wsum) as f32,
                            (wz[2] / wsum) as f32,
                        ],
                        depth,
                    });
                }
            }
        }
    }
    out
}

/// Twice the signed area of `(a, b, x)`: positive when `x` is left of `a → b` (y down).
fn edge(a: DVec2, b: DVec2, x: DVec2) -> f64 {
    (b.x - a.x) * (x.y - a.y) - (b.y - a.y) * (x.x - a.x)
}

/// Tie rule for a pixel centre exactly on an edge with direction `(dx, dy)` (interior
/// positive): exactly one of an edge and its reverse owns the sample.
fn top_left(dy: f64, dx: f64) -> bool {
    dy > 0.0 || (dy == 0.0 && dx < 0.0)
}

/// Inclusive pixel range whose centres `i + ½` lie in `[lo, hi]`, clamped to `[0, size)`.
fn pixel_range(lo: f64, hi: f64, size: usize) -> Option<(usize, usize)> {
    let first = (lo - 0.5).ceil().max(0.0);
    let last = (hi - 0.5).floor().min(size as f64 - 1.0);
    (first <= last).then_some((first as usize, last as usize))
}

#[cfg(test)]
mod tests {
    use glam::Affine3A;
    use lifegom_render::camera::Intrinsics;

    use super::*;

    /// Identity extrinsics, f = 1, c = 0: world `(u·z, v·z, z)` lands on pixel coords `(u, v)`.
    fn screen(w: u32, h: u32) -> Camera {
        Camera::new(
            Intrinsics {
                fx: 1.0,
                fy: 1.0,
                cx: 0.0,
                cy: 0.0,
            },
            Affine3A::IDENTITY,
            w,
            h,
        )
        .unwrap()
    }

    #[test]
    fn a_split_square_covers_every_pixel_once_and_interpolates() {
        // Square [0,8]² at depth 2, split along the diagonal that passes through pixel centres.
        let z = 2.0;
        let v = [
            Vec3::new(0.0, 0.0, z),
            Vec3::new(8.0 * z, 0.0, z),
            Vec3::new(8.0 * z, 8.0 * z, z),
            Vec3::new(0.0, 8.0 * z, z),
        ];
        let faces = [[0, 1, 2], [0, 2, 3]];
        let img = rasterize(&v, &faces, &screen(10, 10));
        let covered = img.iter().filter(|f| f.is_some()).count();
        assert_eq!(covered, 64);
        // Each diagonal centre (i+½, i+½) belongs to exactly one face: both faces got pixels.
        let f0 = img.iter().flatten().filter(|f| f.face == 0).count();
        assert!(f0 > 20 && f0 < 44, "{f0}");
        for frag in img.iter().flatten() {
            assert!((frag.depth - z).abs() < 1e-5);
            assert!((frag.bary.iter().sum::<f32>() - 1.0).abs() < 1e-5);
        }
        // Interpolating x over the pixel (3, 5) gives its centre's world x / z = 3.5.
        let frag = img[5 * 10 + 3].unwrap();
        let f = faces[frag.face as usize];
        let x: f32 = (0..3).map(|c| frag.bary[c] * v[f[c] as usize].x).sum();
        assert!((x / z - 3.5).abs() < 1e-4, "{x}");
    }

    #[test]
    fn nearer_triangle_wins_and_perspective_is_correct() {
        let far = [
            Vec3::new(-10.0, -10.0, 5.0),
            Vec3::new(50.0, -10.0, 5.0),
            Vec3::new(-10.0, 50.0, 5.0),
        ];
        // A slanted triangle: depth varies across the screen.
        let near = [
            Vec3::new(0.0, 0.0, 1.0),
            Vec3::new(12.0, 0.0, 3.0),
            Vec3::new(0.0, 8.0, 2.0),
        ];
        let verts: Vec<Vec3> = far.iter().chain(&near).copied().collect();
        let img = rasterize(&verts, &[[0, 1, 2], [3, 4, 5]], &screen(8, 8));
        let frag = img[8 + 1].unwrap();
        assert_eq!(frag.face, 1);
        // The interpolated 3D point must project back onto the pixel centre (1.5, 1.5).
        let p: Vec3 = (0..3).map(|c| frag.bary[c] * near[c]).sum();
        assert!(
            (p.x / p.z - 1.5).abs() < 1e-4 && (p.y / p.z - 1.5).abs() < 1e-4,
            "{p}"
        );
        assert!((p.z - frag.depth).abs() < 1e-4);
        assert_eq!(img[8 + 5].unwrap().face, 0);
    }

    #[test]
    fn degenerate_and_behind_camera_triangles_draw_nothing() {
        let v = [
            Vec3::new(0.0, 0.0, 1.0),
            Vec3::new(4.0, 4.0, 1.0),
            Vec3::new(8.0, 8.0, 1.0),
            Vec3::new(0.0, 8.0, -1.0),
        ];
        let img = rasterize(&v, &[[0, 1, 2], [0, 2, 3], [0, 1, 9]], &screen(8, 8));
        assert!(img.iter().all(Option::is_none));
    }
}
