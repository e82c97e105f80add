//! Reductions over host slices in independent lanes, for the CPU kernels' short rows.
//!
//! A sum written as one running total (`s = s + a[i]·b[i]`) is a chain of dependent float adds:
//! each waits for the previous one (about four cycles), and the compiler may not reorder it,
//! because float addition is not associative. The CPU kernels reduce thousands of short rows per
//! call (a pixel's channels in the sampling backward, a head's channels in attention, a row in
//! LayerNorm), so that latency, not arithmetic, was their cost. Here a row is summed in
//! [`LANES`] running totals that advance together (one vector register's worth), added pairwise
//! at the end, and the rest after the last full group of lanes goes into one more total. The
//! result differs from the running total by float rounding only, and it is the same on every
//! run and thread count: the order depends on the row length alone.

use std::ops::{Add, Mul, Sub};

/// Independent running totals per reduction: eight `f32` fill one 256-bit register.
pub(crate) const LANES: usize = 8;

/// What the reductions need of a float type (`f32`, and `f64` in the precision tests).
pub(crate) trait LaneFloat:
    Copy + Default + Add<Output = Self> + Sub<Output = Self> + Mul<Output = Self>
{
}

impl<T: Copy + Default + Add<Output = T> + Sub<Output = T> + Mul<Output = T>> LaneFloat for T {}

/// `Σ f(i)` for `i < n`, in [`LANES`] totals (module docs).
#[inline(always)]
fn reduce<T: LaneFloat>(n: usize, f: impl Fn(usize) -> T) -> T {
    let mut acc = [T::default(); LANES];
    let full = n - n % LANES;
    for base in (0..full).step_by(LANES) {
        for (lane, total) in acc.iter_mut().enumerate() {
            *total = *total + f(base + lane);
        }
    }
    let mut rest = T::default();
    for i in full..n {
        rest = rest + f(i);
    }
    let [a0, a1, a2, a3, a4, a5, a6, a7] = acc;
    (((a0 + a4) + (a1 + a5)) + ((a2 + a6) + (a3 + a7))) + rest
}

/// `⟨a, b⟩` over the shorter of the two.
#[inline]
pub(crate) fn dot<T: LaneFloat>(a: &[T], b: &[T]) -> T {
    let n = a.len().min(b.len());
    let (a, b) = (&a[..n], &b[..n]);
    reduce(n, |i| a[i] * b[i])
}

/// `Σ a`.
#[inline]
pub(crate) fn sum<T: LaneFloat>(a: &[T]) -> T {
    reduce(a.len(), |i| a[i])
}

/// `Σ (a − m)²`.
#[inline]
pub(crate) fn sum_squared_deviation<T: LaneFloat>(a: &[T], m: T) -> T {
    reduce(a.len(), |i| (a[i] - m) * (a[i] - m))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Against plain `f64` sums at every length around the lane groups, in `f64` (where the
    /// reordering changes nothing measurable) and `f32` (within rounding).
    #[test]
    fn reductions_equal_plain_sums() {
        for n in 0..3 * LANES + 2 {
            let a: Vec<f64> = (0..n).map(|i| (i as f64 * 0.37).sin() + 0.1).collect();
            let b: Vec<f64> = (0..n + 3).map(|i| (i as f64 * 1.3).cos()).collect();
            let m = 0.25;
            let plain_dot: f64 = a.iter().zip(&b).map(|(x, y)| x * y).sum();
            let plain_sum: f64 = a.iter().sum();
            let plain_dev: f64 = a.iter().map(|x| (x - m) * (x - m)).sum();
            assert!((dot(&a, &b) - plain_dot).abs() <= 1e-12, "dot, n = {n}");
            assert!((sum(&a) - plain_sum).abs() <= 1e-12, "sum, n = {n}");
            assert!(
                (sum_squared_deviation(&a, m) - plain_dev).abs() <= 1e-12,
                "deviation, n = {n}"
            );
            let a32: Vec<f32> = a.iter().map(|&x| x as f32).collect();
            let b32: Vec<f32> = b.iter().map(|&x| x as f32).collect();
            let scale = 1.0 + a.iter().zip(&b).map(|(x, y)| (x * y).abs()).sum::<f64>();
            assert!(
                (f64::from(dot(&a32, &b32)) - plain_dot).abs() <= 1e-6 * scale,
                "f32 dot, n = {n}"
            );
        }
    }
}
