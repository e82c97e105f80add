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
//! A [`Pyramid`] is several such maps sampled at the same image positions, the last one through
//! a per-texel linear tail. The forward splits the points into rayon tasks; the backward runs
//! one task per level and view, which owns that block of map rows (no two threads add into one
//! row) and computes each footprint once for both the map and the coordinate gradients.

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
    /// `value` rounded to `Self`.
    fn from_f64(value: f64) -> Self;
    /// Whether `self` is NaN.
    fn is_nan(self) -> bool;
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
            fn from_f64(value: f64) -> Self {
                value as $t
            }
            fn is_nan(self) -> bool {
                <$t>::is_nan(self)
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

/// The shape of one level of a [`Pyramid`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct LevelShape {
    /// Map height H.
    pub height: usize,
    /// Map width W.
    pub width: usize,
    /// Channels C.
    pub channels: usize,
}

/// Every level of a feature pyramid, sampled together at image-pixel coordinates.
///
/// A point `(u, v)` of a `width × height` image sits at `x = u·W_l/width − ½` (clamped to
/// `[−2, W_l + 1]`, where every corner is already outside, so the clamp changes no sample and
/// no gradient) on level `l`, and likewise in y; NaN is parked at `−2`. The **last** level's
/// sample is multiplied by `tail` (`[C_last, C_out]`, a per-texel linear map: the encoder's rgb
/// embedding, or the identity) before it is written. One output row per point and view holds
/// every level's channels in level order: `[P, N, Σ_{l<L−1} C_l + C_out]`.
#[derive(Debug, Clone, Copy)]
pub struct Pyramid<'a, T> {
    /// Each level's `[N·H_l·W_l, C_l]` rows, level after level.
    pub rows: &'a [T],
    /// Views N.
    pub views: usize,
    /// The levels, in output order.
    pub levels: &'a [LevelShape],
    /// `(width, height)` of the image the coordinates are in.
    pub image: (usize, usize),
    /// `[C_last, C_out]`, row-major.
    pub tail: &'a [T],
}

/// Where each level lives in [`Pyramid::rows`] and in an output row.
#[derive(Debug, Clone, Copy)]
struct LevelSpan {
    /// First element of the level in `rows`.
    rows_from: usize,
    /// Elements of the level in `rows`.
    rows_len: usize,
    /// First output channel.
    out_from: usize,
    /// `W_l / width`, `H_l / height`.
    scale: (f64, f64),
}

impl<'a, T: Real> Pyramid<'a, T> {
    fn last(&self) -> usize {
        self.levels.len() - 1
    }

    /// Output channels of the tail.
    fn tail_out(&self) -> usize {
        self.tail.len() / self.levels[self.last()].channels.max(1)
    }

    /// Channels of one output row.
    pub fn out_channels(&self) -> usize {
        self.levels[..self.last()]
            .iter()
            .map(|l| l.channels)
            .sum::<usize>()
            + self.tail_out()
    }

    fn spans(&self) -> Vec<LevelSpan> {
        let (mut rows_from, mut out_from) = (0, 0);
        self.levels
            .iter()
            .map(|l| {
                let rows_len = self.views * l.height * l.width * l.channels;
                let span = LevelSpan {
                    rows_from,
                    rows_len,
                    out_from,
                    scale: (
                        l.width as f64 / self.image.0 as f64,
                        l.height as f64 / self.image.1 as f64,
                    ),
                };
                rows_from += rows_len;
                out_from += l.channels;
                span
            })
            .collect()
    }

    fn maps(&self, level: usize, span: &LevelSpan) -> Maps<'a, T> {
        let l = self.levels[level];
        Maps {
            rows: &self.rows[span.rows_from..span.rows_from + span.rows_len],
            views: self.views,
            height: l.height,
            width: l.width,
            channels: l.channels,
        }
    }
}

/// Image coordinate `u` → map coordinate on a level `size` texels wide at `scale` texels per
/// image pixel (see [`Pyramid`]).
fn map_coordinate<T: Real>(u: T, scale: f64, size: usize) -> T {
    if u.is_nan() {
        return T::from_f64(-2.0);
    }
    let x = u * T::from_f64(scale) - T::from_f64(0.5);
    let (lo, hi) = (T::from_f64(-2.0), T::from_f64(size as f64 + 1.0));
    if x < lo {
        lo
    } else if x > hi {
        hi
    } else {
        x
    }
}

impl<T: Real> Maps<'_, T> {
    /// `Σ_corners w·row` added into `acc`.
    fn accumulate(&self, fp: &Footprint<T>, acc: &mut [T]) {
        for corner in 0..4 {
            if fp.row[corner] == usize::MAX {
                continue;
            }
            let w = fp.weight[corner];
            for (a, &v) in acc.iter_mut().zip(self.row(fp.row[corner])) {
                *a += w * v;
            }
        }
    }
}

/// `out[j] = Σ_k s[k]·tail[k][j]`.
fn project<T: Real>(s: &[T], tail: &[T], out: &mut [T]) {
    let width = out.len();
    out.fill(T::ZERO);
    for (k, &sk) in s.iter().enumerate() {
        for (o, &t) in out.iter_mut().zip(&tail[k * width..(k + 1) * width]) {
            *o += sk * t;
        }
    }
}

/// Samples every level of every view at its points: `uv` is `[N, P, 2]` image-pixel
/// coordinates; returns `[P, N, C_out]` (see [`Pyramid`]).
pub fn forward<T: Real>(pyr: &Pyramid<'_, T>, uv: &[T]) -> Vec<T> {
    let n = pyr.views;
    let width = pyr.out_channels();
    let p = uv.len() / (2 * n).max(1);
    let spans = pyr.spans();
    let last = pyr.last();
    let mut out = vec![T::ZERO; p * n * width];
    out.par_chunks_mut(POINTS_PER_TASK * n * width)
        .enumerate()
        .for_each(|(task, chunk)| {
            let mut tail_sample = vec![T::ZERO; pyr.levels[last].channels];
            for (local, point_out) in chunk.chunks_mut(n * width).enumerate() {
                let point = task * POINTS_PER_TASK + local;
                for (view, row) in point_out.chunks_mut(width).enumerate() {
                    let k = view * p + point;
                    let (u, v) = (uv[2 * k], uv[2 * k + 1]);
                    for (level, span) in spans.iter().enumerate() {
                        let maps = pyr.maps(level, span);
                        let x = map_coordinate(u, span.scale.0, maps.width);
                        let y = map_coordinate(v, span.scale.1, maps.height);
                        let fp = maps.footprint(view, x, y);
                        if level == last {
                            tail_sample.fill(T::ZERO);
                            maps.accumulate(&fp, &mut tail_sample);
                            project(&tail_sample, pyr.tail, &mut row[span.out_from..]);
                        } else {
                            let acc = &mut row[span.out_from..span.out_from + maps.channels];
                            maps.accumulate(&fp, acc);
                        }
                    }
                }
            }
        });
    out
}

/// Gradients of [`forward`].
#[derive(Debug)]
pub struct PyramidGrads<T> {
    /// Of [`Pyramid::rows`], when asked for.
    pub rows: Option<Vec<T>>,
    /// Of `uv`, `[N, P, 2]`.
    pub uv: Vec<T>,
    /// Of [`Pyramid::tail`], when asked for.
    pub tail: Option<Vec<T>>,
}

/// One task of [`backward`]: a view of a level, with the part of the rows' gradient it owns.
struct BlockTask<'g, T> {
    level: usize,
    view: usize,
    rows_grad: Option<&'g mut [T]>,
}

/// What one [`BlockTask`] returns: its level's coordinate gradients for its view's points
/// (`[P]` pairs, already `∂/∂(u, v)`), and for the last level the view's part of `∂tail`.
struct BlockGrads<T> {
    level: usize,
    view: usize,
    uv: Vec<(T, T)>,
    tail: Option<Vec<T>>,
}

/// Gradients of [`forward`] given `grad` (`[P, N, C_out]`).
///
/// One task per level and view: it recomputes each point's footprint once and from it adds
/// the coordinate gradient (`Σ_corners (∂w/∂x)·⟨g, row⟩`, times `∂x/∂u = W_l/width`) and, when
/// `want_rows`, scatters `w·g` into the rows of its own map block, which no other task touches.
/// On the last level `g` is first taken back through the tail (`g·tailᵀ`), and `∂tail` is
/// `Σ_points sampleᵀ·g`. The per-level coordinate gradients and the per-view `∂tail` are then
/// added in level and view order, so the result does not depend on the thread count.
pub fn backward<T: Real>(
    pyr: &Pyramid<'_, T>,
    uv: &[T],
    grad: &[T],
    want_rows: bool,
    want_tail: bool,
) -> PyramidGrads<T> {
    let n = pyr.views;
    let width = pyr.out_channels();
    let p = uv.len() / (2 * n).max(1);
    let spans = pyr.spans();
    let last = pyr.last();
    let tail_out = pyr.tail_out();

    let mut rows_grad = want_rows.then(|| vec![T::ZERO; pyr.rows.len()]);
    let mut tasks: Vec<BlockTask<'_, T>> = Vec::with_capacity(spans.len() * n);
    match rows_grad.as_mut() {
        Some(all) => {
            let mut rest: &mut [T] = all;
            for (level, span) in spans.iter().enumerate() {
                let (block, tail) = rest.split_at_mut(span.rows_len);
                rest = tail;
                let per_view = span.rows_len / n.max(1);
                for (view, rows) in block.chunks_mut(per_view.max(1)).enumerate() {
                    tasks.push(BlockTask {
                        level,
                        view,
                        rows_grad: Some(rows),
                    });
                }
            }
        }
        None => {
            for level in 0..spans.len() {
                for view in 0..n {
                    tasks.push(BlockTask {
                        level,
                        view,
                        rows_grad: None,
                    });
                }
            }
        }
    }

    let blocks: Vec<BlockGrads<T>> = tasks
        .into_par_iter()
        .map(|task| {
            let BlockTask {
                level,
                view,
                mut rows_grad,
            } = task;
            let span = &spans[level];
            let maps = pyr.maps(level, span);
            let c = maps.channels;
            let first_row = view * maps.height * maps.width;
            let (su, sv) = (T::from_f64(span.scale.0), T::from_f64(span.scale.1));
            let is_tail = level == last;
            let mut tail_grad = (is_tail && want_tail).then(|| vec![T::ZERO; c * tail_out]);
            let mut sample = vec![T::ZERO; c];
            let mut g_sample = vec![T::ZERO; c];
            let mut coords = Vec::with_capacity(p);
            for point in 0..p {
                let k = view * p + point;
                let (u, v) = (uv[2 * k], uv[2 * k + 1]);
                let x = map_coordinate(u, span.scale.0, maps.width);
                let y = map_coordinate(v, span.scale.1, maps.height);
                let fp = maps.footprint(view, x, y);
                let g_row = &grad[(point * n + view) * width..][..width];
                let g: &[T] = if is_tail {
                    let g_out = &g_row[span.out_from..span.out_from + tail_out];
                    for (kk, gs) in g_sample.iter_mut().enumerate() {
                        *gs = lanes::dot(g_out, &pyr.tail[kk * tail_out..(kk + 1) * tail_out]);
                    }
                    if let Some(tg) = tail_grad.as_mut() {
                        sample.fill(T::ZERO);
                        maps.accumulate(&fp, &mut sample);
                        for (kk, &s) in sample.iter().enumerate() {
                            for (t, &go) in
                                tg[kk * tail_out..(kk + 1) * tail_out].iter_mut().zip(g_out)
                            {
                                *t += s * go;
                            }
                        }
                    }
                    &g_sample
                } else {
                    &g_row[span.out_from..span.out_from + c]
                };
                let (mut gx, mut gy) = (T::ZERO, T::ZERO);
                for corner in 0..4 {
                    if fp.row[corner] == usize::MAX {
                        continue;
                    }
                    let gv = lanes::dot(g, maps.row(fp.row[corner]));
                    gx += fp.d_dx[corner] * gv;
                    gy += fp.d_dy[corner] * gv;
                    if let Some(rows) = rows_grad.as_mut() {
                        let w = fp.weight[corner];
                        let r = fp.row[corner] - first_row;
                        for (dst, &gv) in rows[r * c..(r + 1) * c].iter_mut().zip(g) {
                            *dst += w * gv;
                        }
                    }
                }
                coords.push((gx * su, gy * sv));
            }
            BlockGrads {
                level,
                view,
                uv: coords,
                tail: tail_grad,
            }
        })
        .collect();

    // Tasks were made level-major, view-minor, and `collect` keeps that order.
    let mut uv_grad = vec![T::ZERO; n * p * 2];
    let mut tail_grad = (want_tail).then(|| vec![T::ZERO; pyr.tail.len()]);
    for block in blocks {
        debug_assert!(block.level < spans.len() && block.view < n);
        let dst = &mut uv_grad[block.view * p * 2..(block.view + 1) * p * 2];
        for (pair, (gx, gy)) in dst.chunks_exact_mut(2).zip(block.uv) {
            pair[0] += gx;
            pair[1] += gy;
        }
        if let (Some(total), Some(part)) = (tail_grad.as_mut(), block.tail) {
            for (t, v) in total.iter_mut().zip(part) {
                *t += v;
            }
        }
    }
    PyramidGrads {
        rows: rows_grad,
        uv: uv_grad,
        tail: tail_grad,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const ONE_LEVEL: [LevelShape; 1] = [LevelShape {
        height: 2,
        width: 3,
        channels: 2,
    }];
    const IDENTITY: [f64; 4] = [1.0, 0.0, 0.0, 1.0];

    /// `backward`'s gradients against central differences of `Σ grad·forward` for the
    /// coordinates `check_uv` selects, and against unit steps for every `row_step`-th map value
    /// and every tail value (the loss is linear in both, so a unit step is exact). Returns the
    /// gradients.
    fn assert_matches_differences(
        pyr: &Pyramid<'_, f64>,
        uv: &[f64],
        grad: &[f64],
        check_uv: impl Fn(usize) -> bool,
        row_step: usize,
    ) -> PyramidGrads<f64> {
        let grads = backward(pyr, uv, grad, true, true);
        let loss = |pyr: &Pyramid<'_, f64>, uv: &[f64]| {
            forward(pyr, uv)
                .iter()
                .zip(grad)
                .map(|(a, b)| a * b)
                .sum::<f64>()
        };
        let eps = 1e-6;
        for k in (0..uv.len()).filter(|&k| check_uv(k)) {
            let (mut plus, mut minus) = (uv.to_vec(), uv.to_vec());
            plus[k] += eps;
            minus[k] -= eps;
            let fd = (loss(pyr, &plus) - loss(pyr, &minus)) / (2.0 * eps);
            assert!(
                (grads.uv[k] - fd).abs() < 1e-6,
                "uv[{k}]: {} vs {fd}",
                grads.uv[k]
            );
        }
        // The loss is linear in the map rows and in the tail: a unit step is its derivative.
        let base = loss(pyr, uv);
        let unit_steps = |what: &str,
                          values: &[f64],
                          analytic: &[f64],
                          step: usize,
                          loss_with: &dyn Fn(&[f64]) -> f64| {
            for i in (0..values.len()).step_by(step) {
                let mut plus = values.to_vec();
                plus[i] += 1.0;
                let fd = loss_with(&plus) - base;
                assert!((analytic[i] - fd).abs() < 1e-9, "{what} value {i}");
            }
        };
        let rows_g = grads.rows.as_ref().expect("asked for");
        unit_steps("row", pyr.rows, rows_g, row_step, &|rows| {
            loss(&Pyramid { rows, ..*pyr }, uv)
        });
        let tail_g = grads.tail.as_ref().expect("asked for");
        unit_steps("tail", pyr.tail, tail_g, 1, &|tail| {
            loss(&Pyramid { tail, ..*pyr }, uv)
        });
        grads
    }

    /// A 2×3 one-view map sampled at image = map resolution (so `x = u − ½`): inside, on the
    /// border and outside, against hand-computed values, and central differences of the
    /// forward for the coordinate gradients.
    #[test]
    fn forward_and_backward_by_hand() {
        // rows [(j·3 + i)][c], 2 channels: value = 10·i + j, and its negative.
        let rows: Vec<f64> = (0..2)
            .flat_map(|j| (0..3).flat_map(move |i| [10.0 * i as f64 + j as f64, -1.0]))
            .collect();
        let pyr = Pyramid {
            rows: &rows,
            views: 1,
            levels: &ONE_LEVEL,
            image: (3, 2),
            tail: &IDENTITY,
        };
        let at = |x: &[f64], y: &[f64]| -> Vec<f64> {
            x.iter()
                .zip(y)
                .flat_map(|(x, y)| [x + 0.5, y + 0.5])
                .collect()
        };
        let x = [0.25, 1.5, -0.5, 2.5, 5.0];
        let y = [0.5, 0.0, 0.5, 1.0, 0.0];
        let out = forward(&pyr, &at(&x, &y));
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
        let uv = at(&x, &y);
        let grad: Vec<f64> = (0..out.len()).map(|i| 1.0 + 0.1 * i as f64).collect();
        assert_matches_differences(&pyr, &uv, &grad, |_| true, 1);
    }

    /// Several views and levels with a projecting tail: the backward against central
    /// differences for the coordinates and unit steps for the rows and the tail; NaN and
    /// far-away points sample zero with zero gradient.
    #[test]
    fn pyramid_gradients_match_differences() {
        let mut rng = lifegom_render::rng::Rng::new(5);
        let levels = [
            LevelShape {
                height: 6,
                width: 8,
                channels: 3,
            },
            LevelShape {
                height: 3,
                width: 4,
                channels: 2,
            },
            LevelShape {
                height: 6,
                width: 8,
                channels: 2,
            },
        ];
        let views = 2;
        let total: usize = levels
            .iter()
            .map(|l| views * l.height * l.width * l.channels)
            .sum();
        let rows: Vec<f64> = (0..total).map(|_| rng.range(-1.0, 1.0)).collect();
        let tail: Vec<f64> = (0..2 * 5).map(|_| rng.range(-1.0, 1.0)).collect();
        let pyr = Pyramid {
            rows: &rows,
            views,
            levels: &levels,
            image: (16, 12),
            tail: &tail,
        };
        assert_eq!(pyr.out_channels(), 3 + 2 + 5);
        let p = 7;
        let mut uv: Vec<f64> = (0..views * p)
            .flat_map(|_| [rng.range(-1.0, 17.0), rng.range(-1.0, 13.0)])
            .collect();
        uv[2] = f64::NAN;
        uv[5] = 1e9;
        let grad: Vec<f64> = (0..p * views * 10).map(|_| rng.range(-1.0, 1.0)).collect();
        let out = forward(&pyr, &uv);
        let point_view = |k: usize| (k % p, k / p);
        for k in [1usize, 2] {
            let (point, view) = point_view(k);
            let row = &out[(point * views + view) * 10..][..10];
            assert!(row.iter().all(|&v| v == 0.0), "point {k} samples zero");
        }
        let grads =
            assert_matches_differences(&pyr, &uv, &grad, |k| uv[k].is_finite() && uv[k] < 1e8, 5);
        assert_eq!(&grads.uv[2..6], &[0.0; 4]);
        // Without the rows and tail asked for, the coordinate gradient is the same.
        let only_uv = backward(&pyr, &uv, &grad, false, false);
        assert_eq!(only_uv.uv, grads.uv);
        assert!(only_uv.rows.is_none() && only_uv.tail.is_none());
    }
}
