//! [`super::relative_positions`] on Burn's CubeCL backend.
//!
//! - `relative_forward_kernel`, one thread per `(i, κ, axis)`: `p[nbr] − p[centre]`.
//! - `relative_backward_kernel`, one thread per element `(q, axis)` of `∂p`: the gradients of the
//!   slots that name `q` as a neighbour, minus the summed gradients of the groups centred on it,
//!   both lists read from the tables' inverses (`super::GroupTable`, `crate::inverse`) in order:
//!   every element written once, no zero-fill, no atomics, the same sum whatever the
//!   scheduling.
//!
//! An index outside `0..n` reads zero and receives nothing (the callers build them in range;
//! this only keeps a bad index from reading out of bounds).

use burn::backend::TensorMetadata;
use burn::backend::tensor::{FloatTensor, IntTensor};
use burn_cubecl::CubeBackend;
use burn_cubecl::cubecl;
use burn_cubecl::cubecl::prelude::*;
use lifegom_render::cube::host::{
    THREADS_1D, arg, cast_to, count_1d, prepare, prepare_i32, tensor_arg, tensor_f32,
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
fn relative_backward_kernel(
    readers: &[i32],
    grad: &[f32],
    p_grad: &mut [f32],
    units: usize,
    points: usize,
    slots: usize,
    k: usize,
) {
    let unit = ABSOLUTE_POS;
    if unit < units {
        let axis = unit % 3;
        let q = unit / 3;
        let mut total = 0.0f32;
        // The slots naming `q` as a neighbour: `[offsets (points + 1) | slots]`.
        let mut e = readers[q] as usize;
        let end = readers[q + 1] as usize;
        while e < end {
            total += grad[readers[points + 1 + e] as usize * 3 + axis];
            e += 1;
        }
        // The groups centred on `q`, after the neighbours' inverse.
        let base = points + 1 + slots;
        let mut centred = 0.0f32;
        let mut e = readers[base + q] as usize;
        let end = readers[base + q + 1] as usize;
        while e < end {
            let group = readers[base + points + 1 + e] as usize;
            for kk in 0..k {
                centred += grad[(group * k + kk) * 3 + axis];
            }
            e += 1;
        }
        p_grad[unit] = total - centred;
    }
}

impl GroupingOps for CubeBackend {
    fn relative_positions(
        p: FloatTensor<Self>,
        neighbours: IntTensor<Self>,
        centres: IntTensor<Self>,
        _readers: IntTensor<Self>,
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
        readers: IntTensor<Self>,
        grad: FloatTensor<Self>,
        points: usize,
        k: usize,
    ) -> FloatTensor<Self> {
        let dtype = grad.dtype();
        let (client, device) = (grad.client.clone(), grad.device.clone());
        let slots = grad.shape().num_elements() / 3;
        let (readers, grad) = (prepare_i32(readers), prepare(grad));
        let units = points * 3;
        let p_grad = client.empty(4 * units.max(1));
        if units > 0 {
            relative_backward_kernel::launch(
                &client,
                count_1d(units),
                CubeDim::new_1d(THREADS_1D),
                tensor_arg(&readers),
                tensor_arg(&grad),
                arg(&p_grad, units),
                units,
                points,
                slots,
                k,
            );
        }
        cast_to(tensor_f32(&client, &device, p_grad, &[points, 3]), dtype)
    }
}
