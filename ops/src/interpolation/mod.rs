//! The Point Transformer's transition-up interpolation as one op on CubeCL devices (design.md
//! §7.5).
//!
//! Each decoder level brings the coarser level's features to its points by inverse-distance
//! weights over the 3 nearest coarse points: `Σ_j w_ij·x[nbr_ij]`. Composed from tensor ops it is
//! a gather, a broadcast product and a sum, and in the backward the product's and the sum's
//! gradients and a zero-filled scatter: on a GPU about seven launches per level and pass.
//! [`interpolate`] is one launch each way (the `cube` module); [`interpolate_onto`] adds the
//! transition-up's fine features in the same launch, their gradient the output's. The backward
//! gathers rather than scatters: the table is planned on the host, which also lists, for each
//! coarse point, the slots `i·K + j` that name it ([`NeighbourTable`]), so each coarse point's
//! gradient is one thread's sum in a fixed order (no zero-fill, no atomics). The CPU backends
//! keep the composition.

mod cube;
pub mod op;

use burn::tensor::{Device, Int, Tensor, TensorData};
use lifegom_render::device::runs_on_host;
use lifegom_render::select::select_rows;

/// An interpolation's neighbour table `[m·K]` (row `i`'s `K` coarse points), and on CubeCL
/// devices its inverse for the backward: for each of the `n` coarse points, the slots `i·K + j`
/// that name it, as `[offsets (n + 1) | slots]` (module docs; the CPU backends' composition
/// does not read it). Built on the host, uploaded once.
#[derive(Debug, Clone)]
pub struct NeighbourTable {
    neighbours: Tensor<1, Int>,
    readers: Option<Tensor<1, Int>>,
}

impl NeighbourTable {
    /// The table `neighbours` (`K` coarse indices per interpolated row) over `points` coarse
    /// points, on `device`. An index outside `0..points` names no point (it reads zero and
    /// receives nothing).
    pub fn new(neighbours: &[i64], points: usize, device: &Device) -> Self {
        let int = |v: Vec<i64>| {
            let len = v.len();
            Tensor::<1, Int>::from_data(TensorData::new(v, [len]), device)
        };
        Self {
            neighbours: int(neighbours.to_vec()),
            readers: (!runs_on_host(device))
                .then(|| int(crate::inverse::readers(neighbours, points))),
        }
    }
}

/// `Σ_j weights[i, j]·x[neighbours[i·K + j]]` as `[m, c]`, for `x` `[n, c]`, the `table`
/// `[m·K]` over `n` points and `weights` `[m, K]`: one op on CubeCL devices, the gather, product
/// and sum on the CPU backends. The gradient reaches `x`; the table and the weights take none.
///
/// # Panics
///
/// If the table does not hold `K` entries per row of `weights`.
pub fn interpolate(x: Tensor<2>, table: &NeighbourTable, weights: Tensor<2>) -> Tensor<2> {
    interpolate_onto(None, x, table, weights)
}

/// `base + interpolate(x, neighbours, weights)` (`base` `[m, c]`, or none), the sum in the op's
/// launch on CubeCL devices: the transition-up's `fine + interpolated`. The gradient reaches
/// `base` and `x`.
///
/// # Panics
///
/// As [`interpolate`], or if `base` is not `[m, c]`.
pub fn interpolate_onto(
    base: Option<Tensor<2>>,
    x: Tensor<2>,
    table: &NeighbourTable,
    weights: Tensor<2>,
) -> Tensor<2> {
    let neighbours = table.neighbours.clone();
    let [m, k] = weights.dims();
    assert_eq!(
        neighbours.dims()[0],
        m * k,
        "{k} neighbours per interpolated row"
    );
    let c = x.dims()[1];
    if let Some(base) = &base {
        assert_eq!(
            base.dims(),
            [m, c],
            "the base of an interpolation is [m, c]"
        );
    }
    if runs_on_host(&x.device()) {
        let rows = (select_rows(x, 0, neighbours).reshape([m, k, c])
            * weights.detach().reshape([m, k, 1]))
        .sum_dim(1)
        .reshape([m, c]);
        return match base {
            Some(base) => base + rows,
            None => rows,
        };
    }
    let weights = weights.detach();
    // Without a base the op reads none: the (detached) weights stand in, taking no gradient.
    let (base, onto) = match base {
        Some(base) => (base, op::Base::Added),
        None => (weights.clone(), op::Base::None),
    };
    Tensor::from_dispatch(
        <burn::backend::Dispatch as op::InterpolationOps>::point_interpolation(
            x.into_dispatch(),
            neighbours.into_dispatch(),
            table
                .readers
                .clone()
                .expect("a device table has its inverse")
                .into_dispatch(),
            weights.into_dispatch(),
            base.into_dispatch(),
            onto,
        ),
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::tensor::{Device, TensorData};
    use lifegom_render::testing::{Rng, read, wgpu_test_device};

    /// Interpolated rows and the source's gradient (of a weighted sum), with coarse points
    /// shared by several rows, a row naming one point twice and points named by none; onto a
    /// base when `onto` (then also the base's gradient).
    fn rows_and_gradient(device: &Device, onto: bool) -> (Vec<f32>, Vec<f32>, Vec<f32>) {
        let ad = device.clone().autodiff();
        let mut rng = Rng::new(9);
        let (n, m, k, c) = (6, 9, 3, 5);
        let x: Vec<f32> = (0..n * c).map(|_| rng.range_f32(-1.0, 1.0)).collect();
        let mut neighbours: Vec<i64> = (0..m * k).map(|s| ((s * 5 + s / k) % 5) as i64).collect();
        neighbours[4] = neighbours[3];
        let weights: Vec<f32> = (0..m * k).map(|_| rng.range_f32(0.0, 1.0)).collect();
        let probe: Vec<f32> = (0..m * c).map(|_| rng.range_f32(-1.0, 1.0)).collect();
        let x = Tensor::<2>::from_data(TensorData::new(x, [n, c]), &ad).require_grad();
        let table = NeighbourTable::new(&neighbours, n, &ad);
        let weights = Tensor::<2>::from_data(TensorData::new(weights, [m, k]), &ad);
        let base: Vec<f32> = (0..m * c).map(|_| rng.range_f32(-1.0, 1.0)).collect();
        let base = Tensor::<2>::from_data(TensorData::new(base, [m, c]), &ad).require_grad();
        let out = if onto {
            interpolate_onto(Some(base.clone()), x.clone(), &table, weights)
        } else {
            interpolate(x.clone(), &table, weights)
        };
        let probe = Tensor::<2>::from_data(TensorData::new(probe, [m, c]), &ad);
        let grads = (out.clone() * probe).sum().backward();
        let base_grad = base.grad(&grads).map(read).unwrap_or_default();
        assert_eq!(
            base_grad.is_empty(),
            !onto,
            "the base takes a gradient when added"
        );
        (
            read(out),
            read(x.grad(&grads).expect("a gradient")),
            base_grad,
        )
    }

    /// The op on lavapipe against the composition on Flex, values and gradients, within float
    /// summation order, alone and onto a base.
    #[test]
    fn interpolate_matches_composition_wgpu() {
        let Some(device) = wgpu_test_device() else {
            return;
        };
        for onto in [false, true] {
            let want = rows_and_gradient(&Device::flex(), onto);
            let got = rows_and_gradient(&device, onto);
            let parts = [
                ("rows", &got.0, &want.0),
                ("∂x", &got.1, &want.1),
                ("∂base", &got.2, &want.2),
            ];
            for (what, a, b) in parts {
                assert_eq!(a.len(), b.len(), "{what}");
                for (i, (u, v)) in a.iter().zip(b.iter()).enumerate() {
                    assert!(
                        (u - v).abs() <= 1e-5,
                        "{what}[{i}], onto {onto}: {u} against {v}"
                    );
                }
            }
            assert!(want.1.iter().any(|&g| g != 0.0));
        }
    }
}
