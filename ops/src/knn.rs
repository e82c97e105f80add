//! Point-cloud neighbourhood queries on the host: farthest point sampling (FPS) and k-nearest
//! neighbours (kNN), the two geometric ops the Point Transformer needs and Burn does not have
//! (design.md §7.6).
//!
//! Both run on `[f32; 3]` slices read back from the device once per forward: the results are
//! integer indices (and, for the interpolation weights, distances) that carry no gradient, so
//! nothing is lost by leaving the autodiff graph for them. The features are then gathered on the
//! device with `Tensor::select`, whose backward is a scatter-add.
//!
//! # Semantics (one batch)
//!
//! - **FPS** ([`farthest_point_sampling`]) starts from index 0 and repeatedly takes the point
//!   whose squared distance to the already chosen set is largest; among exactly tied points it
//!   takes the **lowest index**. Deterministic and `O(n·m)`. When all remaining points are at
//!   distance 0 (duplicates) it may pick an already chosen point again, as the reference does;
//!   the caller never relies on the chosen points being distinct.
//! - **kNN** ([`knn`]) returns, for every query, the `k` reference points with the smallest
//!   squared distance, sorted ascending by `(d², index)`: a query that is itself a reference
//!   point finds itself first (distance 0), and among exactly equidistant candidates the
//!   **lower index** is kept, so the answer is unique and independent of the search structure.
//!   When `k` exceeds the number of reference points the list is padded with index 0 at squared
//!   distance [`PAD_DIST2`], which is exactly the reference kernel's initial heap content
//!   (`best_idx = start`, `best_dist = 1e10`).
//!
//! # Ties: where this differs from the reference CUDA ops (Zhao et al.'s `pointops`)
//!
//! Away from exact ties both ops return what `pointops` returns. At exact ties they can differ,
//! and both answers are valid:
//!
//! - The reference kNN kernel keeps a max-heap of the `k` best and replaces its root only when a
//!   candidate is *strictly* closer, so among exactly equidistant candidates the survivor depends
//!   on the heap's internal order, not on the index. On the bit-exactly mirror-symmetric low-res
//!   template this changes the neighbour sets of 14 vertices, and the Point Transformer output
//!   moves by up to ~1e-2 of its scale at the first feedback step.
//! - The reference FPS kernel scans the points in a thread-strided pattern and reduces across
//!   threads keeping the lower thread slot on ties, so among exactly tied points it takes the one
//!   with the smallest `index mod B` (`B`, the CUDA block size, is the largest power of two
//!   `≤ n`, at most 1024), then the lowest index. That is the lowest index too whenever the tied
//!   indices lie in one range `[m·B, (m+1)·B)`; otherwise the two may pick different points.
//!
//! lifegom keeps the index rule on purpose (design.md §13.1): it does not depend on a heap
//! layout or a launch configuration.
//!
//! # Search structure
//!
//! Brute force is `O(n·m)` distance evaluations: ~190M for the 13,718-vertex template, too slow
//! to redo every forward. [`knn`] bins the reference points into a uniform grid (about two
//! points per cell for a volume-filling cloud; a body surface fills fewer cells with more points
//! each) and visits cells in growing Chebyshev shells around the query's cell. After each shell
//! it stops once the current k-th distance is *strictly* below the distance from the query to
//! the nearest unvisited cell (minus a rounding margin): no unvisited point can then enter the
//! list, not even as a lower-index tie, so the result equals [`knn_brute_force`] exactly.
//! Queries are processed in parallel with rayon.

use rayon::prelude::*;

/// Squared distance given to padding neighbours when `k` exceeds the reference count.
pub const PAD_DIST2: f32 = 1e10;

/// Below this many distance evaluations (`n·m`) the grid is not worth building.
const BRUTE_FORCE_LIMIT: usize = 1 << 16;

/// Target reference points per grid cell (for a volume-filling cloud).
const POINTS_PER_CELL: f64 = 2.0;

/// Queries per parallel work item.
const QUERY_CHUNK: usize = 256;

#[inline]
fn dist2(a: &[f32; 3], b: &[f32; 3]) -> f32 {
    let dx = a[0] - b[0];
    let dy = a[1] - b[1];
    let dz = a[2] - b[2];
    dx * dx + dy * dy + dz * dz
}

/// Farthest point sampling: `m` indices into `points` (fewer if `points` has fewer), the first
/// being 0. See the module docs for tie-breaking.
pub fn farthest_point_sampling(points: &[[f32; 3]], m: usize) -> Vec<u32> {
    let n = points.len();
    let m = m.min(n);
    if m == 0 {
        return Vec::new();
    }
    // Structure of arrays and three simple passes per pick (update the distance to the chosen
    // set, take its maximum, find the first index holding it): each pass vectorises, where one
    // fused loop tracking the arg-max does not. Per element the arithmetic is the same.
    let xs: Vec<f32> = points.iter().map(|p| p[0]).collect();
    let ys: Vec<f32> = points.iter().map(|p| p[1]).collect();
    let zs: Vec<f32> = points.iter().map(|p| p[2]).collect();
    let mut min_d2 = vec![f32::INFINITY; n];
    let mut chosen = Vec::with_capacity(m);
    let mut last = 0usize;
    chosen.push(0u32);
    for _ in 1..m {
        let (px, py, pz) = (xs[last], ys[last], zs[last]);
        for (((d, &x), &y), &z) in min_d2.iter_mut().zip(&xs).zip(&ys).zip(&zs) {
            let (dx, dy, dz) = (x - px, y - py, z - pz);
            let dj = dx * dx + dy * dy + dz * dz;
            *d = if dj < *d { dj } else { *d };
        }
        let mut lanes = [-1.0f32; 8];
        let mut chunks = min_d2.chunks_exact(8);
        for c in &mut chunks {
            for (l, &v) in lanes.iter_mut().zip(c) {
                *l = if v > *l { v } else { *l };
            }
        }
        let max = chunks
            .remainder()
            .iter()
            .chain(&lanes)
            .fold(-1.0f32, |a, &v| if v > a { v } else { a });
        // The first index attaining the maximum (the reference kernel's `besti = 0` start makes
        // an all-zero row pick 0); a NaN row (non-finite input) also falls back to 0.
        last = min_d2.iter().position(|&v| v == max).unwrap_or(0);
        chosen.push(last as u32);
    }
    chosen
}

/// Result of a kNN query: row `i` (`k` entries) holds the neighbours of query `i`.
#[derive(Debug, Clone, PartialEq)]
pub struct Neighbours {
    /// Neighbours per query.
    pub k: usize,
    /// Reference indices, `[m·k]` row-major, ascending by `(d², index)`.
    pub indices: Vec<u32>,
    /// Squared distances matching `indices`.
    pub dist2: Vec<f32>,
}

impl Neighbours {
    /// Number of queries.
    pub fn len(&self) -> usize {
        self.indices.len().checked_div(self.k).unwrap_or(0)
    }

    /// Whether there are no queries.
    pub fn is_empty(&self) -> bool {
        self.indices.is_empty()
    }
}

/// A sorted list of the best `k` candidates, ordered by `(d², index)`.
struct Best<'a> {
    idx: &'a mut [u32],
    d2: &'a mut [f32],
    len: usize,
}

impl<'a> Best<'a> {
    fn new(idx: &'a mut [u32], d2: &'a mut [f32]) -> Self {
        Self { idx, d2, len: 0 }
    }

    fn full(&self) -> bool {
        self.len == self.idx.len()
    }

    fn worst(&self) -> f32 {
        self.d2[self.len - 1]
    }

    #[inline]
    fn offer(&mut self, d: f32, i: u32) {
        let k = self.idx.len();
        let less = |d1: f32, i1: u32, d2: f32, i2: u32| d1 < d2 || (d1 == d2 && i1 < i2);
        if self.len == k && !less(d, i, self.d2[k - 1], self.idx[k - 1]) {
            return;
        }
        // Insertion: k ≤ 16 here, so a linear shift beats a heap.
        let mut pos = if self.len < k { self.len } else { k - 1 };
        while pos > 0 && less(d, i, self.d2[pos - 1], self.idx[pos - 1]) {
            self.d2[pos] = self.d2[pos - 1];
            self.idx[pos] = self.idx[pos - 1];
            pos -= 1;
        }
        self.d2[pos] = d;
        self.idx[pos] = i;
        if self.len < k {
            self.len += 1;
        }
    }

    /// Pads the unfilled tail the way the reference kernel does.
    fn pad(&mut self) {
        for j in self.len..self.idx.len() {
            self.idx[j] = 0;
            self.d2[j] = PAD_DIST2;
        }
        self.len = self.idx.len();
    }
}

/// Exact kNN by scanning every reference point (the oracle for [`knn`], and its small-input
/// path).
pub fn knn_brute_force(reference: &[[f32; 3]], queries: &[[f32; 3]], k: usize) -> Neighbours {
    let mut indices = vec![0u32; queries.len() * k];
    let mut d2s = vec![0f32; queries.len() * k];
    if k > 0 {
        indices
            .par_chunks_mut(k * QUERY_CHUNK)
            .zip(d2s.par_chunks_mut(k * QUERY_CHUNK))
            .zip(queries.par_chunks(QUERY_CHUNK))
            .for_each(|((idx, d2), qs)| {
                for ((idx, d2), q) in idx.chunks_mut(k).zip(d2.chunks_mut(k)).zip(qs) {
                    let kk = k.min(reference.len());
                    let mut best = Best::new(&mut idx[..kk], &mut d2[..kk]);
                    for (j, r) in reference.iter().enumerate() {
                        best.offer(dist2(q, r), j as u32);
                    }
                    Best::new(&mut idx[kk..], &mut d2[kk..]).pad();
                }
            });
    }
    Neighbours {
        k,
        indices,
        dist2: d2s,
    }
}

/// Uniform grid over the reference points, cells in x-fastest order, points sorted by cell
/// (stable, so ascending index within a cell).
struct Grid {
    origin: [f64; 3],
    cell: f64,
    dims: [usize; 3],
    /// `cell_start[c]..cell_start[c+1]` indexes `order` for cell `c`.
    cell_start: Vec<u32>,
    order: Vec<u32>,
    /// Absolute rounding margin for the stopping test (distance units).
    margin: f64,
}

impl Grid {
    fn build(points: &[[f32; 3]]) -> Self {
        let n = points.len();
        let mut lo = [f64::INFINITY; 3];
        let mut hi = [f64::NEG_INFINITY; 3];
        for p in points {
            for a in 0..3 {
                lo[a] = lo[a].min(f64::from(p[a]));
                hi[a] = hi[a].max(f64::from(p[a]));
            }
        }
        let ext = [hi[0] - lo[0], hi[1] - lo[1], hi[2] - lo[2]];
        let max_ext = ext[0].max(ext[1]).max(ext[2]);
        let scale = lo.iter().chain(&hi).fold(max_ext, |m, v| m.max(v.abs()));
        let (cell, dims) = if max_ext > 0.0 {
            // Flat axes count as 1/64 of the largest extent so the volume stays meaningful.
            let floor = max_ext / 64.0;
            let vol: f64 = ext.iter().map(|e| e.max(floor)).product();
            let mut cell = (vol * POINTS_PER_CELL / n as f64).cbrt();
            let dims_for = |cell: f64| ext.map(|e| ((e / cell).floor() as usize + 1).max(1));
            let mut dims = dims_for(cell);
            // Cap the cell count (memory, empty-shell scans) at ~4 cells per point.
            while dims.iter().product::<usize>() > 4 * n + 8 {
                cell *= 1.25;
                dims = dims_for(cell);
            }
            (cell, dims)
        } else {
            (1.0, [1, 1, 1])
        };
        let mut grid = Grid {
            origin: lo,
            cell,
            dims,
            cell_start: Vec::new(),
            order: Vec::new(),
            margin: scale * 1e-5 + 1e-12,
        };
        let ncells = dims.iter().product::<usize>();
        let cell_of: Vec<u32> = points
            .iter()
            .map(|p| grid.linear(grid.coords(p)) as u32)
            .collect();
        let mut start = vec![0u32; ncells + 1];
        for &c in &cell_of {
            start[c as usize + 1] += 1;
        }
        for c in 0..ncells {
            start[c + 1] += start[c];
        }
        let mut fill = start.clone();
        let mut order = vec![0u32; n];
        for (i, &c) in cell_of.iter().enumerate() {
            order[fill[c as usize] as usize] = i as u32;
            fill[c as usize] += 1;
        }
        grid.cell_start = start;
        grid.order = order;
        grid
    }

    /// Cell coordinates of a point, clamped into the grid (queries may lie outside it).
    fn coords(&self, p: &[f32; 3]) -> [usize; 3] {
        std::array::from_fn(|a| {
            let t = ((f64::from(p[a]) - self.origin[a]) / self.cell).floor();
            (t.max(0.0) as usize).min(self.dims[a] - 1)
        })
    }

    fn linear(&self, c: [usize; 3]) -> usize {
        c[0] + self.dims[0] * (c[1] + self.dims[1] * c[2])
    }

    /// Offers every point of the cells at Chebyshev distance exactly `r` from `c`.
    fn scan_shell(
        &self,
        reference: &[[f32; 3]],
        q: &[f32; 3],
        c: [usize; 3],
        r: usize,
        best: &mut Best,
    ) {
        let range = |a: usize| {
            let lo = c[a].saturating_sub(r);
            let hi = (c[a] + r).min(self.dims[a] - 1);
            (lo, hi)
        };
        let (x0, x1) = range(0);
        let (y0, y1) = range(1);
        let (z0, z1) = range(2);
        for z in z0..=z1 {
            let on_z = z.abs_diff(c[2]) == r;
            for y in y0..=y1 {
                let on_yz = on_z || y.abs_diff(c[1]) == r;
                let mut visit = |x: usize| {
                    let cell = self.linear([x, y, z]);
                    let (s, e) = (self.cell_start[cell], self.cell_start[cell + 1]);
                    for &i in &self.order[s as usize..e as usize] {
                        best.offer(dist2(q, &reference[i as usize]), i);
                    }
                };
                if on_yz {
                    (x0..=x1).for_each(&mut visit);
                } else {
                    // Interior rows of the shell only touch its two x faces (here r > 0).
                    if let Some(x) = c[0].checked_sub(r) {
                        visit(x);
                    }
                    if c[0] + r <= x1 {
                        visit(c[0] + r);
                    }
                }
            }
        }
    }

    /// Distance from `q` to the nearest cell outside the cube of radius `r` around `c`, or
    /// `None` when that cube covers the whole grid.
    fn outside_bound(&self, q: &[f32; 3], c: [usize; 3], r: usize) -> Option<f64> {
        let mut bound = f64::INFINITY;
        for a in 0..3 {
            let qa = f64::from(q[a]);
            if c[a] > r {
                let face = self.origin[a] + (c[a] - r) as f64 * self.cell;
                bound = bound.min(qa - face);
            }
            if c[a] + r + 1 < self.dims[a] {
                let face = self.origin[a] + (c[a] + r + 1) as f64 * self.cell;
                bound = bound.min(face - qa);
            }
        }
        bound.is_finite().then_some(bound)
    }

    fn query(&self, reference: &[[f32; 3]], q: &[f32; 3], best: &mut Best) {
        let c = self.coords(q);
        for r in 0.. {
            self.scan_shell(reference, q, c, r, best);
            let Some(bound) = self.outside_bound(q, c, r) else {
                return;
            };
            if best.full() {
                let room = bound - self.margin;
                if room > 0.0 && f64::from(best.worst()) < room * room {
                    return;
                }
            }
        }
    }
}

/// The `k` nearest reference points of every query, self included when a query is a reference
/// point; exact and identical to [`knn_brute_force`] (module docs).
///
/// # Panics
///
/// If `reference` is empty while there are queries and `k > 0`.
pub fn knn(reference: &[[f32; 3]], queries: &[[f32; 3]], k: usize) -> Neighbours {
    if k == 0 || queries.is_empty() {
        return Neighbours {
            k,
            indices: Vec::new(),
            dist2: Vec::new(),
        };
    }
    assert!(!reference.is_empty(), "kNN over an empty reference set");
    if reference.len() * queries.len() <= BRUTE_FORCE_LIMIT {
        return knn_brute_force(reference, queries, k);
    }
    let grid = Grid::build(reference);
    let kk = k.min(reference.len());
    let mut indices = vec![0u32; queries.len() * k];
    let mut d2s = vec![0f32; queries.len() * k];
    indices
        .par_chunks_mut(k * QUERY_CHUNK)
        .zip(d2s.par_chunks_mut(k * QUERY_CHUNK))
        .zip(queries.par_chunks(QUERY_CHUNK))
        .for_each(|((idx, d2), qs)| {
            for ((idx, d2), q) in idx.chunks_mut(k).zip(d2.chunks_mut(k)).zip(qs) {
                let mut best = Best::new(&mut idx[..kk], &mut d2[..kk]);
                grid.query(reference, q, &mut best);
                Best::new(&mut idx[kk..], &mut d2[kk..]).pad();
            }
        });
    Neighbours {
        k,
        indices,
        dist2: d2s,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use lifegom_render::rng::Rng;

    fn cloud(rng: &mut Rng, n: usize, scale: [f32; 3]) -> Vec<[f32; 3]> {
        (0..n)
            .map(|_| std::array::from_fn(|a| (rng.next_f32() - 0.5) * scale[a]))
            .collect()
    }

    #[test]
    fn fps_starts_at_zero_then_takes_the_farthest() {
        let pts = [
            [0.0, 0.0, 0.0],
            [1.0, 0.0, 0.0],
            [5.0, 0.0, 0.0],
            [2.0, 2.0, 0.0],
            [0.0, -3.0, 0.0],
        ];
        let s = farthest_point_sampling(&pts, 3);
        // 0 first; 2 is farthest from 0 (d²=25); then min-distance to {0,2}: 1→1, 3→4, 4→9.
        assert_eq!(s, vec![0, 2, 4]);
        assert_eq!(farthest_point_sampling(&pts, 10).len(), 5);
        assert!(farthest_point_sampling(&pts, 0).is_empty());
    }

    #[test]
    fn fps_is_deterministic_and_spread() {
        let pts = cloud(&mut Rng::new(7), 3000, [1.0, 2.0, 0.5]);
        let a = farthest_point_sampling(&pts, 750);
        let b = farthest_point_sampling(&pts, 750);
        assert_eq!(a, b);
        assert_eq!(a[0], 0);
        let mut sorted = a.clone();
        sorted.sort_unstable();
        sorted.dedup();
        assert_eq!(
            sorted.len(),
            a.len(),
            "distinct points yield distinct samples"
        );
        // Brute-force check of the greedy rule for the first few picks.
        let mut mind = vec![f32::INFINITY; pts.len()];
        for w in a.windows(2).take(20) {
            for (j, d) in mind.iter_mut().enumerate() {
                *d = d.min(dist2(&pts[j], &pts[w[0] as usize]));
            }
            let max = mind.iter().cloned().fold(-1.0, f32::max);
            assert_eq!(mind[w[1] as usize], max);
        }
    }

    #[test]
    fn fps_on_duplicates_is_finite_and_sized() {
        let pts = vec![[1.0, 2.0, 3.0]; 10];
        assert_eq!(farthest_point_sampling(&pts, 4), vec![0, 0, 0, 0]);
    }

    #[test]
    fn knn_matches_brute_force() {
        let mut rng = Rng::new(3);
        for &(n, m, k, scale) in &[
            (2000usize, 2000usize, 16usize, [1.0f32, 2.0, 0.3]),
            (3000, 750, 16, [1.0, 1.0, 1.0]),
            (500, 2000, 3, [0.2, 1.0, 0.0]), // flat cloud, queries outside the grid
            (1000, 1000, 8, [1.0, 1.0, 1.0]),
        ] {
            let reference = cloud(&mut rng, n, scale);
            let queries = if m == n {
                reference.clone()
            } else {
                cloud(&mut rng, m, [1.5, 2.5, 0.5])
            };
            let grid = knn(&reference, &queries, k);
            let brute = knn_brute_force(&reference, &queries, k);
            assert_eq!(grid, brute, "n={n} m={m} k={k}");
            if m == n {
                for i in 0..m {
                    assert_eq!(grid.indices[i * k], i as u32, "self first");
                    assert_eq!(grid.dist2[i * k], 0.0);
                }
            }
            for row in grid.dist2.chunks(k) {
                assert!(row.windows(2).all(|w| w[0] <= w[1]));
            }
        }
    }

    #[test]
    fn knn_pads_and_handles_duplicates() {
        let reference = vec![[0.5, 0.5, 0.5]; 5];
        let nb = knn(&reference, &reference, 8);
        assert_eq!(nb.len(), 5);
        for row in 0..5 {
            assert_eq!(&nb.indices[row * 8..row * 8 + 5], &[0, 1, 2, 3, 4]);
            assert_eq!(&nb.indices[row * 8 + 5..row * 8 + 8], &[0, 0, 0]);
            assert_eq!(nb.dist2[row * 8 + 7], PAD_DIST2);
        }
        // Many duplicates through the grid path too.
        let reference = vec![[0.0, 1.0, 2.0]; 400];
        assert_eq!(
            knn(&reference, &reference, 16),
            knn_brute_force(&reference, &reference, 16)
        );
    }
}
