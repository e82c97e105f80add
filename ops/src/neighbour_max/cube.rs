//! [`super::max_over_neighbours`] on Burn's CubeCL backend.
//!
//! - `neighbour_max_kernel`, one thread per output element `(i, ch)`: walks the `k` neighbours
//!   in order and keeps the first largest value and its neighbour.
//! - `neighbour_max_backward_kernel`, one thread per element `(i, j, ch)` of `∂h`: the output's
//!   gradient where `j` is the maximum's neighbour, zero elsewhere.

use burn::backend::TensorMetadata;
use burn::backend::tensor::{FloatTensor, IntTensor};
use burn::tensor::DType;
use burn_cubecl::CubeBackend;
use burn_cubecl::cubecl;
use burn_cubecl::cubecl::prelude::*;
use lifegom_render::cube::host::{
    THREADS_1D, arg, cast_to, count_1d, empty_u32, prepare, prepare_i32, tensor_arg, tensor_f32,
    tensor_of,
};

use super::op::{NeighbourMaxKernels, NeighbourMaxOps};

#[cube(launch)]
fn neighbour_max_kernel(
    h: &[f32],
    out: &mut [f32],
    argmax: &mut [i32],
    units: usize,
    k: usize,
    c: usize,
) {
    let unit = ABSOLUTE_POS;
    if unit < units {
        let ch = unit % c;
        let base = (unit / c) * k * c + ch;
        let mut best = h[base];
        let mut from = 0usize;
        for j in 1..k {
            let value = h[base + j * c];
            if value > best {
                best = value;
                from = j;
            }
        }
        out[unit] = best;
        argmax[unit] = from as i32;
    }
}

#[cube(launch)]
fn neighbour_max_backward_kernel(
    argmax: &[i32],
    grad: &[f32],
    out: &mut [f32],
    units: usize,
    k: usize,
    c: usize,
) {
    let unit = ABSOLUTE_POS;
    if unit < units {
        let ch = unit % c;
        let j = (unit / c) % k;
        let i = unit / (k * c);
        let mut value = 0.0f32;
        if argmax[i * c + ch] as usize == j {
            value = grad[i * c + ch];
        }
        out[unit] = value;
    }
}

impl NeighbourMaxKernels for CubeBackend {
    fn neighbour_max_indexed(h: FloatTensor<Self>) -> (FloatTensor<Self>, IntTensor<Self>) {
        let dtype = h.dtype();
        let [m, k, c] = h.shape().dims::<3>();
        let (client, device) = (h.client.clone(), h.device.clone());
        let h = prepare(h);
        let units = m * c;
        let out = client.empty(4 * units.max(1));
        let argmax = empty_u32(&client, units);
        if units > 0 && k > 0 {
            neighbour_max_kernel::launch(
                &client,
                count_1d(units),
                CubeDim::new_1d(THREADS_1D),
                tensor_arg(&h),
                arg(&out, units),
                arg(&argmax, units),
                units,
                k,
                c,
            );
        }
        (
            cast_to(tensor_f32(&client, &device, out, &[m, c]), dtype),
            tensor_of(&client, &device, argmax, &[m, c], DType::I32),
        )
    }

    fn neighbour_max_backward(
        argmax: IntTensor<Self>,
        grad: FloatTensor<Self>,
        k: usize,
    ) -> FloatTensor<Self> {
        let dtype = grad.dtype();
        let [m, c] = grad.shape().dims::<2>();
        let (client, device) = (grad.client.clone(), grad.device.clone());
        let (argmax, grad) = (prepare_i32(argmax), prepare(grad));
        let units = m * k * c;
        let out = client.empty(4 * units.max(1));
        if units > 0 {
            neighbour_max_backward_kernel::launch(
                &client,
                count_1d(units),
                CubeDim::new_1d(THREADS_1D),
                tensor_arg(&argmax),
                tensor_arg(&grad),
                arg(&out, units),
                units,
                k,
                c,
            );
        }
        cast_to(tensor_f32(&client, &device, out, &[m, k, c]), dtype)
    }
}

impl NeighbourMaxOps for CubeBackend {
    fn neighbour_max(h: FloatTensor<Self>) -> FloatTensor<Self> {
        Self::neighbour_max_indexed(h).0
    }
}
