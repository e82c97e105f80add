//! Bilinear sampling on host slices: the forward and the hand-written backward of
//! [`super::op::BilinearSampleOps`] on the CPU backends (design.md §7.2).
//!
//! A map is stored channel-last, `rows[(b·H + j)·W + i][c]`; a point of view `b` sits at map
//! pixel coordinates `(x, y)` (pixel `i` has its centre at `x = i`). With `x₀ = ⌊x⌋`,
//! `f_x = x − x₀` (and the same in y) the sample is
//!
//! `s = Σ_corners w_x·w_y·rows[corner]`, `w_x ∈ {1 − f_x, f_x}` for `x₀`, `x₀ + 1`,
//!
//! where a corner outside the map has weight 0 (zero padding). The backward is the transpose
//! of that sum for the map values (a scatter-add of `w·g` into each corner's row) and, for the
//! coordinates, the slope of the weights: `∂w_x/∂x = −1` for `x₀`, `+1` for `x₀ + 1`, zero for
//! a corner outside (its weight is the constant 0). This is exactly the gradient of the tensor-op
//! composition it replaces ([`super::Level::sample_reference`]), which stays as the test
//! reference.
//!
//! Work is split by rayon over points (forward, coordinate gradients) and over views (map
//! gradients: each view owns a disjoint block of rows, so no two threads add into one row).

use std::ops::{Add, AddAssign, Mul, Sub};

use rayon::prelude::*;

use crate::lanes;

/// Points per rayon task: small enough to balance two cores, large enough to amortise the task.
const POINTS_PER_TASK: usize = 256;

/// The float types the kernels run in (`f32`, and `f64` for the precision tests).
pub trait Real:
    Copy
    + Send
    + Sync
    + PartialOrd
    + Add<Output = Self>
    + Sub<Output = Self>
    + Mul<Output = Self>
    + AddAssign
    + Default
{
    /// 0.
    const ZERO: Self;
    /// 1.
    const ONE: Self;
    /// `⌊self⌋` as an index (callers pass finite, clamped coordinates).
    fn floor_index(self) -> (i64, Self);
}

macro_rules! impl_real {
    ($($t:ty),*) => {$(
        impl Real for $t {
            const ZERO: Self = 0.0;
            const ONE: Self = 1.0;
            fn floor_index(self) -> (i64, Self) {
                let f = self.floor();
                (f as i64, f)
            }
        }
    )*};
}

impl_real!(f32, f64);

/// The maps and points of one call.
#[derive(Debug, Clone, Copy)]
pub struct Maps<'a, T> {
    /// `[N·H·W, C]`, row-major.
    pub rows: &'a [T],
    /// Views N.
    pub views: usize,
    /// Map height H.
    pub height: usize,
    /// Map width W.
    pub width: usize,
    /// Channels C.
    pub channels: usize,
}

/// The bilinear footprint of one point: up to four rows and their weights and weight slopes.
struct Footprint<T> {
    /// Row index of each corner inside the map (`usize::MAX` for one outside).
    row: [usize; 4],
    /// `w_x·w_y` per corner, 0 outside.
    weight: [T; 4],
    /// `∂(w_x·w_y)/∂x` per corner.
    d_dx: [T; 4],
    /// `∂(w_x·w_y)/∂y` per corner.
    d_dy: [T; 4],
}

impl<T: Real> Maps<'_, T> {
    /// Corner order `(x₀, y₀), (x₀+1, y₀), (x₀, y₀+1), (x₀+1, y₀+1)`, as the reference's.
    fn footprint(&self, view: usize, x: T, y: T) -> Footprint<T> {
        let (x0, x0f) = x.floor_index();
        let (y0, y0f) = y.floor_index();
        let (fx, fy) = (x - x0f, y - y0f);
        let inside_x = |i: i64| i >= 0 && i < self.width as i64;
        let inside_y = |j: i64| j >= 0 && j < self.height as i64;
        let zero = T::ZERO;
        let one = T::ONE;
        // Weight and slope along one axis for the low and high corner.
        let axis = |inside_lo: bool, inside_hi: bool, f: T| {
            let (w_lo, s_lo) = if inside_lo {
                (one - f, zero - one)
            } else {
                (zero, zero)
            };
            let (w_hi, s_hi) = if inside_hi { (f, one) } else { (zero, zero) };
            ([w_lo, w_hi], [s_lo, s_hi])
        };
        let (wx, sx) = axis(inside_x(x0), inside_x(x0 + 1), fx);
        let (wy, sy) = axis(inside_y(y0), inside_y(y0 + 1), fy);
        let mut fp = Footprint {
            row: [usize::MAX; 4],
            weight: [zero; 4],
            d_dx: [zero; 4],
            d_dy: [zero; 4],
        };
        for k in 0..4 {
            let (a, b) = (k & 1, k >> 1);
            let (i, j) = (x0 + a as i64, y0 + b as i64);
            if inside_x(i) && inside_y(j) {
                fp.row[k] = (view * self.height + j as usize) * self.width + i as usize;
            }
            fp.weight[k] = wx[a] * wy[b];
            fp.d_dx[k] = sx[a] * wy[b];
            fp.d_dy[k] = wx[a] * sy[b];
        }
        fp
    }

    fn row(&self, r: usize) -> &[T] {
        &self.rows[r * self.channels..(r + 1) * self.channels]
    }
}

/// Samples every view's maps at its points: `x`, `y` are `[N, P]` map-pixel coordinates
/// (finite); returns `[P, N, C]`.
pub fn forward<T: Real>(maps: &Maps<'_, T>, x: &[T], y: &[T]) -> Vec<T> {
    let (n, c) = (maps.views, maps.channels);
    let p = x.len() / n.max(1);
    let mut out = vec![T::ZERO; p * n * c];
    out.par_chunks_mut(POINTS_PER_TASK * n * c)
        .enumerate()
        .for_each(|(task, chunk)| {
            for (local, point_out) in chunk.chunks_mut(n * c).enumerate() {
                let point = task * POINTS_PER_TASK + local;
                for (view, acc) in point_out.chunks_mut(c).enumerate() {
                    let k = view * p + point;
                    let fp = maps.footprint(view, x[k], y[k]);
                    for corner in 0..4 {
                        if fp.row[corner] == usize::MAX {
                            continue;
                        }
                        let w = fp.weight[corner];
                        for (a, &v) in acc.iter_mut().zip(maps.row(fp.row[corner])) {
                            *a += w * v;
                        }
                    }
                }
            }
        });
    out
}

/// Gradients of [`forward`] given `grad` (`[P, N, C]`): the map rows' (`[N·H·W, C]`, when
/// `want_rows`) and the coordinates' (`[N, P]` each).
pub fn backward<T: Real>(
    maps: &Maps<'_, T>,
    x: &[T],
    y: &[T],
    grad: &[T],
    want_rows: bool,
) -> (Option<Vec<T>>, Vec<T>, Vec<T>) {
    let (n, c) = (maps.views, maps.channels);
    let p = x.len() / n.max(1);
    let grad_at = |point: usize, view: usize| &grad[(point * n + view) * c..][..c];

    let mut grad_xy = vec![(T::ZERO, T::ZERO); n * p];
    grad_xy
        .par_chunks_mut(POINTS_PER_TASK)
        .enumerate()
        .for_each(|(task, chunk)| {
            for (local, out) in chunk.iter_mut().enumerate() {
                let k = task * POINTS_PER_TASK + local;
                let (view, point) = (k / p, k % p);
                let fp = maps.footprint(view, x[k], y[k]);
                let g = grad_at(point, view);
                let (mut gx, mut gy) = (T::ZERO, T::ZERO);
                for corner in 0..4 {
                    if fp.row[corner] == usize::MAX {
                        continue;
                    }
                    let gv = lanes::dot(g, maps.row(fp.row[corner]));
                    gx += fp.d_dx[corner] * gv;
                    gy += fp.d_dy[corner] * gv;
                }
                *out = (gx, gy);
            }
        });
    let (grad_x, grad_y) = grad_xy.into_iter().unzip();

    let grad_rows = want_rows.then(|| {
        let rows_per_view = maps.height * maps.width;
        let mut rows = vec![T::ZERO; maps.rows.len()];
        rows.par_chunks_mut(rows_per_view * c)
            .enumerate()
            .for_each(|(view, block)| {
                let first_row = view * rows_per_view;
                for point in 0..p {
                    let k = view * p + point;
                    let fp = maps.footprint(view, x[k], y[k]);
                    let g = grad_at(point, view);
                    for corner in 0..4 {
                        if fp.row[corner] == usize::MAX {
                            continue;
                        }
                        let w = fp.weight[corner];
                        let r = fp.row[corner] - first_row;
                        for (dst, &gv) in block[r * c..(r + 1) * c].iter_mut().zip(g) {
                            *dst += w * gv;
                        }
                    }
                }
            });
        rows
    });
    (grad_rows, grad_x, grad_y)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A 2×3 one-view map: inside, on the border and outside, against hand-computed values and
    /// central differences of the forward for the coordinate gradients.
    #[test]
    fn forward_and_backward_by_hand() {
        // rows [(j·3 + i)][c], 2 channels: value = 10·i + j, and its negative.
        let rows: Vec<f64> = (0..2)
            .flat_map(|j| (0..3).flat_map(move |i| [10.0 * i as f64 + j as f64, -1.0]))
            .collect();
        let maps = Maps {
            rows: &rows,
            views: 1,
            height: 2,
            width: 3,
            channels: 2,
        };
        let x = [0.25, 1.5, -0.5, 2.5, 5.0];
        let y = [0.5, 0.0, 0.5, 1.0, 0.0];
        let out = forward(&maps, &x, &y);
        // Inside: bilinear in a linear ramp is the ramp.
        assert!((out[0] - 3.0).abs() < 1e-12 && (out[1] + 1.0).abs() < 1e-12);
        assert!((out[2] - 15.0).abs() < 1e-12);
        // Half outside on the left: only the x₀ + 1 = 0 column, weight 0.5.
        assert!((out[4] - 0.5 * 0.5).abs() < 1e-12, "{}", out[4]);
        // x = 2.5 fades the right column by half; y = 1 sits on the last row.
        assert!((out[6] - 0.5 * 21.0).abs() < 1e-12, "{}", out[6]);
        assert_eq!(&out[8..10], &[0.0, 0.0]);

        // Gradients away from integer coordinates, where the bilinear weights have kinks.
        let y = [0.5, 0.3, 0.5, 0.7, 0.2];
        let grad: Vec<f64> = (0..out.len()).map(|i| 1.0 + 0.1 * i as f64).collect();
        let (rows_g, gx, gy) = backward(&maps, &x, &y, &grad, true);
        let loss = |x: &[f64], y: &[f64]| {
            forward(&maps, x, y)
                .iter()
                .zip(&grad)
                .map(|(a, b)| a * b)
                .sum::<f64>()
        };
        let eps = 1e-6;
        for k in 0..x.len() {
            let (mut xp, mut xm) = (x, x);
            xp[k] += eps;
            xm[k] -= eps;
            let fd = (loss(&xp, &y) - loss(&xm, &y)) / (2.0 * eps);
            assert!((gx[k] - fd).abs() < 1e-6, "x[{k}]: {} vs {fd}", gx[k]);
            let (mut yp, mut ym) = (y, y);
            yp[k] += eps;
            ym[k] -= eps;
            let fd = (loss(&x, &yp) - loss(&x, &ym)) / (2.0 * eps);
            assert!((gy[k] - fd).abs() < 1e-6, "y[{k}]: {} vs {fd}", gy[k]);
        }
        // The loss is linear in the rows: a unit step of each row value is exact.
        let rows_g = rows_g.expect("asked for");
        for r in 0..rows.len() {
            let mut plus = rows.clone();
            plus[r] += 1.0;
            let m = Maps {
                rows: &plus,
                ..maps
            };
            let fd = forward(&m, &x, &y)
                .iter()
                .zip(&grad)
                .map(|(a, b)| a * b)
                .sum::<f64>()
                - loss(&x, &y);
            assert!((rows_g[r] - fd).abs() < 1e-9, "row value {r}");
        }
    }
}
