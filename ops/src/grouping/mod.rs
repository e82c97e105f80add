//! The Point Transformer's grouping offsets `p_j − p_i` as one op on CubeCL devices
//! (design.md §7.5).
//!
//! Each level of the Point Transformer groups its points with their `k` nearest neighbours,
//! in the same level (the PT layers) or in the finer one (a transition-down), and the layers read
//! the neighbours' positions relative to the group's centre. Composed from tensor ops this is a
//! gather of the level's positions, themselves a gather of the finer level's, and a broadcast
//! subtraction; its backward is a zero-filled scatter per gather, a reduction for the broadcast
//! and an addition per level into the positions' gradient: on a GPU about 60 launches per
//! network pass at the tiny preset. Every level's points are a subset of the input vertices, so
//! the host composes the tables into indices of the input `p` and [`relative_positions`] reads
//! `p` directly: one launch each way (the `cube` module), the backward a gather over the
//! tables' inverses that the host builds with them ([`GroupTable`]). The CPU backends keep the
//! composition.

mod cube;
pub mod op;

use burn::tensor::{Device, Int, Tensor, TensorData};
use lifegom_render::device::runs_on_host;
use lifegom_render::select::select_rows;

/// The tables of [`relative_positions`]: `neighbours` `[m·k]` and `centres` `[m]` (rows of
/// `p`), and on CubeCL devices, for the backward, their inverses over the `n` points
/// (`[offsets | slots]` of the neighbours, then of the centres; `crate::inverse`; the CPU
/// backends' composition does not read them), built on the host and uploaded once.
#[derive(Debug, Clone)]
pub struct GroupTable {
    neighbours: Tensor<1, Int>,
    centres: Tensor<1, Int>,
    readers: Option<Tensor<1, Int>>,
}

impl GroupTable {
    /// The groups of `neighbours` (`k` per centre) around `centres`, rows of `points` points, on
    /// `device`. An index outside `0..points` reads zero and receives nothing.
    pub fn new(neighbours: &[i64], centres: &[i64], points: usize, device: &Device) -> Self {
        let int = |v: Vec<i64>| {
            let len = v.len();
            Tensor::<1, Int>::from_data(TensorData::new(v, [len]), device)
        };
        let readers = (!runs_on_host(device)).then(|| {
            int(crate::inverse::readers(neighbours, points)
                .into_iter()
                .chain(crate::inverse::readers(centres, points))
                .collect())
        });
        Self {
            neighbours: int(neighbours.to_vec()),
            centres: int(centres.to_vec()),
            readers,
        }
    }
}

/// `p[neighbours[i·k + κ]] − p[centres[i]]` as `[m, k, 3]`, for `p` `[n, 3]` and the groups of
/// `table`: one op on CubeCL devices, the gathers and subtraction on the CPU backends. The
/// gradient reaches `p`; the tables take none.
///
/// # Panics
///
/// If `p` is not `[n, 3]` or the neighbours are not a multiple of the centres.
pub fn relative_positions(p: Tensor<2>, table: &GroupTable) -> Tensor<3> {
    assert_eq!(p.dims()[1], 3, "positions are [n, 3]");
    let (neighbours, centres) = (table.neighbours.clone(), table.centres.clone());
    let [slots] = neighbours.dims();
    let [m] = centres.dims();
    assert!(
        m > 0 && slots.is_multiple_of(m),
        "{slots} neighbour slots for {m} groups"
    );
    if runs_on_host(&p.device()) {
        return select_rows(p.clone(), 0, neighbours).reshape([m, slots / m, 3])
            - select_rows(p, 0, centres).unsqueeze_dim::<3>(1);
    }
    Tensor::from_dispatch(
        <burn::backend::Dispatch as op::GroupingOps>::relative_positions(
            p.into_dispatch(),
            neighbours.into_dispatch(),
            centres.into_dispatch(),
            table
                .readers
                .clone()
                .expect("a device table has its inverse")
                .into_dispatch(),
        ),
    )
}

/// One level of a point hierarchy whose every level is a subset of the input points (the
/// Point Transformer's FPS levels), kept the way [`level_offsets`] reads it on this backend:
/// its rows in the input points and, on the CPU backends, its own positions, gathered from the
/// previous level's (the composition of the module docs; on CubeCL devices the offsets read the
/// input positions through the rows, and no level keeps a tensor).
#[derive(Debug, Clone)]
pub struct LevelPoints {
    rows: Vec<u32>,
    positions: Option<Tensor<2>>,
}

impl LevelPoints {
    /// The finest level: the input points `positions` `[n, 3]`, as rows `rows` of themselves.
    pub fn input(positions: &Tensor<2>, rows: Vec<u32>) -> Self {
        let positions = runs_on_host(&positions.device()).then(|| positions.clone());
        Self { rows, positions }
    }

    /// The level of this level's points `picks`, which are rows `rows` of the input points.
    pub fn pick(&self, picks: &[u32], rows: Vec<u32>) -> Self {
        let positions = self
            .positions
            .as_ref()
            .map(|p| select_rows(p.clone(), 0, index_tensor(picks, &p.device())));
        Self { rows, positions }
    }

    /// Its points' rows in the input points.
    pub fn rows(&self) -> &[u32] {
        &self.rows
    }
}

/// The neighbours `nb` (points of `reference`) of each point of `query`, as rows of
/// `reference` `[m·k]`, and their offsets from that point, `[m, k, 3]`, for levels of the input
/// points `positions` `[n, 3]`: on the CPU backends a gather of `reference`'s positions less
/// `query`'s, on CubeCL devices one [`relative_positions`] over the input positions (the same
/// values, in fewer launches). The gradient reaches `positions`.
pub fn level_offsets(
    positions: &Tensor<2>,
    nb: &crate::knn::Neighbours,
    reference: &LevelPoints,
    query: &LevelPoints,
) -> (Tensor<1, Int>, Tensor<3>) {
    let device = positions.device();
    let indices = index_tensor(&nb.indices, &device);
    if let (Some(p_ref), Some(p_query)) = (&reference.positions, &query.positions) {
        let rel = select_rows(p_ref.clone(), 0, indices.clone()).reshape([nb.len(), nb.k, 3])
            - p_query.clone().unsqueeze_dim::<3>(1);
        return (indices, rel);
    }
    let neighbours: Vec<i64> = nb
        .indices
        .iter()
        .map(|&r| i64::from(reference.rows[r as usize]))
        .collect();
    let centres: Vec<i64> = query.rows.iter().map(|&r| i64::from(r)).collect();
    let table = GroupTable::new(&neighbours, &centres, positions.dims()[0], &device);
    (indices, relative_positions(positions.clone(), &table))
}

fn index_tensor(idx: &[u32], device: &Device) -> Tensor<1, Int> {
    let data: Vec<i64> = idx.iter().map(|&i| i64::from(i)).collect();
    Tensor::from_data(TensorData::new(data, [idx.len()]), device)
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::tensor::{Device, TensorData};
    use lifegom_render::testing::{Rng, read, wgpu_test_device};

    /// Offsets and the positions' gradient (of a weighted sum) for groups with repeated
    /// neighbours, a centre among its own neighbours and points in no group.
    fn offsets_and_gradient(device: &Device) -> (Vec<f32>, Vec<f32>) {
        let ad = device.clone().autodiff();
        let mut rng = Rng::new(5);
        let (n, m, k) = (11, 4, 5);
        let p: Vec<f32> = (0..n * 3).map(|_| rng.range_f32(-1.0, 1.0)).collect();
        let neighbours: Vec<i64> = (0..m * k).map(|s| ((s * 7 + s / k) % 9) as i64).collect();
        let centres: Vec<i64> = vec![0, 3, 3, 8];
        let weights: Vec<f32> = (0..m * k * 3).map(|_| rng.range_f32(-1.0, 1.0)).collect();
        let p = Tensor::<2>::from_data(TensorData::new(p, [n, 3]), &ad).require_grad();
        let table = GroupTable::new(&neighbours, &centres, n, &ad);
        let out = relative_positions(p.clone(), &table);
        let w = Tensor::<3>::from_data(TensorData::new(weights, [m, k, 3]), &ad);
        let grads = (out.clone() * w).sum().backward();
        (read(out), read(p.grad(&grads).expect("a gradient")))
    }

    /// The op on lavapipe against the composition on Flex: equal offsets (a difference of the
    /// same two floats) and the gradient within float summation order.
    #[test]
    fn relative_positions_match_composition_wgpu() {
        let Some(device) = wgpu_test_device() else {
            return;
        };
        let (want, want_grad) = offsets_and_gradient(&Device::flex());
        let (got, got_grad) = offsets_and_gradient(&device);
        assert_eq!(got, want);
        for (i, (a, b)) in got_grad.iter().zip(&want_grad).enumerate() {
            assert!((a - b).abs() <= 1e-5, "∂p[{i}]: {a} against {b}");
        }
        assert!(want_grad.iter().any(|&g| g != 0.0));
    }

    /// Two levels' offsets and the positions' gradient: the finest level's self-neighbours,
    /// then a picked level's neighbours in the finest one.
    fn level_offsets_and_gradient(device: &Device) -> (Vec<f32>, Vec<f32>) {
        let ad = device.clone().autodiff();
        let mut rng = Rng::new(9);
        let (n, k) = (9, 3);
        let p: Vec<f32> = (0..n * 3).map(|_| rng.range_f32(-1.0, 1.0)).collect();
        let p = Tensor::<2>::from_data(TensorData::new(p, [n, 3]), &ad).require_grad();
        let neighbours = |m: usize, of: usize| crate::knn::Neighbours {
            k,
            indices: (0..m * k).map(|s| ((s * 5 + 1) % of) as u32).collect(),
            dist2: vec![0.0; m * k],
        };
        let fine = LevelPoints::input(&p, (0..n as u32).collect());
        let picks = [7, 2, 4];
        let coarse = fine.pick(&picks, picks.to_vec());
        let (_, self_rel) = level_offsets(&p, &neighbours(n, n), &fine, &fine);
        let (idx, down_rel) = level_offsets(&p, &neighbours(3, n), &fine, &coarse);
        assert_eq!(idx.dims(), [3 * k]);
        let rel = Tensor::cat(vec![self_rel, down_rel], 0);
        let w: Vec<f32> = (0..(n + 3) * k * 3)
            .map(|_| rng.range_f32(-1.0, 1.0))
            .collect();
        let w = Tensor::<3>::from_data(TensorData::new(w, [n + 3, k, 3]), &ad);
        let grads = (rel.clone() * w).sum().backward();
        (read(rel), read(p.grad(&grads).expect("a gradient")))
    }

    /// The levels' offsets on lavapipe (one op over the input positions) against Flex (each
    /// level's own positions): equal offsets, the gradient within float summation order.
    #[test]
    fn level_offsets_match_across_backends_wgpu() {
        let Some(device) = wgpu_test_device() else {
            return;
        };
        let (want, want_grad) = level_offsets_and_gradient(&Device::flex());
        let (got, got_grad) = level_offsets_and_gradient(&device);
        assert_eq!(got, want);
        for (i, (a, b)) in got_grad.iter().zip(&want_grad).enumerate() {
            assert!((a - b).abs() <= 1e-5, "∂p[{i}]: {a} against {b}");
        }
        assert!(want_grad.iter().any(|&g| g != 0.0));
    }
}
