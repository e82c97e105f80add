//! Weight gradients formed split-k on CubeCL devices (design.md §1.4).
//!
//! A layer's weight gradient `Xᵀ·G` (`X` `[rows, in]`, `G` `[rows, out]`) is a small output over
//! a long reduction: the rows are every pass's points (3,687 in the quickstart, 41,154 at the
//! paper's setting) or a convolution's output pixels (786,432 for the encoder's stem at 1024²
//! and three views). Burn's CubeCL matmul gives each output tile to one cube that walks the
//! whole reduction, so a few cubes work while the card idles: 1.2 ms for
//! `[144 × 3,687]·[3,687 × 144]` on an H200, where the same product over 128-row chunks, one
//! batched product `[S, in, c]·[S, c, out]` and a sum over the `S` chunks, takes 0.06 ms
//! (BENCHMARKS.md, `matmul-bench`). [`SplitK`] plans the chunks for the shared layers'
//! gradient kernel (`crate::shared_linear`), whose cubes of chunk `z` write partial `z`, then
//! one sum:
//!
//! - chunks are at least [`SPLIT_K_ROWS`] rows long, and there are at most [`MAX_CHUNKS`] of
//!   them (the paper's widest layer was faster with 81 chunks of 512 rows than with 322 of 128);
//! - the partial products `[S, in, out]` stay under [`MAX_PARTIAL_BYTES`]: wide layers over
//!   many rows take longer chunks instead of more of them;
//! - a reduction of fewer than two chunks' rows is one product.
//!
//! A bias gradient `Σ_rows G` is summed the same way, as the row of ones' part of the shared
//! layers' gradient (`crate::shared_linear`).
//!
//! [`SplitK::plan`] may leave the last chunk short ([`SplitK::padded_rows`] covers the rows; the
//! gradient kernel bounds each chunk by the rows, so nothing is padded). The result is the
//! gradient up to float summation order. (Until b406b80, 2026-11-28, the convolutions' weight
//! gradients were Burn's batched products over chunks that divide the rows; the convolutions are
//! shared products now, `crate::conv_norm`.)

use std::cell::Cell;

/// The fewest rows a chunk has by default: the fastest of 128, 256 and 512 rows for every
/// weight-gradient shape of the quickstart step on an H200.
pub const SPLIT_K_ROWS: usize = 128;

/// The most chunks by default.
pub const MAX_CHUNKS: usize = 128;

/// The most bytes the chunks' partial products `[chunks, in, out]` may take by default.
pub const MAX_PARTIAL_BYTES: usize = 256 << 20;

thread_local! {
    /// [`force_split_k_rows`]'s choice on this thread.
    static FORCED_ROWS: Cell<Option<usize>> = const { Cell::new(None) };
}

/// Sets the rows per chunk of split-k weight gradients for backward passes run on the calling
/// thread (Burn's autodiff runs a backward on the thread that calls it): `Some(0)` forms each
/// gradient as one product, `Some(n)` splits every gradient over more than `n` rows into chunks
/// of about `n` rows, `None` restores the default rule (module docs). For benchmarks
/// (`train-bench --split-k-rows`) and tests.
pub fn force_split_k_rows(rows: Option<usize>) {
    FORCED_ROWS.with(|forced| forced.set(rows));
}

/// How a weight gradient `Xᵀ·G` over `rows` rows is formed: `chunks` products of `chunk_rows`
/// rows each, then summed; one chunk is the plain product.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct SplitK {
    /// Chunks `S`.
    pub chunks: usize,
    /// Rows per chunk.
    pub chunk_rows: usize,
}

impl SplitK {
    /// One product over all `rows`.
    fn whole(rows: usize) -> Self {
        Self {
            chunks: 1,
            chunk_rows: rows,
        }
    }

    /// The most chunks for a `[rows, inputs]ᵀ·[rows, outputs]` product whose last chunk may be
    /// short, or `None` for one product (module docs).
    fn most_chunks(rows: usize, inputs: usize, outputs: usize) -> Option<usize> {
        let most = match FORCED_ROWS.with(Cell::get) {
            Some(0) => return None,
            Some(forced) => rows / forced,
            // Only reductions of at least two full chunks gain from a split.
            None if rows < 2 * SPLIT_K_ROWS => return None,
            None => {
                let partial_bytes = (inputs * outputs * size_of::<f32>()).max(1);
                rows.div_ceil(SPLIT_K_ROWS)
                    .min(MAX_CHUNKS)
                    .min(MAX_PARTIAL_BYTES / partial_bytes)
            }
        };
        (most >= 2).then_some(most)
    }

    /// The split of a `[rows, inputs]ᵀ·[rows, outputs]` product, whose last chunk may be short:
    /// its chunks cover [`Self::padded_rows`] (module docs).
    pub fn plan(rows: usize, inputs: usize, outputs: usize) -> Self {
        let Some(most) = Self::most_chunks(rows, inputs, outputs) else {
            return Self::whole(rows);
        };
        let chunk_rows = match FORCED_ROWS.with(Cell::get) {
            Some(forced) => forced,
            None => rows.div_ceil(most).next_multiple_of(SPLIT_K_ROWS),
        };
        let chunks = rows.div_ceil(chunk_rows);
        if chunks < 2 {
            return Self::whole(rows);
        }
        Self { chunks, chunk_rows }
    }

    /// The rows the chunks cover: at least the rows planned for.
    pub fn padded_rows(self) -> usize {
        self.chunks * self.chunk_rows
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn plan(rows: usize, inputs: usize, outputs: usize) -> (usize, usize) {
        let p = SplitK::plan(rows, inputs, outputs);
        (p.chunks, p.chunk_rows)
    }

    /// The default rule: none under two chunks' rows, 128-row chunks for the quickstart's
    /// layers, longer ones past [`MAX_CHUNKS`] or where the partials would pass the memory
    /// bound (the paper's widest layer), and what a forced length asks for.
    #[test]
    fn padded_plans() {
        assert_eq!(plan(255, 144, 144), (1, 255));
        assert_eq!(plan(256, 144, 144), (2, 128));
        assert_eq!(plan(3687, 144, 432), (29, 128));
        assert_eq!(SplitK::plan(3687, 8, 8).padded_rows(), 3712);
        // 256 MiB / (1152² · 4 B) = 50 chunks at most: ⌈41,154 / 50⌉ = 824 → 896 rows.
        assert_eq!(plan(41154, 1152, 1152), (46, 896));
        // 128 chunks at most: ⌈100,000 / 128⌉ = 782 → 896 rows.
        assert_eq!(plan(100_000, 8, 8), (112, 896));
        force_split_k_rows(Some(0));
        assert_eq!(plan(41154, 1152, 1152), (1, 41154));
        force_split_k_rows(Some(8));
        assert_eq!(plan(37, 6, 6), (5, 8));
        assert_eq!(plan(8, 6, 6), (1, 8));
        force_split_k_rows(None);
        assert_eq!(plan(37, 6, 6), (1, 37));
    }

    /// The rule's promises over many shapes: whole chunks cover the rows with less than one
    /// chunk of padding, chunks are whole multiples of [`SPLIT_K_ROWS`] rows, and neither
    /// [`MAX_CHUNKS`] nor [`MAX_PARTIAL_BYTES`] is passed.
    #[test]
    fn plans_keep_their_bounds() {
        let widths = [
            (1, 1),
            (8, 8),
            (144, 432),
            (1152, 1152),
            (4608, 512),
            (9000, 9000),
        ];
        for rows in (0..20_000)
            .step_by(97)
            .chain([41_154, 786_432, 1 << 20, 999_983])
        {
            for &(inputs, outputs) in &widths {
                let partial = |p: SplitK| p.chunks * inputs * outputs * size_of::<f32>();
                let what = format!("{rows} rows, [{inputs} × {outputs}]");
                let p = SplitK::plan(rows, inputs, outputs);
                if p.chunks == 1 {
                    assert_eq!(p.chunk_rows, rows, "{what}: one product");
                } else {
                    assert!(p.padded_rows() >= rows, "{what}: covered");
                    assert!(p.padded_rows() - rows < p.chunk_rows, "{what}: padding");
                    assert!(p.chunk_rows.is_multiple_of(SPLIT_K_ROWS), "{what}: chunk");
                    assert!(p.chunks <= MAX_CHUNKS, "{what}: chunks");
                    assert!(partial(p) <= MAX_PARTIAL_BYTES, "{what}: memory");
                }
            }
        }
    }
}
