//! [`super::interpolate`] on Burn's CubeCL backend.
//!
//! - `interpolate_forward_kernel`, one thread per output element `(i, ch)`: the weighted sum of
//!   the `K` neighbours' channel `ch`, in neighbour order.
//! - `interpolate_backward_kernel`, one thread per element `(p, ch)` of `∂x`: the sum of
//!   `w[i, j]·g[i, ch]` over the slots `i·K + j` that name coarse point `p`, in slot order (the
//!   table's inverse, `super::NeighbourTable`): every element written once, no zero-fill, no
//!   atomics, and the same sum whatever the scheduling.
//!
//! A neighbour index outside `0..n` reads zero and receives nothing (the callers build them in
//! range; this only keeps a bad index from reading out of bounds).

use burn::backend::TensorMetadata;
use burn::backend::tensor::{FloatTensor, IntTensor};
use burn_cubecl::CubeBackend;
use burn_cubecl::cubecl;
use burn_cubecl::cubecl::prelude::*;
use lifegom_render::cube::host::{
    THREADS_1D, arg, cast_to, count_1d, prepare, prepare_i32, tensor_arg, tensor_f32,
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
fn interpolate_backward_kernel(
    readers: &[i32],
    weights: &[f32],
    grad: &[f32],
    x_grad: &mut [f32],
    units: usize,
    points: usize,
    k: usize,
    c: usize,
) {
    let unit = ABSOLUTE_POS;
    if unit < units {
        let ch = unit % c;
        let p = unit / c;
        let mut total = 0.0f32;
        let end = readers[p + 1] as usize;
        let mut e = readers[p] as usize;
        while e < end {
            let slot = readers[points + 1 + e] as usize;
            total += weights[slot] * grad[(slot / k) * c + ch];
            e += 1;
        }
        x_grad[unit] = total;
    }
}

impl InterpolationOps for CubeBackend {
    fn point_interpolation(
        x: FloatTensor<Self>,
        neighbours: IntTensor<Self>,
        _readers: IntTensor<Self>,
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
        readers: IntTensor<Self>,
        weights: FloatTensor<Self>,
        grad: FloatTensor<Self>,
        points: usize,
    ) -> FloatTensor<Self> {
        let dtype = grad.dtype();
        let (client, device) = (grad.client.clone(), grad.device.clone());
        let c = grad.shape()[1];
        let k = weights.shape()[1];
        let (readers, weights, grad) = (prepare_i32(readers), prepare(weights), prepare(grad));
        let units = points * c;
        let x_grad = client.empty(4 * units.max(1));
        if units > 0 {
            interpolate_backward_kernel::launch(
                &client,
                count_1d(units),
                CubeDim::new_1d(THREADS_1D),
                tensor_arg(&readers),
                tensor_arg(&weights),
                tensor_arg(&grad),
                arg(&x_grad, units),
                units,
                points,
                k,
                c,
            );
        }
        cast_to(tensor_f32(&client, &device, x_grad, &[points, c]), dtype)
    }
}
