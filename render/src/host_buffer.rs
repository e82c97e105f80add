//! Output buffers of the CPU kernels, initialised on rayon's threads (design.md §1.4).
//!
//! A kernel's output must exist, initialised, before its parallel tasks accumulate into it: the
//! Linear op writes the bias into every row and then accumulates the product onto it. For
//! outputs of megabytes, copying one row after another on the calling thread (plus the first
//! touch of fresh pages) ran while the other core waited (BENCHMARKS.md, 2026-11-25: "five more
//! cuts of the serial part"). Here it is split over rayon's threads above [`PARALLEL_FILL`]
//! elements.
//!
//! Zero-filled buffers are not here: `vec![0.0; n]` asks the allocator for zeroed memory, which
//! for large sizes is fresh pages that cost no write at all until the kernel writes them. A
//! parallel zero fill wrote every page twice and made the quickstart step 35 ms slower.

use std::mem::MaybeUninit;

use rayon::prelude::*;

/// Buffers of at least this many elements are filled on rayon's threads; smaller ones cost less
/// on the calling thread than a hand-off.
pub const PARALLEL_FILL: usize = 1 << 16;

/// Elements per rayon task (rounded down to whole rows, at least one row).
const ELEMENTS_PER_TASK: usize = 1 << 14;

/// `row` repeated `times` times, back to back (`[times, row.len()]` row-major).
pub fn repeated<T: Copy + Send + Sync>(row: &[T], times: usize) -> Vec<T> {
    let width = row.len();
    let len = width * times;
    if len < PARALLEL_FILL {
        return row.repeat(times);
    }
    let chunk = (ELEMENTS_PER_TASK / width).max(1) * width;
    let mut out: Vec<T> = Vec::with_capacity(len);
    out.spare_capacity_mut()[..len]
        .par_chunks_mut(chunk)
        .for_each(|block| {
            for dst_row in block.chunks_exact_mut(width) {
                for (dst, &v) in dst_row.iter_mut().zip(row) {
                    *dst = MaybeUninit::new(v);
                }
            }
        });
    // SAFETY: the capacity is at least `len`, and every element of `[0, len)` was written
    // above: `len` is a multiple of `width`, as is every chunk, so `chunks_exact_mut(width)`
    // covers each chunk entirely, and each row is written in full from `row`.
    unsafe { out.set_len(len) };
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Small and large buffers, rows of one and of several elements, equal the serial fill.
    #[test]
    fn fills_equal_the_serial_fill() {
        for len in [
            0usize,
            7,
            PARALLEL_FILL - 1,
            PARALLEL_FILL,
            3 * PARALLEL_FILL + 5,
        ] {
            assert_eq!(repeated(&[2.5f32], len), vec![2.5f32; len], "len {len}");
        }
        for (width, times) in [(3usize, 5usize), (144, 3687), (ELEMENTS_PER_TASK + 3, 9)] {
            let row: Vec<f64> = (0..width).map(|i| i as f64 * 0.5 - 1.0).collect();
            assert_eq!(repeated(&row, times), row.repeat(times), "{width}×{times}");
        }
        assert!(repeated::<f32>(&[], 1 << 20).is_empty());
    }
}
