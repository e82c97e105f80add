//! [`super::interpolate`] on Burn's CubeCL backend.
//!
//! - `interpolate_forward_kernel`, one thread per output element `(i, ch)`: the weighted sum of
//!   the `K` neighbours' channel `ch`, in neighbour order.
//! - `interpolate_backward_kernel`, one thread per `(i, ch)` over a zeroed `∂x`: adds
//!   `w[i, j]·g[i, ch]` at each neighbour with float atomic adds
//!   ([`lifegom_render::cube::atomic`]): the order of a row's sums is not fixed.
//!
//! A neighbour index outside `0..n` reads zero and receives nothing (the callers build them in
//! range; this only keeps a bad index from reading out of bounds).

use burn::backend::TensorMetadata;
use burn::backend::tensor::{FloatTensor, IntTensor};
use burn_cubecl::CubeBackend;
use burn_cubecl::cubecl;
use burn_cubecl::cubecl::prelude::*;
use lifegom_render::cube::atomic::{AtomicAddF32, use_native_float_atomics};
use lifegom_render::cube::host::{
    THREADS_1D, arg, cast_to, count_1d, prepare, prepare_i32, tensor_arg, tensor_f32, zeros_f32,
};

use super::op::{Base, InterpolationKernels, InterpolationOps};

#[cube(launch)]
#[allow(clippy::too_many_arguments)]
fn interpolate_forward_kernel(
    x: &[f32],
    neighbours: &[i32],
    weights: &[f32],
    base: &[f32],
    out: &mut [f32],
    units: usize,
    n: usize,
    k: usize,
    c: usize,
    #[comptime] added: bool,
) {
    let unit = ABSOLUTE_POS;
    if unit < units {
        let ch = unit % c;
        let i = unit / c;
        let mut total = 0.0f32;
        for j in 0..k {
            let row = neighbours[i * k + j];
            if row >= 0 && (row as usize) < n {
                total += weights[i * k + j] * x[row as usize * c + ch];
            }
        }
        if added {
            total += base[unit];
        }
        out[unit] = total;
    }
}

#[cube(launch)]
#[allow(clippy::too_many_arguments)]
fn interpolate_backward_kernel<A: AtomicAddF32>(
    neighbours: &[i32],
    weights: &[f32],
    grad: &[f32],
    x_grad: &[Atomic<A>],
    units: usize,
    n: usize,
    k: usize,
    c: usize,
) {
    let unit = ABSOLUTE_POS;
    if unit < units {
        let ch = unit % c;
        let i = unit / c;
        for j in 0..k {
            let row = neighbours[i * k + j];
            if row >= 0 && (row as usize) < n {
                A::atomic_add_f32(
                    &x_grad[row as usize * c + ch],
                    weights[i * k + j] * grad[unit],
                );
            }
        }
    }
}

impl InterpolationOps for CubeBackend {
    fn point_interpolation(
        x: FloatTensor<Self>,
        neighbours: IntTensor<Self>,
        weights: FloatTensor<Self>,
        base: FloatTensor<Self>,
        onto: Base,
    ) -> FloatTensor<Self> {
        let dtype = x.dtype();
        let (client, device) = (x.client.clone(), x.device.clone());
        let [n, c] = [x.shape()[0], x.shape()[1]];
        let [m, k] = [weights.shape()[0], weights.shape()[1]];
        let (x, neighbours, weights) = (prepare(x), prepare_i32(neighbours), prepare(weights));
        let added = onto == Base::Added;
        // Without a base the kernel reads none: the weights are bound in its place.
        let base = if added {
            prepare(base)
        } else {
            weights.clone()
        };
        let units = m * c;
        let out = client.empty(4 * units.max(1));
        if units > 0 {
            interpolate_forward_kernel::launch(
                &client,
                count_1d(units),
                CubeDim::new_1d(THREADS_1D),
                tensor_arg(&x),
                tensor_arg(&neighbours),
                tensor_arg(&weights),
                tensor_arg(&base),
                arg(&out, units),
                units,
                n,
                k,
                c,
                added,
            );
        }
        cast_to(tensor_f32(&client, &device, out, &[m, c]), dtype)
    }
}

impl InterpolationKernels for CubeBackend {
    fn point_interpolation_backward(
        neighbours: IntTensor<Self>,
        weights: FloatTensor<Self>,
        grad: FloatTensor<Self>,
        points: usize,
    ) -> FloatTensor<Self> {
        let dtype = grad.dtype();
        let (client, device) = (grad.client.clone(), grad.device.clone());
        let [m, c] = [grad.shape()[0], grad.shape()[1]];
        let k = weights.shape()[1];
        let (neighbours, weights, grad) =
            (prepare_i32(neighbours), prepare(weights), prepare(grad));
        let x_grad = zeros_f32(&client, &device, points * c);
        let units = m * c;
        if units > 0 {
            macro_rules! launch {
                ($slot:ty) => {
                    interpolate_backward_kernel::launch::<$slot>(
                        &client,
                        count_1d(units),
                        CubeDim::new_1d(THREADS_1D),
                        tensor_arg(&neighbours),
                        tensor_arg(&weights),
                        tensor_arg(&grad),
                        arg(&x_grad, points * c),
                        units,
                        points,
                        k,
                        c,
                    )
                };
            }
            if use_native_float_atomics(&client) {
                launch!(f32);
            } else {
                launch!(u32);
            }
        }
        cast_to(tensor_f32(&client, &device, x_grad, &[points, c]), dtype)
    }
}
