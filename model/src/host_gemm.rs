//! One home for the CPU ops' matrix products on host slices (design.md §1.4).
//!
//! [`gemm_into`] multiplies strided views with the `gemm` crate: a transpose, a column block of a
//! wider matrix or one head's channels are strides and an offset, never a copy. Products above
//! [`PARALLEL_MACS`] multiply-adds run on rayon's threads. `gemm` reduces each output element in
//! a fixed order whatever the thread count, so results are deterministic.

use burn::tensor::Element;
use bytemuck::Pod;

/// Products of at least this many multiply-adds run on rayon's threads; smaller ones cost less
/// on the calling thread than a hand-off. Burn's Flex uses `192³` ≈ 7.1 M, which leaves the
/// Point Transformer's and the heads' ~1–5 M products on one of two cores.
pub const PARALLEL_MACS: usize = 1 << 21;

/// The float types the products run in (`f32`, and `f64` for the precision tests).
pub(crate) trait GemmFloat:
    Element + Pod + Copy + Send + Sync + Default + std::ops::AddAssign
{
    /// The multiplicative identity (gemm's scale factors).
    const ONE: Self;
    /// `value` in this precision.
    fn from_f64(value: f64) -> Self;
}

impl GemmFloat for f32 {
    const ONE: Self = 1.0;
    fn from_f64(value: f64) -> Self {
        value as f32
    }
}

impl GemmFloat for f64 {
    const ONE: Self = 1.0;
    fn from_f64(value: f64) -> Self {
        value
    }
}

/// A strided matrix view: element `(r, c)` at `data[r·row + c·col]`.
#[derive(Clone, Copy)]
pub(crate) struct View<'a, T> {
    pub data: &'a [T],
    pub row: usize,
    pub col: usize,
}

impl<'a, T> View<'a, T> {
    /// A row-major matrix `width` elements wide.
    pub fn row_major(data: &'a [T], width: usize) -> Self {
        Self {
            data,
            row: width,
            col: 1,
        }
    }

    /// The transpose of a row-major matrix `width` elements wide: its data, strides swapped.
    pub fn transposed(data: &'a [T], width: usize) -> Self {
        Self {
            data,
            row: 1,
            col: width,
        }
    }

    /// The same view starting `offset` elements later (a column block, one head's channels).
    pub fn offset(self, offset: usize) -> Self {
        Self {
            data: &self.data[offset.min(self.data.len())..],
            ..self
        }
    }
}

/// The output of [`gemm_into`]: `[m, n]` rows `row` elements apart (`row ≥ n`), so a product
/// can fill a column block of a wider matrix.
pub(crate) struct Out<'a, T> {
    pub data: &'a mut [T],
    pub row: usize,
}

impl<'a, T> Out<'a, T> {
    /// A row-major `[.., width]` output.
    pub fn row_major(data: &'a mut [T], width: usize) -> Self {
        Self { data, row: width }
    }
}

/// Whether [`gemm_into`] adds to the output or overwrites it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Write {
    /// `dst = scale·lhs·rhs`.
    Overwrite,
    /// `dst += scale·lhs·rhs`.
    Accumulate,
}

/// `dst` `[m, n]` `(+)= scale·lhs·rhs` for `lhs` `[m, k]`, `rhs` `[k, n]`.
///
/// Panics if a view or the output is too short for its shape (a caller's bug, not bad input).
pub(crate) fn gemm_into<T: GemmFloat>(
    dst: Out<'_, T>,
    (m, n, k): (usize, usize, usize),
    lhs: View<'_, T>,
    rhs: View<'_, T>,
    write: Write,
    scale: T,
) {
    let last = |v: View<'_, T>, rows: usize, cols: usize| {
        (rows > 0 && cols > 0).then(|| (rows - 1) * v.row + (cols - 1) * v.col)
    };
    assert!(
        m == 0 || n == 0 || (n <= dst.row && (m - 1) * dst.row + n <= dst.data.len()),
        "gemm: output buffer too small"
    );
    assert!(
        last(lhs, m, k).is_none_or(|i| i < lhs.data.len())
            && last(rhs, k, n).is_none_or(|i| i < rhs.data.len()),
        "gemm: operand views out of bounds"
    );
    if m == 0 || n == 0 {
        return;
    }
    let accumulate = write == Write::Accumulate;
    if k == 0 {
        if !accumulate {
            for row in dst.data.chunks_mut(dst.row).take(m) {
                row[..n].fill(T::default());
            }
        }
        return;
    }
    let parallelism = if m.saturating_mul(n).saturating_mul(k) >= PARALLEL_MACS {
        gemm::Parallelism::Rayon(0)
    } else {
        gemm::Parallelism::None
    };
    // SAFETY: every index gemm reads is `r·row + c·col` for `r < rows`, `c < cols` of a view,
    // at most the last index checked above, and it writes `dst[i·row + j]` for `i < m`, `j < n`
    // within the checked length. `dst` is borrowed mutably, so nothing else aliases it. `T` is
    // f32 or f64, which gemm supports.
    unsafe {
        gemm::gemm(
            m,
            n,
            k,
            dst.data.as_mut_ptr(),
            1,
            dst.row as isize,
            accumulate,
            lhs.data.as_ptr(),
            lhs.col as isize,
            lhs.row as isize,
            rhs.data.as_ptr(),
            rhs.col as isize,
            rhs.row as isize,
            T::ONE,
            scale,
            false,
            false,
            false,
            parallelism,
        );
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Strided views, a column block of a wider output, overwrite and accumulate, a scale: all
    /// against a direct triple loop.
    #[test]
    fn strided_products_match_direct_sums() {
        let mut rng = lifegom_render::rng::Rng::new(5);
        let mut random = |n: usize| (0..n).map(|_| rng.range(-1.0, 1.0)).collect::<Vec<f64>>();
        let (m, n, k) = (7usize, 3usize, 5usize);
        // lhs is columns 2..2+k of a [m, 9] matrix; rhs is the transpose of a [n, k] matrix.
        let (a, b) = (random(m * 9), random(n * k));
        let lhs = View::row_major(&a, 9).offset(2);
        let rhs = View::transposed(&b, k);
        // The output fills columns 1..1+n of a [m, 6] matrix.
        let before = random(m * 6);
        for write in [Write::Overwrite, Write::Accumulate] {
            let mut out = before.clone();
            gemm_into(
                Out {
                    data: &mut out[1..],
                    row: 6,
                },
                (m, n, k),
                lhs,
                rhs,
                write,
                0.5,
            );
            for r in 0..m {
                for c in 0..6 {
                    let expect = if (1..1 + n).contains(&c) {
                        let j = c - 1;
                        let product: f64 = (0..k).map(|i| a[r * 9 + 2 + i] * b[j * k + i]).sum();
                        let base = if write == Write::Accumulate {
                            before[r * 6 + c]
                        } else {
                            0.0
                        };
                        base + 0.5 * product
                    } else {
                        before[r * 6 + c]
                    };
                    assert!(
                        (out[r * 6 + c] - expect).abs() < 1e-12,
                        "{write:?} [{r}][{c}]"
                    );
                }
            }
        }
    }
}
