//! [`super::relative_positions`] on Burn's CubeCL backend.
//!
//! - `relative_forward_kernel`, one thread per `(i, κ, axis)`: `p[nbr] − p[centre]`.
//! - `relative_backward_kernel`, one thread per `(i, κ, axis)` over a zeroed `∂p`: adds the
//!   offset's gradient at the neighbour; the thread with `κ = 0` also subtracts the sum of its
//!   group's gradients at the centre, one atomic add per group instead of `k`. Float atomic adds
//!   ([`lifegom_render::cube::atomic`]): the order of a point's sums is not fixed.
//!
//! An index outside `0..n` reads zero and receives nothing (the callers build them in range;
//! this only keeps a bad index from reading out of bounds).

use burn::backend::TensorMetadata;
use burn::backend::tensor::{FloatTensor, IntTensor};
use burn_cubecl::CubeBackend;
use burn_cubecl::cubecl;
use burn_cubecl::cubecl::prelude::*;
use lifegom_render::cube::atomic::{AtomicAddF32, use_native_float_atomics};
use lifegom_render::cube::host::{
    THREADS_1D, arg, cast_to, count_1d, prepare, prepare_i32, tensor_arg, tensor_f32, zeros_f32,
};

use super::op::{GroupingKernels, GroupingOps};

/// `p[row, axis]`, or zero for a row outside `0..n`.
#[cube]
fn coordinate(p: &[f32], row: i32, axis: usize, n: usize) -> f32 {
    let mut value = 0.0f32;
    if row >= 0 && (row as usize) < n {
        value = p[row as usize * 3 + axis];
    }
    value
}

#[cube(launch)]
fn relative_forward_kernel(
    p: &[f32],
    neighbours: &[i32],
    centres: &[i32],
    out: &mut [f32],
    units: usize,
    n: usize,
    k: usize,
) {
    let unit = ABSOLUTE_POS;
    if unit < units {
        let axis = unit % 3;
        let slot = unit / 3;
        out[unit] =
            coordinate(p, neighbours[slot], axis, n) - coordinate(p, centres[slot / k], axis, n);
    }
}

#[cube(launch)]
fn relative_backward_kernel<A: AtomicAddF32>(
    neighbours: &[i32],
    centres: &[i32],
    grad: &[f32],
    p_grad: &[Atomic<A>],
    units: usize,
    n: usize,
    k: usize,
) {
    let unit = ABSOLUTE_POS;
    if unit < units {
        let axis = unit % 3;
        let slot = unit / 3;
        let row = neighbours[slot];
        if row >= 0 && (row as usize) < n {
            A::atomic_add_f32(&p_grad[row as usize * 3 + axis], grad[unit]);
        }
        // The group's first slot (CubeCL kernels have no `is_multiple_of`).
        let group = slot / k;
        if slot == group * k {
            let centre = centres[group];
            if centre >= 0 && (centre as usize) < n {
                let mut total = 0.0f32;
                for kk in 0..k {
                    total += grad[(group * k + kk) * 3 + axis];
                }
                A::atomic_add_f32(&p_grad[centre as usize * 3 + axis], -total);
            }
        }
    }
}

impl GroupingOps for CubeBackend {
    fn relative_positions(
        p: FloatTensor<Self>,
        neighbours: IntTensor<Self>,
        centres: IntTensor<Self>,
    ) -> FloatTensor<Self> {
        let dtype = p.dtype();
        let (client, device) = (p.client.clone(), p.device.clone());
        let n = p.shape()[0];
        let m = centres.shape()[0];
        let slots = neighbours.shape()[0];
        let k = slots / m.max(1);
        let (p, neighbours, centres) = (prepare(p), prepare_i32(neighbours), prepare_i32(centres));
        let units = slots * 3;
        let out = client.empty(4 * units.max(1));
        if units > 0 {
            relative_forward_kernel::launch(
                &client,
                count_1d(units),
                CubeDim::new_1d(THREADS_1D),
                tensor_arg(&p),
                tensor_arg(&neighbours),
                tensor_arg(&centres),
                arg(&out, units),
                units,
                n,
                k,
            );
        }
        cast_to(tensor_f32(&client, &device, out, &[m, k, 3]), dtype)
    }
}

impl GroupingKernels for CubeBackend {
    fn relative_positions_backward(
        neighbours: IntTensor<Self>,
        centres: IntTensor<Self>,
        grad: FloatTensor<Self>,
        points: usize,
    ) -> FloatTensor<Self> {
        let dtype = grad.dtype();
        let (client, device) = (grad.client.clone(), grad.device.clone());
        let m = centres.shape()[0];
        let slots = neighbours.shape()[0];
        let k = slots / m.max(1);
        let (neighbours, centres, grad) =
            (prepare_i32(neighbours), prepare_i32(centres), prepare(grad));
        let p_grad = zeros_f32(&client, &device, points * 3);
        let units = slots * 3;
        if units > 0 {
            macro_rules! launch {
                ($slot:ty) => {
                    relative_backward_kernel::launch::<$slot>(
                        &client,
                        count_1d(units),
                        CubeDim::new_1d(THREADS_1D),
                        tensor_arg(&neighbours),
                        tensor_arg(&centres),
                        tensor_arg(&grad),
                        arg(&p_grad, points * 3),
                        units,
                        points,
                        k,
                    )
                };
            }
            if use_native_float_atomics(&client) {
                launch!(f32);
            } else {
                launch!(u32);
            }
        }
        cast_to(tensor_f32(&client, &device, p_grad, &[points, 3]), dtype)
    }
}
