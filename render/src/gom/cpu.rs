//! The fused GoM geometry op as plain functions: per face in `f64` ([`face_forward`],
//! [`face_backward`]), and over whole `f32` slices with rayon ([`forward`], [`backward`]). This
//! is the CPU implementation of [`super::op::GomGeometryOps`] and the reference the CubeCL
//! kernels mirror (design.md §5.6).
//!
//! Every formula is the one the tensor-op path ([`super::gaussians_from_triangles`] over
//! [`crate::steiner::steiner_frames`] and [`super::so3_exp_map`]) evaluates, including its
//! safety constants, so the two agree to rounding and their gradients match branch for branch.
//! The backward recomputes the cheap per-face forward instead of saving it.

use glam::{DMat3, DVec3};
use rayon::prelude::*;

use crate::steiner::NORMAL_SCALE;

/// Floats per face in the op's output: mean (3) ‖ covariance (6: xx, xy, xz, yy, yz, zz).
pub const OUT_LANES: usize = 9;
/// Corner-table entries per face: 3 corners × 3 `(low-res index, weight)` slots.
pub const CORNER_LANES: usize = 9;
/// `so3_exp_map` floors `|r|²` here before taking `θ = sqrt(·)`, which keeps it smooth at 0.
pub const SO3_THETA2_MIN: f64 = 1e-4;
/// `ε²` in the Steiner frame's normal normalisation `n / sqrt(|n|² + ε²)`.
pub const NORMAL_EPS2: f64 = 1e-24;
/// The Steiner frame treats `atan2(y, x)` as degenerate where
/// `x² + y² ≤ (|f1|² + |f2|²)²·DEGENERATE_REL + DEGENERATE_ABS`.
pub const DEGENERATE_REL: f64 = 1e-12;
/// See [`DEGENERATE_REL`].
pub const DEGENERATE_ABS: f64 = 1e-30;

/// One face's inputs: its corners (already interpolated from low-res vertices) and parameters.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct FaceInputs {
    /// Triangle corners `p0, p1, p2`.
    pub corners: [DVec3; 3],
    /// Axis-angle rotation in the face frame.
    pub so3: DVec3,
    /// Raw (signed) scales.
    pub scale: DVec3,
    /// Mean offset in the face frame.
    pub offset: DVec3,
}

/// Gradients of a scalar loss w.r.t. one face's [`FaceInputs`], field for field.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct FaceGrads {
    /// W.r.t. the corners.
    pub corners: [DVec3; 3],
    /// W.r.t. the rotation.
    pub so3: DVec3,
    /// W.r.t. the scales.
    pub scale: DVec3,
    /// W.r.t. the offset.
    pub offset: DVec3,
}

/// The Steiner frame and the intermediates its backward needs.
struct Frame {
    c: DVec3,
    f1: DVec3,
    f2: DVec3,
    /// `x` after the degenerate shift, and `y`: the arguments of `atan2(y, x_s)`.
    x_s: f64,
    y: f64,
    cs: f64,
    sn: f64,
    a0: DVec3,
    a1: DVec3,
    n: DVec3,
    nrm: f64,
    /// `[2a0 | 2a1 | σ n/nrm]`.
    a: DMat3,
}

fn sigma() -> f64 {
    f64::from(NORMAL_SCALE)
}

/// `1/(2√3)`, with `√3` rounded to `f32` first as `steiner_frames` does: a 3e-8 relative
/// difference in `f2` is invisible in most outputs but not in covariance entries that cancel.
fn inv_two_sqrt3() -> f64 {
    1.0 / (2.0 * f64::from(3f32.sqrt()))
}

/// `(cos t₀, sin t₀)` of `t₀ = ½·atan2(y, x)` by the half-angle identities, without
/// trigonometric calls (which were a fifth of the op's forward): with `r = |(x, y)|`,
/// `cos t₀ = √((r + x)/2r)`, `sin t₀ = √((r − x)/2r)·sign(y)`. Each is taken from the
/// well-conditioned formula and the other from `sin 2t₀ = y/r = 2 sin t₀ cos t₀`, so both keep
/// full precision on either side of `x = 0`; `cos t₀ ≥ 0` as `|t₀| ≤ π/2`, and `y = ±0` with
/// `x < 0` gives `t₀ = ±π/2` like `atan2`. Equal to the trigonometric form to a few ulp.
fn half_angle(x: f64, y: f64) -> (f64, f64) {
    let r = x.hypot(y);
    if r == 0.0 {
        return (1.0, 0.0);
    }
    if x >= 0.0 {
        let cs = ((r + x) / (2.0 * r)).sqrt();
        (cs, y / (2.0 * r * cs))
    } else {
        let sn = ((r - x) / (2.0 * r)).sqrt().copysign(y);
        (y / (2.0 * r * sn), sn)
    }
}

fn steiner(p: &[DVec3; 3]) -> Frame {
    let c = (p[0] + p[1] + p[2]) / 3.0;
    let f1 = (p[2] - c) * 0.5;
    let f2 = (p[1] - p[0]) * inv_two_sqrt3();
    let f11 = f1.dot(f1);
    let f22 = f2.dot(f2);
    let y = 2.0 * f1.dot(f2);
    let x = f11 - f22;
    let degenerate = x * x + y * y <= (f11 + f22) * (f11 + f22) * DEGENERATE_REL + DEGENERATE_ABS;
    // A constant shift, as in `steiner_frames`: dx_s/dx = 1 on both branches.
    let x_s = if degenerate { x + 1.0 } else { x };
    let (cs, sn) = half_angle(x_s, y);
    let a0 = f1 * cs + f2 * sn;
    let a1 = f2 * cs - f1 * sn;
    let n = a0.cross(a1);
    let nrm = (n.dot(n) + NORMAL_EPS2).sqrt();
    let a = DMat3::from_cols(a0 * 2.0, a1 * 2.0, n * (sigma() / nrm));
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

/// `R = exp(hat(r))` and the intermediates its backward needs.
struct Rotation {
    nrm2: f64,
    theta: f64,
    fac1: f64,
    fac2: f64,
    k: DMat3,
    k2: DMat3,
    r: DMat3,
}

fn outer(u: DVec3, v: DVec3) -> DMat3 {
    DMat3::from_cols(u * v.x, u * v.y, u * v.z)
}

/// `Σ_ij a_ij b_ij`.
fn frobenius(a: &DMat3, b: &DMat3) -> f64 {
    a.x_axis.dot(b.x_axis) + a.y_axis.dot(b.y_axis) + a.z_axis.dot(b.z_axis)
}

fn so3_exp(r: DVec3) -> Rotation {
    let nrm2 = r.dot(r);
    let theta = nrm2.max(SO3_THETA2_MIN).sqrt();
    let (st, ct) = theta.sin_cos();
    let fac1 = st / theta;
    let fac2 = (1.0 - ct) / (theta * theta);
    // Rows [[0, −z, y], [z, 0, −x], [−y, x, 0]], written as columns.
    let k = DMat3::from_cols(
        DVec3::new(0.0, r.z, -r.y),
        DVec3::new(-r.z, 0.0, r.x),
        DVec3::new(r.y, -r.x, 0.0),
    );
    let k2 = outer(r, r) - DMat3::IDENTITY * nrm2;
    let rot = DMat3::IDENTITY + k * fac1 + k2 * fac2;
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

/// The Gaussian of one face: mean (3) ‖ covariance (6: xx, xy, xz, yy, yz, zz).
pub fn face_forward(face: &FaceInputs) -> [f64; OUT_LANES] {
    let frame = steiner(&face.corners);
    let rot = so3_exp(face.so3);
    let m = frame.a * rot.r * DMat3::from_diagonal(face.scale);
    let mean = frame.c + frame.a * face.offset;
    let cov = m * m.transpose();
    [
        mean.x,
        mean.y,
        mean.z,
        cov.x_axis.x,
        cov.y_axis.x,
        cov.z_axis.x,
        cov.y_axis.y,
        cov.z_axis.y,
        cov.z_axis.z,
    ]
}

/// Gradients of `Σ grad·face_forward(face)` w.r.t. every input of the face.
pub fn face_backward(face: &FaceInputs, grad: &[f64; OUT_LANES]) -> FaceGrads {
    let frame = steiner(&face.corners);
    let rot = so3_exp(face.so3);
    let s = DMat3::from_diagonal(face.scale);
    let rs = rot.r * s;
    let m = frame.a * rs;
    let g_mean = DVec3::new(grad[0], grad[1], grad[2]);
    let [gxx, gxy, gxz, gyy, gyz, gzz] = [grad[3], grad[4], grad[5], grad[6], grad[7], grad[8]];
    // Σ = M Mᵀ read as its upper triangle: dL/dM = (G + Gᵀ) M with G that triangle, so the
    // diagonal counts twice.
    let g_sym = DMat3::from_cols(
        DVec3::new(2.0 * gxx, gxy, gxz),
        DVec3::new(gxy, 2.0 * gyy, gyz),
        DVec3::new(gxz, gyz, 2.0 * gzz),
    );
    let g_m = g_sym * m;
    let g_rs = frame.a.transpose() * g_m;
    let g_a = g_m * rs.transpose() + outer(g_mean, face.offset);
    let g_r = g_rs * s;
    let scale = DVec3::new(
        g_rs.x_axis.dot(rot.r.x_axis),
        g_rs.y_axis.dot(rot.r.y_axis),
        g_rs.z_axis.dot(rot.r.z_axis),
    );
    FaceGrads {
        corners: steiner_backward(&frame, &g_a, g_mean),
        so3: so3_exp_backward(face.so3, &rot, &g_r),
        scale,
        offset: frame.a.transpose() * g_mean,
    }
}

fn so3_exp_backward(r: DVec3, rot: &Rotation, g_r: &DMat3) -> DVec3 {
    let g_fac1 = frobenius(g_r, &rot.k);
    let g_fac2 = frobenius(g_r, &rot.k2);
    let g_k = *g_r * rot.fac1;
    let g_k2 = *g_r * rot.fac2;
    // `col(j)[i]` is row i, column j.
    let at = |m: &DMat3, i: usize, j: usize| m.col(j)[i];
    let from_k = DVec3::new(
        at(&g_k, 2, 1) - at(&g_k, 1, 2),
        at(&g_k, 0, 2) - at(&g_k, 2, 0),
        at(&g_k, 1, 0) - at(&g_k, 0, 1),
    );
    let from_k2 = (g_k2 + g_k2.transpose()) * r;
    let mut g_nrm2 = -(g_k2.x_axis.x + g_k2.y_axis.y + g_k2.z_axis.z);
    // Burn's `clamp_min` is a mask-fill of `x < min`: the gradient passes where `x ≥ min`.
    if rot.nrm2 >= SO3_THETA2_MIN {
        let th = rot.theta;
        let (st, ct) = th.sin_cos();
        let d_fac1 = (th * ct - st) / (th * th);
        let d_fac2 = (th * st - 2.0 * (1.0 - ct)) / (th * th * th);
        g_nrm2 += (g_fac1 * d_fac1 + g_fac2 * d_fac2) / (2.0 * th);
    }
    from_k + from_k2 + r * (2.0 * g_nrm2)
}

/// Chains `dL/dA` and `dL/dc` (the mean's direct term) back to the three corners.
fn steiner_backward(fr: &Frame, g_a: &DMat3, g_c: DVec3) -> [DVec3; 3] {
    let g_nh = g_a.z_axis;
    let g_n = (g_nh / fr.nrm - fr.n * (fr.n.dot(g_nh) / (fr.nrm * fr.nrm * fr.nrm))) * sigma();
    let g_a0 = g_a.x_axis * 2.0 + fr.a1.cross(g_n);
    let g_a1 = g_a.y_axis * 2.0 + g_n.cross(fr.a0);
    let g_cs = g_a0.dot(fr.f1) + g_a1.dot(fr.f2);
    let g_sn = g_a0.dot(fr.f2) - g_a1.dot(fr.f1);
    let g_t0 = -g_cs * fr.sn + g_sn * fr.cs;
    let den = fr.x_s * fr.x_s + fr.y * fr.y;
    let g_y = 0.5 * g_t0 * fr.x_s / den;
    let g_x = -0.5 * g_t0 * fr.y / den;
    let g_f1 = g_a0 * fr.cs - g_a1 * fr.sn + fr.f2 * (2.0 * g_y) + fr.f1 * (2.0 * g_x);
    let g_f2 = g_a0 * fr.sn + g_a1 * fr.cs + fr.f1 * (2.0 * g_y) - fr.f2 * (2.0 * g_x);
    let g_c = (g_c - g_f1 * 0.5) / 3.0;
    let g_f2 = g_f2 * inv_two_sqrt3();
    [g_c - g_f2, g_c + g_f2, g_c + g_f1 * 0.5]
}

/// The op's inputs as flat host slices.
#[derive(Debug, Clone, Copy)]
pub struct GeometrySlices<'a> {
    /// Low-res vertices, `[V*3]`.
    pub vertices: &'a [f32],
    /// `[F*3]`.
    pub so3: &'a [f32],
    /// `[F*3]`.
    pub scales: &'a [f32],
    /// `[F*3]`.
    pub offsets: &'a [f32],
    /// `[F*9]`: face `f`, corner `k`, slot `m` at `9f + 3k + m`.
    pub corner_index: &'a [i32],
    /// `[F*9]`, matching `corner_index`.
    pub corner_weight: &'a [f32],
}

impl GeometrySlices<'_> {
    /// Number of faces; panics (a programming error, checked by the op's callers) if lengths
    /// disagree.
    pub fn num_faces(&self) -> usize {
        let f = self.so3.len() / 3;
        assert!(
            self.so3.len() == 3 * f
                && self.scales.len() == 3 * f
                && self.offsets.len() == 3 * f
                && self.corner_index.len() == CORNER_LANES * f
                && self.corner_weight.len() == CORNER_LANES * f
                && self.vertices.len().is_multiple_of(3),
            "GeometrySlices: inconsistent lengths"
        );
        f
    }

    fn num_vertices(&self) -> usize {
        self.vertices.len() / 3
    }

    /// Low-res vertex of corner-table entry `e`, or `None` for an out-of-range index (which the
    /// op treats as weight 0: it cannot return an error).
    fn slot(&self, e: usize) -> Option<usize> {
        usize::try_from(self.corner_index[e])
            .ok()
            .filter(|&v| v < self.num_vertices())
    }

    fn vec3(values: &[f32], i: usize) -> DVec3 {
        DVec3::new(
            f64::from(values[3 * i]),
            f64::from(values[3 * i + 1]),
            f64::from(values[3 * i + 2]),
        )
    }

    /// Face `f`'s corners and parameters, in `f64`.
    pub fn face(&self, f: usize) -> FaceInputs {
        let corner = |k: usize| {
            (0..3)
                .map(|m| CORNER_LANES * f + 3 * k + m)
                .filter_map(|e| {
                    self.slot(e)
                        .map(|v| Self::vec3(self.vertices, v) * f64::from(self.corner_weight[e]))
                })
                .sum()
        };
        FaceInputs {
            corners: [corner(0), corner(1), corner(2)],
            so3: Self::vec3(self.so3, f),
            scale: Self::vec3(self.scales, f),
            offset: Self::vec3(self.offsets, f),
        }
    }
}

/// Faces per rayon task: a face is ~200 flops, so tasks of a few thousand amortise scheduling.
const FACES_PER_TASK: usize = 1024;

/// The op's forward: `[F*9]`, per face mean ‖ covariance.
pub fn forward(inputs: &GeometrySlices<'_>) -> Vec<f32> {
    let f = inputs.num_faces();
    let mut out = vec![0.0f32; OUT_LANES * f];
    out.par_chunks_mut(OUT_LANES * FACES_PER_TASK)
        .enumerate()
        .for_each(|(task, chunk)| {
            for (i, face_out) in chunk.chunks_exact_mut(OUT_LANES).enumerate() {
                let values = face_forward(&inputs.face(task * FACES_PER_TASK + i));
                for (o, v) in face_out.iter_mut().zip(values) {
                    *o = v as f32;
                }
            }
        });
    out
}

/// Gradients of the op's inputs, as flat `f32` vectors.
#[derive(Debug, Clone, PartialEq)]
pub struct GeometryGrads {
    /// `[V*3]`.
    pub vertices: Vec<f32>,
    /// `[F*3]`.
    pub so3: Vec<f32>,
    /// `[F*3]`.
    pub scales: Vec<f32>,
    /// `[F*3]`.
    pub offsets: Vec<f32>,
}

/// The most blocks the backward's vertex scatter is split into: enough to keep two to eight
/// cores busy, few enough that the blocks' private vertex arrays (`24·V` bytes each) and their
/// final sum stay small beside the faces' work.
pub const MAX_SCATTER_BLOCKS: usize = 16;

/// The fewest faces a scatter block holds: below this a block's task overhead and its private
/// vertex array outweigh its faces.
pub const MIN_FACES_PER_SCATTER_BLOCK: usize = 1024;

/// Faces per block of the backward's vertex scatter for a mesh of `faces` faces. Each block sums
/// its corner gradients into its own low-res vertex array in face order, and the blocks are
/// added in block order: the result depends on the face count alone, not on the number of
/// threads, so it is deterministic. A training mesh (9,816 faces at one subdivision of the
/// low-res template) gets nine blocks instead of one, so both cores share its backward.
pub fn faces_per_scatter_block(faces: usize) -> usize {
    let blocks = (faces / MIN_FACES_PER_SCATTER_BLOCK).clamp(1, MAX_SCATTER_BLOCKS);
    faces.div_ceil(blocks).max(1)
}

/// The op's backward given `dL/d(output)` (`[F*9]`). Faces run in parallel, writing their own
/// `so3`/`scale`/`offset` rows; the scatter into the shared low-res vertices is blocked as
/// [`faces_per_scatter_block`] describes.
pub fn backward(inputs: &GeometrySlices<'_>, grad_out: &[f32]) -> GeometryGrads {
    let f = inputs.num_faces();
    assert_eq!(
        grad_out.len(),
        OUT_LANES * f,
        "gom backward: the output gradient has the wrong length"
    );
    let v = inputs.num_vertices();
    let mut so3 = vec![0.0f32; 3 * f];
    let mut scales = vec![0.0f32; 3 * f];
    let mut offsets = vec![0.0f32; 3 * f];
    let block_faces = faces_per_scatter_block(f);
    let store = |out: &mut [f32], g: DVec3| {
        out.copy_from_slice(&[g.x as f32, g.y as f32, g.z as f32]);
    };
    let blocks: Vec<Vec<DVec3>> = so3
        .par_chunks_mut(3 * block_faces)
        .zip(scales.par_chunks_mut(3 * block_faces))
        .zip(offsets.par_chunks_mut(3 * block_faces))
        .enumerate()
        .map(|(block, ((so3, scales), offsets))| {
            let first = block * block_faces;
            let mut vertices = vec![DVec3::ZERO; v];
            let rows = so3
                .chunks_exact_mut(3)
                .zip(scales.chunks_exact_mut(3))
                .zip(offsets.chunks_exact_mut(3));
            for (i, ((so3, scale), offset)) in rows.enumerate() {
                let face = first + i;
                let g = &grad_out[OUT_LANES * face..OUT_LANES * (face + 1)];
                let g: [f64; OUT_LANES] = std::array::from_fn(|i| f64::from(g[i]));
                let grads = face_backward(&inputs.face(face), &g);
                for (k, g_corner) in grads.corners.iter().enumerate() {
                    for m in 0..3 {
                        let e = CORNER_LANES * face + 3 * k + m;
                        if let Some(v) = inputs.slot(e) {
                            vertices[v] += *g_corner * f64::from(inputs.corner_weight[e]);
                        }
                    }
                }
                store(so3, grads.so3);
                store(scale, grads.scale);
                store(offset, grads.offset);
            }
            vertices
        })
        .collect();
    let vertices = (0..v)
        .flat_map(|i| {
            let sum = blocks.iter().fold(DVec3::ZERO, |acc, b| acc + b[i]);
            [sum.x as f32, sum.y as f32, sum.z as f32]
        })
        .collect();
    GeometryGrads {
        vertices,
        so3,
        scales,
        offsets,
    }
}

#[cfg(test)]
mod tests {
    //! Central finite differences of [`face_forward`] against [`face_backward`], for every
    //! input component, on the configurations where the frame or the exponential map branch.
    use super::*;
    use crate::rng::Rng;

    /// The scatter blocks cover every face once, number at most [`MAX_SCATTER_BLOCKS`], hold at
    /// least [`MIN_FACES_PER_SCATTER_BLOCK`] faces unless the mesh has fewer, and depend on the
    /// face count alone.
    #[test]
    fn scatter_blocks_cover_the_faces_within_their_bounds() {
        for f in [
            1,
            7,
            1023,
            1024,
            1025,
            9_816,
            16_384,
            16_385,
            109_680,
            438_720,
            1 << 22,
        ] {
            let b = faces_per_scatter_block(f);
            let blocks = f.div_ceil(b);
            assert!(
                blocks * b >= f && (blocks - 1) * b < f,
                "{f} faces in blocks of {b}"
            );
            assert!(blocks <= MAX_SCATTER_BLOCKS, "{f} faces: {blocks} blocks");
            assert!(
                b >= MIN_FACES_PER_SCATTER_BLOCK.min(f),
                "{f} faces: blocks of {b}"
            );
        }
        // The quickstart's training mesh is shared by both cores.
        assert_eq!(9_816usize.div_ceil(faces_per_scatter_block(9_816)), 9);
    }

    fn loss(face: &FaceInputs, w: &[f64; OUT_LANES]) -> f64 {
        face_forward(face).iter().zip(w).map(|(a, b)| a * b).sum()
    }

    /// The 18 scalar inputs of a face, for perturbing one at a time.
    fn component(face: &mut FaceInputs, i: usize) -> &mut f64 {
        let v = match i / 3 {
            0..=2 => &mut face.corners[i / 3],
            3 => &mut face.so3,
            4 => &mut face.scale,
            _ => &mut face.offset,
        };
        &mut v[i % 3]
    }

    fn grad_component(g: &FaceGrads, i: usize) -> f64 {
        let v = match i / 3 {
            0..=2 => g.corners[i / 3],
            3 => g.so3,
            4 => g.scale,
            _ => g.offset,
        };
        v[i % 3]
    }

    const NAMES: [&str; 6] = ["p0", "p1", "p2", "so3", "scale", "offset"];

    fn check_face(what: &str, face: &FaceInputs, rng: &mut Rng) {
        // Covariances are ~|p|² and means ~|p|: weight them so both matter in the loss.
        let size = (face.corners[1] - face.corners[0])
            .length()
            .max((face.corners[2] - face.corners[0]).length());
        let w: [f64; OUT_LANES] = std::array::from_fn(|i| {
            rng.range(-1.0, 1.0) * if i < 3 { 1.0 } else { 1.0 / (size * size) }
        });
        let analytic = face_backward(face, &w);
        let eps = 1e-6;
        for i in 0..18 {
            let mut plus = *face;
            *component(&mut plus, i) += eps;
            let mut minus = *face;
            *component(&mut minus, i) -= eps;
            let numeric = (loss(&plus, &w) - loss(&minus, &w)) / (2.0 * eps);
            let a = grad_component(&analytic, i);
            assert!(a.is_finite(), "{what}: {}[{}] is {a}", NAMES[i / 3], i % 3);
            assert!(
                (a - numeric).abs() <= 1e-6 * a.abs().max(numeric.abs()) + 1e-7,
                "{what}: {}[{}]: analytic {a} vs numeric {numeric}",
                NAMES[i / 3],
                i % 3
            );
        }
    }

    fn random_vec(rng: &mut Rng, lo: f64, hi: f64) -> DVec3 {
        DVec3::new(rng.range(lo, hi), rng.range(lo, hi), rng.range(lo, hi))
    }

    fn random_scale(rng: &mut Rng) -> DVec3 {
        let mut s = random_vec(rng, 0.5, 2.0);
        for i in 0..3 {
            if rng.uniform() < 0.3 {
                s[i] = -s[i];
            }
        }
        s
    }

    #[test]
    fn half_angle_equals_the_trigonometric_form() {
        let mut rng = Rng::new(21);
        let mut cases: Vec<(f64, f64)> = (0..2000)
            .map(|_| (rng.range(-2.0, 2.0), rng.range(-2.0, 2.0)))
            .collect();
        // The axes, both signed zeros, and points just either side of the negative x-axis.
        cases.extend([
            (1.0, 0.0),
            (-1.0, 0.0),
            (-1.0, -0.0),
            (0.0, 1.0),
            (0.0, -1.0),
            (-1.0, 1e-12),
            (-1.0, -1e-12),
            (1e-300, 1e-300),
        ]);
        for (x, y) in cases {
            let (sn, cs) = (0.5 * y.atan2(x)).sin_cos();
            let (c, s) = half_angle(x, y);
            assert!(
                (c - cs).abs() <= 4.0 * f64::EPSILON && (s - sn).abs() <= 4.0 * f64::EPSILON,
                "({x}, {y}): half-angle ({c}, {s}) vs trigonometric ({cs}, {sn})"
            );
        }
        assert_eq!(half_angle(0.0, 0.0), (1.0, 0.0));
    }

    #[test]
    fn random_faces_match_finite_differences() {
        let mut rng = Rng::new(11);
        for case in 0..40 {
            // so3 from tiny (below the θ floor) through moderate to past π.
            let so3_scale = [1e-3, 0.3, 1.5, 4.0][case % 4];
            let face = FaceInputs {
                corners: std::array::from_fn(|_| random_vec(&mut rng, -0.3, 0.3)),
                so3: random_vec(&mut rng, -so3_scale, so3_scale),
                scale: random_scale(&mut rng),
                offset: random_vec(&mut rng, -1.0, 1.0),
            };
            check_face(&format!("random face {case}"), &face, &mut rng);
        }
    }

    #[test]
    fn so3_at_and_around_the_theta_floor() {
        let mut rng = Rng::new(12);
        let corners = [
            DVec3::new(0.1, 0.0, 0.2),
            DVec3::new(0.5, 0.05, 0.1),
            DVec3::new(0.2, 0.4, 0.0),
        ];
        // |r|² = 0 exactly, well below 1e-4, just past it, and a large rotation.
        for (what, r) in [
            ("zero", DVec3::ZERO),
            ("tiny", DVec3::new(3e-3, -2e-3, 1e-3)),
            ("past the floor", DVec3::new(8e-3, -6e-3, 2e-3)),
            ("large", DVec3::new(2.5, -2.0, 1.5)),
        ] {
            let face = FaceInputs {
                corners,
                so3: r,
                scale: DVec3::new(1.3, -0.7, 0.9),
                offset: DVec3::new(0.2, -0.4, 0.6),
            };
            check_face(what, &face, &mut rng);
        }
    }

    /// Close to a circle (`x² + y²` about 1e-4 of `(|f1|² + |f2|²)²`, far above the degenerate
    /// threshold): `t0` is ill-conditioned but differentiable.
    #[test]
    fn near_circle_triangle() {
        let mut rng = Rng::new(13);
        let h = 3f64.sqrt() / 2.0;
        let face = FaceInputs {
            corners: [
                DVec3::new(0.0, 0.0, 0.0),
                DVec3::new(0.2, 0.0, 0.0),
                DVec3::new(0.1, 0.2 * h * 1.01, 0.003),
            ],
            so3: DVec3::new(0.4, -0.3, 0.8),
            scale: DVec3::new(1.2, 0.6, -0.9),
            offset: DVec3::new(0.3, 0.2, -0.5),
        };
        let frame = steiner(&face.corners);
        let (f11, f22) = (frame.f1.dot(frame.f1), frame.f2.dot(frame.f2));
        let ratio = (frame.x_s.powi(2) + frame.y.powi(2)) / (f11 + f22).powi(2);
        assert!(ratio > 1e-6 && ratio < 1e-3, "not near a circle: {ratio}");
        check_face("near circle", &face, &mut rng);
    }

    /// An exact circle takes the degenerate branch (`t0 = 0`). The frame jumps under a corner
    /// perturbation, but with an isotropic in-plane scale, a rotation about the normal and an
    /// offset along it the Gaussian does not depend on `t0` (`a0a0ᵀ + a1a1ᵀ = f1f1ᵀ + f2f2ᵀ`),
    /// so every finite difference is well defined and must match.
    #[test]
    fn equilateral_triangle_takes_the_degenerate_branch() {
        let mut rng = Rng::new(14);
        let h = 3f64.sqrt() / 2.0;
        let face = FaceInputs {
            corners: [
                DVec3::new(0.0, 0.0, 0.0),
                DVec3::new(0.2, 0.0, 0.0),
                DVec3::new(0.1, 0.2 * h, 0.0),
            ],
            so3: DVec3::new(0.0, 0.0, 0.7),
            scale: DVec3::new(1.1, 1.1, -0.8),
            offset: DVec3::new(0.0, 0.0, 0.4),
        };
        let frame = steiner(&face.corners);
        assert_eq!(
            frame.x_s,
            frame.f1.dot(frame.f1) - frame.f2.dot(frame.f2) + 1.0
        );
        check_face("equilateral", &face, &mut rng);
    }

    /// A zero-area triangle: `n = 0`, so the normal column is 0 and its derivative is of order
    /// `σ/ε` — finite, but far too steep for a finite difference. With no scale along the normal,
    /// a rotation about it and no normal offset nothing reads that column, and every other path
    /// (the in-plane frame of a degenerate inellipse, `a1 = 0`) is checked.
    #[test]
    fn zero_area_triangle() {
        let mut rng = Rng::new(15);
        let corners = [
            DVec3::new(0.0, 0.1, 0.0),
            DVec3::new(0.2, 0.2, 0.1),
            DVec3::new(0.3, 0.25, 0.15),
        ];
        let face = FaceInputs {
            corners,
            so3: DVec3::new(0.0, 0.0, -0.6),
            scale: DVec3::new(0.9, -1.4, 0.0),
            offset: DVec3::new(0.5, -0.2, 0.0),
        };
        assert!(steiner(&corners).n.length() < 1e-15);
        check_face("zero area", &face, &mut rng);
        // With general parameters the gradients are huge along the normal, but finite.
        let general = FaceInputs {
            corners,
            so3: DVec3::new(0.3, 0.2, -0.6),
            scale: DVec3::new(0.9, -1.4, 0.7),
            offset: DVec3::new(0.5, -0.2, 0.3),
        };
        let g = face_backward(&general, &[1.0; OUT_LANES]);
        for i in 0..18 {
            assert!(
                grad_component(&g, i).is_finite(),
                "zero area, component {i}"
            );
        }
    }

    /// The slice functions interpolate corners through the table and scatter corner gradients
    /// back with the same weights.
    #[test]
    fn slices_interpolate_and_scatter() {
        let vertices = [
            0.0f32, 0.0, 0.0, 0.4, 0.0, 0.1, 0.1, 0.3, 0.0, 0.2, 0.2, 0.2,
        ];
        // One face: corner 0 = v0, corner 1 = (v1 + v2)/2, corner 2 = v3 (index 9 is out of
        // range and contributes nothing).
        let corner_index = [0i32, 0, 0, 1, 2, 0, 3, 9, 0];
        let corner_weight = [1.0f32, 0.0, 0.0, 0.5, 0.5, 0.0, 1.0, 1.0, 0.0];
        let so3 = [0.2f32, -0.1, 0.3];
        let scales = [1.0f32, 0.5, -2.0];
        let offsets = [0.1f32, 0.2, -0.3];
        let inputs = GeometrySlices {
            vertices: &vertices,
            so3: &so3,
            scales: &scales,
            offsets: &offsets,
            corner_index: &corner_index,
            corner_weight: &corner_weight,
        };
        let face = inputs.face(0);
        let v = |i: usize| GeometrySlices::vec3(&vertices, i);
        assert!((face.corners[1] - (v(1) + v(2)) * 0.5).length() < 1e-12);
        assert!((face.corners[2] - v(3)).length() < 1e-12);
        let out = forward(&inputs);
        let expect = face_forward(&face);
        for (o, e) in out.iter().zip(expect) {
            assert!((f64::from(*o) - e).abs() <= 1e-6 * e.abs() + 1e-9);
        }
        let grad_out = [0.3f32, -0.2, 0.5, 10.0, -4.0, 3.0, 7.0, 1.0, -6.0];
        let grads = backward(&inputs, &grad_out);
        let face_grads = face_backward(&face, &std::array::from_fn(|i| f64::from(grad_out[i])));
        let expect_v = [
            face_grads.corners[0],
            face_grads.corners[1] * 0.5,
            face_grads.corners[1] * 0.5,
            face_grads.corners[2],
        ];
        for (i, e) in expect_v.iter().enumerate() {
            let g = GeometrySlices::vec3(&grads.vertices, i);
            assert!((g - *e).length() <= 1e-6 * e.length() + 1e-9, "vertex {i}");
        }
    }
}
