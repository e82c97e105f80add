//! `select` that stays correct on CubeCL backends at any index count.
//!
//! The backward of `Tensor::select` is a `select_assign` with `Add`, and Burn 0.22.1's CubeCL
//! `select_assign` mis-sums once it is given 65,536 or more indices (65,535 add up exactly; a
//! test in `tests/tests/backend_parity.rs` gathers 70,000 rows on wgpu and finds errors of 5
//! where the values are about 1). The model gathers rows by index in many places (face corners,
//! feature samples, neighbours); at the official template's size some of them pass that count
//! in training. [`select_rows`] splits such a gather into chunks of [`SELECT_CHUNK`] indices and
//! concatenates the results, so every backward `select_assign` stays below the bug. On the CPU
//! backends, and below the threshold, it is exactly `Tensor::select`: their numerics do not
//! change by a bit (a split gather's gradient is summed per chunk, a float reordering).

use burn::tensor::{Int, Tensor};

use crate::device::runs_on_host;

/// Indices per `select` (and so per backward `select_assign`) once a gather is split.
pub const SELECT_CHUNK: usize = 32_768;

/// Index counts from which [`select_rows`] splits (the first count Burn 0.22.1 mis-sums).
pub const SELECT_SPLIT_FROM: usize = 65_536;

/// `tensor.select(dim, indices)`, split into chunks of [`SELECT_CHUNK`] indices on CubeCL
/// devices when there are [`SELECT_SPLIT_FROM`] or more (module docs). Same values and
/// gradients.
pub fn select_rows<const D: usize>(
    tensor: Tensor<D>,
    dim: usize,
    indices: Tensor<1, Int>,
) -> Tensor<D> {
    let n = indices.dims()[0];
    if n < SELECT_SPLIT_FROM || runs_on_host(&tensor.device()) {
        return tensor.select(dim, indices);
    }
    split_select(tensor, dim, indices)
}

fn split_select<const D: usize>(
    tensor: Tensor<D>,
    dim: usize,
    indices: Tensor<1, Int>,
) -> Tensor<D> {
    let n = indices.dims()[0];
    let parts: Vec<Tensor<D>> = (0..n)
        .step_by(SELECT_CHUNK)
        .map(|start| {
            let len = SELECT_CHUNK.min(n - start);
            tensor
                .clone()
                .select(dim, indices.clone().narrow(0, start, len))
        })
        .collect();
    Tensor::cat(parts, dim)
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::tensor::{Device, TensorData};

    use crate::testing::read;

    /// Split and unsplit gathers give the same values and the same gradient; on a CPU device
    /// `select_rows` is plain `select`.
    #[test]
    fn split_gathers_equal_select() {
        let device = Device::flex().autodiff();
        let (rows, n) = (300usize, SELECT_SPLIT_FROM + 1234);
        let index: Vec<i64> = (0..n as i64).map(|i| (i * 7919) % rows as i64).collect();
        let x = Tensor::<2>::from_data(
            TensorData::new((0..rows * 2).map(|i| i as f32 * 0.01).collect(), [rows, 2]),
            &device,
        )
        .require_grad();
        let idx = Tensor::<1, Int>::from_data(TensorData::new(index, [n]), &device);
        let w = Tensor::<2>::ones([n, 2], &device);
        // The split path itself (select_rows takes it on CubeCL devices only).
        let a = split_select(x.clone(), 0, idx.clone());
        let b = x.clone().select(0, idx);
        assert_eq!(read(a.clone()), read(b.clone()));
        let ga = read(x.grad(&(a * w.clone()).sum().backward()).unwrap());
        let gb = read(x.grad(&(b * w).sum().backward()).unwrap());
        assert_eq!(ga, gb);
        assert!(runs_on_host(&device));
    }
}
