//! Host dropout as one custom op on the CPU backends (design.md §7.4).
//!
//! `y = x·m` with `m` the mask of a [`MaskStream`]. As a tensor product the mask is a float
//! tensor the size of `x`, and Flex runs the product and its backward (`∂x = ∂y·m`) as
//! elementwise loops on the calling thread: the fusion applies dropout to about 8.5 million
//! elements per quickstart step, so those passes cost milliseconds of one core while the other
//! waited (BENCHMARKS.md, session 11).
//!
//! Here the forward draws the mask and multiplies in one pass, split over rayon's threads in
//! the stream's task blocks ([`MaskStream::at`]), and, when the input is tracked, keeps the mask
//! as one bit per element for the backward, which multiplies the gradient by the same values on
//! rayon's threads. Values equal the product with the float mask bit for bit: each element is
//! `x·s` or `x·0` with the same `s` ([`MaskStream::scale`], widened for `f64`).

// NdArray is deprecated in Burn 0.22 in favour of Flex; ndarray is the CI backend the project
// requires (design.md §1.4).
#![allow(deprecated)]

use std::ops::Mul;
use std::sync::Arc;

use burn::backend::TensorMetadata;
use burn::backend::autodiff::checkpoint::base::Checkpointer;
use burn::backend::autodiff::checkpoint::strategy::CheckpointStrategy;
use burn::backend::autodiff::grads::Gradients;
use burn::backend::autodiff::ops::{Backward, Ops, OpsKind};
use burn::backend::tensor::FloatTensor;
use burn::backend::{Autodiff, Backend, Flex, NdArray, backend_extension};
use burn::tensor::Element;
use bytemuck::Pod;
use rayon::prelude::*;

use super::{MASK_VALUES_PER_TASK, MaskStream};
use lifegom_render::in_precision;
use lifegom_render::op_backward::gradient_per_input;
use lifegom_render::readback::{HostLend, cpu_float_from};

/// Mask bits per word of [`KeptBits`]; [`MASK_VALUES_PER_TASK`] is a multiple of it, so a
/// task's block of values is a whole number of words.
const BITS: usize = 64;

/// `x·m` for the mask `m` of `mask` over `x`'s elements in row-major order; the gradient flows
/// to `x`.
#[backend_extension(NdArray, Flex, Autodiff)]
pub trait HostDropoutOps: Backend {
    /// The masked product.
    fn host_dropout(x: FloatTensor<Self>, mask: MaskStream) -> FloatTensor<Self>;
}

/// A drawn mask, one bit per element (bit `i % 64` of word `i / 64` set where element `i` is
/// kept), and the kept elements' value: what the backward multiplies by.
#[derive(Debug, Clone)]
pub struct KeptBits {
    words: Arc<Vec<u64>>,
    scale: f32,
}

/// The float types the kernels run in (`f32`, and `f64` for the precision tests).
trait MaskFloat: Element + Pod + Mul<Output = Self> + From<f32> + Send + Sync {}
impl MaskFloat for f32 {}
impl MaskFloat for f64 {}

/// `(x·m, m's bits)`. Task `t` draws the stream from value `t·MASK_VALUES_PER_TASK`, as
/// [`MaskStream::values`] does.
fn forward_kernel<T: MaskFloat>(x: &[T], mask: MaskStream) -> (Vec<T>, KeptBits) {
    let [kept, dropped] = [T::from(mask.scale()), T::from(0.0)];
    let mut y = vec![dropped; x.len()];
    let mut words = vec![0u64; x.len().div_ceil(BITS)];
    y.par_chunks_mut(MASK_VALUES_PER_TASK)
        .zip(x.par_chunks(MASK_VALUES_PER_TASK))
        .zip(words.par_chunks_mut(MASK_VALUES_PER_TASK / BITS))
        .enumerate()
        .for_each(|(task, ((y, x), words))| {
            let mut stream = mask.at(task * MASK_VALUES_PER_TASK);
            for ((y, x), word) in y.chunks_mut(BITS).zip(x.chunks(BITS)).zip(words) {
                // Two values per draw, low half first: 32 draws per word.
                for pair in 0..BITS / 2 {
                    let [low, high] = stream.next_pair();
                    *word |= (u64::from(low) << (2 * pair)) | (u64::from(high) << (2 * pair + 1));
                }
                for (i, (y, &x)) in y.iter_mut().zip(x).enumerate() {
                    *y = x * if (*word >> i) & 1 == 1 { kept } else { dropped };
                }
            }
        });
    let bits = KeptBits {
        words: Arc::new(words),
        scale: mask.scale(),
    };
    (y, bits)
}

/// `∂y·m` from the mask's bits.
fn backward_kernel<T: MaskFloat>(g: &[T], bits: &KeptBits) -> Vec<T> {
    let [kept, dropped] = [T::from(bits.scale), T::from(0.0)];
    let mut dx = vec![dropped; g.len()];
    dx.par_chunks_mut(MASK_VALUES_PER_TASK)
        .zip(g.par_chunks(MASK_VALUES_PER_TASK))
        .zip(bits.words.par_chunks(MASK_VALUES_PER_TASK / BITS))
        .for_each(|((dx, g), words)| {
            for ((dx, g), &word) in dx.chunks_mut(BITS).zip(g.chunks(BITS)).zip(words) {
                for (i, (dx, &g)) in dx.iter_mut().zip(g).enumerate() {
                    *dx = g * if (word >> i) & 1 == 1 { kept } else { dropped };
                }
            }
        });
    dx
}

fn cpu_forward<B: HostLend>(x: FloatTensor<B>, mask: MaskStream) -> (FloatTensor<B>, KeptBits) {
    in_precision!(x.dtype(), cpu_forward_in(x, mask))
}

fn cpu_forward_in<B: HostLend, T: MaskFloat>(
    x: FloatTensor<B>,
    mask: MaskStream,
) -> (FloatTensor<B>, KeptBits) {
    let (device, shape, dtype) = (x.device(), x.shape(), x.dtype());
    let values = B::lend_float::<T>("dropout input", &x);
    let (y, bits) = forward_kernel(&values, mask);
    (cpu_float_from::<B, T>(y, shape, dtype, &device), bits)
}

fn cpu_backward<B: HostLend>(bits: KeptBits, grad: FloatTensor<B>) -> [FloatTensor<B>; 1] {
    in_precision!(grad.dtype(), cpu_backward_in(bits, grad))
}

fn cpu_backward_in<B: HostLend, T: MaskFloat>(
    bits: KeptBits,
    grad: FloatTensor<B>,
) -> [FloatTensor<B>; 1] {
    let (device, shape, dtype) = (grad.device(), grad.shape(), grad.dtype());
    let g = B::lend_float::<T>("dropout gradient", &grad);
    [cpu_float_from::<B, T>(
        backward_kernel(&g, &bits),
        shape,
        dtype,
        &device,
    )]
}

impl HostDropoutOps for NdArray {
    fn host_dropout(x: FloatTensor<Self>, mask: MaskStream) -> FloatTensor<Self> {
        cpu_forward::<Self>(x, mask).0
    }
}

impl HostDropoutOps for Flex {
    fn host_dropout(x: FloatTensor<Self>, mask: MaskStream) -> FloatTensor<Self> {
        cpu_forward::<Self>(x, mask).0
    }
}

#[derive(Debug)]
struct DropoutBackward;

impl<B: HostLend> Backward<B, 1> for DropoutBackward {
    type State = KeptBits;

    fn backward(
        self,
        ops: Ops<Self::State, 1>,
        grads: &mut Gradients,
        _checkpointer: &mut Checkpointer,
    ) {
        gradient_per_input::<B, _, 1>(ops, grads, cpu_backward::<B>);
    }
}

impl<B: HostDropoutOps + HostLend, C: CheckpointStrategy> HostDropoutOps for Autodiff<B, C> {
    fn host_dropout(x: FloatTensor<Self>, mask: MaskStream) -> FloatTensor<Self> {
        let (x, node) = x.into_parts();
        match DropoutBackward
            .prepare::<C>([node])
            .compute_bound()
            .stateful()
        {
            OpsKind::Tracked(prep) => {
                let (y, bits) = cpu_forward::<B>(x, mask);
                prep.finish(bits, y)
            }
            OpsKind::UnTracked(prep) => prep.finish(B::host_dropout(x, mask)),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::tensor::{Device, Distribution, Tensor, TensorData};
    use lifegom_render::testing::read;

    /// Lengths around the task and word boundaries (odd ones end on a draw's low half).
    const LENGTHS: [usize; 6] = [
        1,
        63,
        65,
        MASK_VALUES_PER_TASK - 1,
        MASK_VALUES_PER_TASK + 64,
        2 * MASK_VALUES_PER_TASK + 7,
    ];

    fn op<const D: usize>(x: Tensor<D>, mask: MaskStream) -> Tensor<D> {
        Tensor::from_dispatch(<burn::backend::Dispatch as HostDropoutOps>::host_dropout(
            x.into_dispatch(),
            mask,
        ))
    }

    /// The op is the product with the float mask of [`MaskStream::values`], bit for bit, values and gradient,
    /// on and off an autodiff device; a negative input times a dropped value stays `-0`.
    fn equals_the_float_mask_product(device: &Device) {
        for (k, n) in LENGTHS.into_iter().enumerate() {
            let mask = MaskStream {
                keep: 0.8,
                seed: 11 + k as u64,
            };
            let floats = mask.values(n);
            let m = Tensor::<1>::from_data(TensorData::new(floats, [n]), device);
            let x = Tensor::<1>::random([n], Distribution::Uniform(-1.0, 1.0), device);
            let g = Tensor::<1>::random([n], Distribution::Uniform(-1.0, 1.0), device);
            let product = read(x.clone() * m.clone());
            let bits = |v: Vec<f32>| v.into_iter().map(f32::to_bits).collect::<Vec<_>>();
            assert_eq!(
                bits(read(op(x.clone(), mask))),
                bits(product.clone()),
                "n = {n}"
            );

            let x_ad = Tensor::<1>::from_inner(x).require_grad();
            let y = op(x_ad.clone(), mask);
            assert_eq!(bits(read(y.clone())), bits(product), "tracked, n = {n}");
            let grads = (y * Tensor::from_inner(g.clone())).sum().backward();
            let dx = read(x_ad.grad(&grads).expect("x takes part"));
            assert_eq!(bits(dx), bits(read(g * m)), "gradient, n = {n}");
        }
    }

    /// In `f64` (the precision tests' type) the kept value is the `f32` scale widened, as the
    /// float mask converted to the input's type is.
    #[test]
    fn f64_kernels_use_the_widened_scale() {
        let mask = MaskStream { keep: 0.7, seed: 2 };
        let n = MASK_VALUES_PER_TASK + 3;
        let floats = mask.values(n);
        let x: Vec<f64> = (0..n).map(|i| (i as f64).sin()).collect();
        let (y, bits) = forward_kernel(&x, mask);
        let expected: Vec<f64> = x
            .iter()
            .zip(&floats)
            .map(|(x, &m)| x * f64::from(m))
            .collect();
        assert_eq!(y, expected);
        assert_eq!(backward_kernel(&x, &bits), expected, "∂x = g·m with g = x");
    }

    lifegom_render::cpu_backend_tests!(host_dropout_equals_the_float_mask_product => equals_the_float_mask_product);
}
