//! The row gather on Burn's CubeCL backend: Burn's gather forward, and a scatter-add backward
//! with one thread per element of the output's gradient.
//!
//! Viewing the source as `[outer, rows, inner]` (`rows` along the gathered axis) and the
//! output's gradient as `[outer, N, inner]`, thread `(o, i, c)` adds `grad[o, i, c]` to
//! `source_grad[o, indices[i], c]` with a float atomic add ([`crate::cube::atomic`]). Burn's own
//! backward (`select_assign` with `Add`) runs one thread per `(o, c)` walking all `N` indices in
//! order: 144 threads over 117,792 indices for the tiny network's face features, the bulk of a
//! training step on an H100 (BENCHMARKS.md, "On a GPU").
//!
//! The atomic adds make the sum's order, and so its last bits, depend on thread scheduling, as
//! in the rasterizer's backward.

use burn::backend::TensorMetadata;
use burn::backend::ops::FloatTensorOps;
use burn::backend::tensor::{FloatTensor, IntTensor};
use burn::tensor::DType;
use burn_cubecl::CubeBackend;
use burn_cubecl::cubecl;
use burn_cubecl::cubecl::prelude::*;

use super::op::{RowGatherKernels, RowGatherOps};
use crate::cube::atomic::{AtomicAddF32, use_native_float_atomics};
use crate::cube::host::{
    arg, cast_to, count_1d, prepare, prepare_i32, tensor_arg, tensor_f32, zeros_f32,
};

/// One thread per element of `grad` (`[outer, count, inner]`): adds it to `out`
/// (`[outer, rows, inner]`) at its row's index. Indices outside `0..rows` add nothing.
#[cube(launch)]
fn scatter_add_rows_kernel<A: AtomicAddF32>(
    grad: &[f32],
    indices: &[i32],
    out: &[Atomic<A>],
    units: usize,
    count: usize,
    inner: usize,
    rows: usize,
) {
    let unit = ABSOLUTE_POS;
    if unit < units {
        let c = unit % inner;
        let oi = unit / inner;
        let i = oi % count;
        let o = oi / count;
        let row = indices[i];
        if row >= 0 && (row as usize) < rows {
            A::atomic_add_f32(&out[(o * rows + row as usize) * inner + c], grad[unit]);
        }
    }
}

impl RowGatherOps for CubeBackend {
    fn gather_rows(
        tensor: FloatTensor<Self>,
        dim: usize,
        indices: IntTensor<Self>,
    ) -> FloatTensor<Self> {
        Self::float_select(tensor, dim, indices)
    }
}

impl RowGatherKernels for CubeBackend {
    fn scatter_add_rows(
        grad: FloatTensor<Self>,
        dim: usize,
        indices: IntTensor<Self>,
        rows: usize,
        dtype: DType,
    ) -> FloatTensor<Self> {
        let _span = tracing::trace_span!("cube_scatter_add_rows").entered();
        let shape = grad.shape();
        let dims: &[usize] = &shape;
        let outer: usize = dims[..dim].iter().product();
        let count = dims[dim];
        let inner: usize = dims[dim + 1..].iter().product();
        let mut source_shape = dims.to_vec();
        source_shape[dim] = rows;
        let (client, device) = (grad.client.clone(), grad.device.clone());
        let out_len = outer * rows * inner;
        let out = zeros_f32(&client, &device, out_len);
        let units = outer * count * inner;
        if units > 0 && out_len > 0 {
            let grad = prepare(grad);
            let indices = prepare_i32(indices);
            macro_rules! launch {
                ($slot:ty) => {
                    scatter_add_rows_kernel::launch::<$slot>(
                        &client,
                        count_1d(units),
                        CubeDim::new_1d(crate::cube::host::THREADS_1D),
                        tensor_arg(&grad),
                        tensor_arg(&indices),
                        arg(&out, out_len),
                        units,
                        count,
                        inner,
                        rows,
                    )
                };
            }
            if use_native_float_atomics(&client) {
                launch!(f32);
            } else {
                launch!(u32);
            }
        }
        cast_to(tensor_f32(&client, &device, out, &source_shape), dtype)
    }
}
