//! The face-local Steiner frame `A` of a triangle (design.md §5.3).
//!
//! For a triangle `(v0, v1, v2)` with centroid `c`, the vectors `f1 = (v2 − c)/2` and
//! `f2 = (v1 − v0)/(2√3)` are conjugate semi-diameters of its Steiner inellipse (the largest
//! ellipse inside it, touching each edge at its midpoint). Rotating them by
//! `t0 = ½·atan2(2 f1·f2, |f1|² − |f2|²)` gives the orthogonal principal semi-axes `a0`, `a1`.
//! The frame is `A = [2a0 | 2a1 | σ·n̂]` with `n̂` the unit normal and `σ = 1 mm`, so a Gaussian
//! with local covariance `I` is the inellipse blown up 2× in-plane and 1 mm thick, and local
//! offsets are in "inellipse units" in-plane and millimetres along the normal.
//!
//! # Degenerate triangles
//!
//! The frame has two singular configurations, and both occur in real meshes:
//! - a **circle** (`f1 ⟂ f2`, `|f1| = |f2|`, e.g. an equilateral triangle): `t0` is undefined
//!   because every diameter is principal, and `atan2(0, 0)` has a NaN gradient;
//! - a **zero-area** triangle: `f1 ∥ f2` and `n̂ = 0/0`.
//!
//! Both are handled so values *and gradients* stay finite: where `atan2`'s argument is
//! negligible relative to the triangle's size, `t0 = 0` (any angle is a valid answer), and the
//! normal is normalised as `n / sqrt(|n|² + ε²)` (the reference's `F.normalize` divides by
//! `max(|n|, 1e-12)`, which agrees for any non-degenerate triangle). A zero-area triangle gets
//! `n = 0`: its Gaussian is flat, and the rasterizer's 0.3 px² dilation keeps it renderable.

use burn::tensor::Tensor;

/// Thickness of a Gaussian along the face normal, metres (`σ` in design.md §5.3).
pub const NORMAL_SCALE: f32 = 1e-3;

/// Steiner frames of a batch of triangles.
#[derive(Debug, Clone)]
pub struct SteinerFrames {
    /// Face centroids, `[F, 3]`.
    pub centroids: Tensor<2>,
    /// Frames `A`, `[F, 3, 3]`; `A[f, :, k]` is the k-th column (`2a0`, `2a1`, `σ·n̂`).
    pub frames: Tensor<3>,
}

fn dot(a: &Tensor<2>, b: &Tensor<2>) -> Tensor<2> {
    (a.clone() * b.clone()).sum_dim(1)
}

/// Computes the Steiner frames of triangles given by their corner positions (`[F, 3]` each),
/// differentiably in all corners.
pub fn steiner_frames(v0: Tensor<2>, v1: Tensor<2>, v2: Tensor<2>) -> SteinerFrames {
    let centroids = (v0.clone() + v1.clone() + v2.clone()) / 3.0;
    let f1 = (v2 - centroids.clone()) / 2.0;
    let f2 = (v1 - v0) / (2.0 * 3.0f32.sqrt());
    let f11 = dot(&f1, &f1);
    let f22 = dot(&f2, &f2);
    let y = dot(&f1, &f2) * 2.0;
    let x = f11.clone() - f22.clone();
    // Circle or zero-area: atan2's argument vanishes relative to the triangle's scale⁴. Shift x
    // there (a constant mask, so no gradient flows through the test) to land on t0 = 0.
    let size2 = (f11 + f22).powi_scalar(2);
    let degenerate =
        (x.clone().powi_scalar(2) + y.clone().powi_scalar(2)).lower_equal(size2 * 1e-12 + 1e-30);
    let x_safe = x.clone().mask_where(degenerate, x + 1.0);
    let t0 = y.atan2(x_safe) * 0.5;
    let (cos, sin) = (t0.clone().cos(), t0.sin());
    let a0 = f1.clone() * cos.clone() + f2.clone() * sin.clone();
    let a1 = f2 * cos - f1 * sin;
    let n = a0.clone().cross(a1.clone(), 1);
    let norm = (dot(&n, &n) + 1e-24).sqrt();
    let n = n / norm * NORMAL_SCALE;
    let frames = Tensor::stack::<3>(vec![a0 * 2.0, a1 * 2.0, n], 2);
    SteinerFrames { centroids, frames }
}

#[cfg(test)]
mod tests {
    #![allow(deprecated)]
    use super::*;
    use burn::tensor::{Device, TensorData};

    fn t2(v: &[[f32; 3]], device: &Device) -> Tensor<2> {
        Tensor::from_data(
            TensorData::new(
                v.iter().flatten().copied().collect::<Vec<_>>(),
                [v.len(), 3],
            ),
            device,
        )
    }

    use crate::testing::read;

    /// The inellipse of a triangle touches each edge midpoint: with A's in-plane columns as the
    /// semi-axes (×2), each midpoint m satisfies |A⁻¹_inplane (m − c)| = ½.
    fn check_inellipse(device: &Device) {
        let tri = [[0.1f32, 0.0, 0.2], [0.5, 0.05, 0.1], [0.2, 0.4, 0.0]];
        let fr = steiner_frames(
            t2(&tri[0..1], device),
            t2(&tri[1..2], device),
            t2(&tri[2..3], device),
        );
        let a = read(fr.frames);
        let col = |k: usize| glam::Vec3::new(a[k], a[3 + k], a[6 + k]);
        let (c0, c1, n) = (col(0) / 2.0, col(1) / 2.0, col(2));
        assert!(c0.dot(c1).abs() < 1e-6, "principal axes must be orthogonal");
        assert!((n.length() - NORMAL_SCALE).abs() < 1e-7);
        assert!(n.dot(c0).abs() < 1e-9 && n.dot(c1).abs() < 1e-9);
        let v: Vec<glam::Vec3> = tri.iter().map(|p| glam::Vec3::from_array(*p)).collect();
        let c = (v[0] + v[1] + v[2]) / 3.0;
        for (p, q) in [(0, 1), (1, 2), (2, 0)] {
            let m = (v[p] + v[q]) / 2.0 - c;
            let (u, w) = (
                m.dot(c0) / c0.length_squared(),
                m.dot(c1) / c1.length_squared(),
            );
            assert!(
                (u * u + w * w - 1.0).abs() < 1e-4,
                "edge midpoint {p}{q} is not on the inellipse"
            );
        }
    }

    crate::cpu_backend_tests!(inellipse => check_inellipse);
}
