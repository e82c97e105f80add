//! Products of per-head channel blocks with a projection's column blocks, as one custom op on the
//! CPU backends: what the single-query cross-attention needs to attend without projecting its
//! keys and values (design.md §7.4).
//!
//! A projection `W` `[D, H·d_k]` (Burn's `[in, out]` layout, output channels grouped by head)
//! has one column block `W_h` `[D, d_k]` per head. For `a` with one block per head:
//!
//! - [`HeadMap::Forward`]: `[B, H·D] → [B, H·d_k]`, `out_h = s·a_h·W_h` (head `h` of the input
//!   goes through head `h`'s slice of the projection);
//! - [`HeadMap::Adjoint`]: `[B, H·d_k] → [B, H·D]`, `out_h = s·a_h·W_hᵀ`.
//!
//! Each map's input gradient is the other map of the output gradient, and both weight
//! gradients are `∂W_h = s·wide_hᵀ·narrow_h` with `wide` the `H·D`-wide operand and `narrow` the
//! `H·d_k`-wide one. Every product is one `gemm` call per head on strided views of the
//! operands ([`crate::host_gemm`]): no head is copied out. CubeCL devices do not use the op; the
//! cross-attention there keeps its literal form (see [`super::AttentionLayer`]).

// NdArray is deprecated in Burn 0.22 in favour of Flex; ndarray is the CI backend the project
// requires (design.md §1.4).
#![allow(deprecated)]

use burn::backend::TensorMetadata;
use burn::backend::autodiff::checkpoint::base::Checkpointer;
use burn::backend::autodiff::checkpoint::strategy::CheckpointStrategy;
use burn::backend::autodiff::grads::Gradients;
use burn::backend::autodiff::ops::{Backward, Ops};
use burn::backend::tensor::FloatTensor;
use burn::backend::{Autodiff, Backend, Flex, NdArray, backend_extension};
use burn::tensor::{Shape, Tensor};

use crate::host_gemm::{GemmFloat, Out, PARALLEL_MACS, View, Write, gemm_into};
use lifegom_render::in_precision;
use lifegom_render::op_backward::{gradient_per_input, record};
use lifegom_render::readback::{HostLend, cpu_float_from};

/// See the module docs.
#[backend_extension(NdArray, Flex, Autodiff)]
pub trait HeadProductOps: Backend {
    /// `a` `[B, ..]` times `weight` `[D, H·d_k]`, head block by head block.
    fn head_product(
        a: FloatTensor<Self>,
        weight: FloatTensor<Self>,
        product: HeadProduct,
    ) -> FloatTensor<Self>;
}

/// Which product, over how many heads, with which scale.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct HeadProduct {
    /// Heads H; must divide the weight's columns.
    pub heads: usize,
    /// Which way the blocks are multiplied.
    pub map: HeadMap,
    /// The factor `s` applied to every product.
    pub scale: f64,
}

/// The two products of [`HeadProduct`]; each is the other's input gradient.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum HeadMap {
    /// `[B, H·D] → [B, H·d_k]`: `out_h = s·a_h·W_h`.
    Forward,
    /// `[B, H·d_k] → [B, H·D]`: `out_h = s·a_h·W_hᵀ`.
    Adjoint,
}

impl HeadMap {
    fn other(self) -> Self {
        match self {
            Self::Forward => Self::Adjoint,
            Self::Adjoint => Self::Forward,
        }
    }
}

/// `product` of `a` `[B, ..]` with `weight` `[D, H·d_k]` on a CPU device (callers route; the
/// op has no CubeCL implementation).
///
/// Panics if `a`'s width is not `H·D` ([`HeadMap::Forward`]) or `H·d_k` ([`HeadMap::Adjoint`]),
/// or if H does not divide the weight's columns: shapes fixed by the caller's layer, not input.
pub fn head_product(a: Tensor<2>, weight: Tensor<2>, product: HeadProduct) -> Tensor<2> {
    let dims = HeadDims::of(&a.shape(), &weight.shape(), product);
    assert_eq!(
        a.dims()[1],
        dims.input_width(product.map),
        "head product {product:?}: input {:?} against weight {:?}",
        a.dims(),
        weight.dims()
    );
    Tensor::from_dispatch(<burn::backend::Dispatch as HeadProductOps>::head_product(
        a.into_dispatch(),
        weight.into_dispatch(),
        product,
    ))
}

/// The sizes of one call.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct HeadDims {
    rows: usize,
    heads: usize,
    /// The weight's rows (the model width D).
    wide: usize,
    /// Channels per head d_k.
    narrow: usize,
}

impl HeadDims {
    fn of(a: &Shape, weight: &Shape, product: HeadProduct) -> Self {
        let heads = product.heads.max(1);
        assert!(
            weight[1].is_multiple_of(heads),
            "head product: {heads} heads do not divide the weight's {} columns",
            weight[1]
        );
        Self {
            rows: a[0],
            heads,
            wide: weight[0],
            narrow: weight[1] / heads,
        }
    }

    fn input_width(&self, map: HeadMap) -> usize {
        match map {
            HeadMap::Forward => self.heads * self.wide,
            HeadMap::Adjoint => self.heads * self.narrow,
        }
    }

    fn output_width(&self, map: HeadMap) -> usize {
        self.input_width(map.other())
    }
}

/// The op's inputs on one backend: what the forward takes and the node keeps.
#[derive(Debug, Clone)]
pub struct HeadProductInputs<B: Backend> {
    a: FloatTensor<B>,
    weight: FloatTensor<B>,
    product: HeadProduct,
}

/// What a backend implements so that `Autodiff<B>` can differentiate the op.
#[doc(hidden)]
pub trait HeadProductKernels: Backend {
    /// The forward.
    fn head_product_forward(inputs: HeadProductInputs<Self>) -> FloatTensor<Self>;
    /// `[∂a, ∂W]` given `∂out`.
    fn head_product_backward(
        inputs: HeadProductInputs<Self>,
        grad: FloatTensor<Self>,
    ) -> [FloatTensor<Self>; 2];
}

/// `map` of `a` with `w`, head by head, into a fresh `[rows, output width]` buffer.
fn product_kernel<T: GemmFloat>(
    a: &[T],
    w: &[T],
    dims: HeadDims,
    map: HeadMap,
    scale: T,
) -> Vec<T> {
    let HeadDims {
        rows,
        heads,
        wide,
        narrow,
    } = dims;
    let (a_width, out_width) = (dims.input_width(map), dims.output_width(map));
    let w_width = heads * narrow;
    let mut out = vec![T::default(); rows * out_width];
    for h in 0..heads {
        let (shape, a_offset, out_offset, w_h) = match map {
            // [rows, D] · [D, d_k]
            HeadMap::Forward => (
                (rows, narrow, wide),
                h * wide,
                h * narrow,
                View::row_major(w, w_width).offset(h * narrow),
            ),
            // [rows, d_k] · [d_k, D]
            HeadMap::Adjoint => (
                (rows, wide, narrow),
                h * narrow,
                h * wide,
                View::transposed(w, w_width).offset(h * narrow),
            ),
        };
        gemm_into(
            Out {
                data: &mut out[out_offset.min(rows * out_width)..],
                row: out_width,
            },
            shape,
            View::row_major(a, a_width).offset(a_offset),
            w_h,
            Write::Overwrite,
            scale,
        );
    }
    out
}

/// `∂W` `[D, H·d_k]` with blocks `s·wide_hᵀ·narrow_h`, for `wide` `[rows, H·D]` and `narrow`
/// `[rows, H·d_k]`.
fn weight_grad_kernel<T: GemmFloat>(wide: &[T], narrow: &[T], dims: HeadDims, scale: T) -> Vec<T> {
    let HeadDims {
        rows,
        heads,
        wide: d,
        narrow: dk,
    } = dims;
    let mut dw = vec![T::default(); d * heads * dk];
    for h in 0..heads {
        gemm_into(
            Out {
                data: &mut dw[(h * dk).min(d * heads * dk)..],
                row: heads * dk,
            },
            (d, dk, rows),
            View::transposed(wide, heads * d).offset(h * d),
            View::row_major(narrow, heads * dk).offset(h * dk),
            Write::Overwrite,
            scale,
        );
    }
    dw
}

/// `(∂a, ∂W)` given `g` `= ∂out`, side by side on rayon's threads when large.
fn backward_kernel<T: GemmFloat>(
    a: &[T],
    w: &[T],
    g: &[T],
    dims: HeadDims,
    map: HeadMap,
    scale: T,
) -> (Vec<T>, Vec<T>) {
    let input_grad = || product_kernel(g, w, dims, map.other(), scale);
    let weight_grad = || match map {
        HeadMap::Forward => weight_grad_kernel(a, g, dims, scale),
        HeadMap::Adjoint => weight_grad_kernel(g, a, dims, scale),
    };
    let macs = dims.rows * dims.heads * dims.wide * dims.narrow;
    if macs >= PARALLEL_MACS {
        rayon::join(input_grad, weight_grad)
    } else {
        (input_grad(), weight_grad())
    }
}

fn cpu_forward<B: HostLend>(inputs: HeadProductInputs<B>) -> FloatTensor<B> {
    in_precision!(inputs.a.dtype(), cpu_forward_in(inputs))
}

fn cpu_forward_in<B: HostLend, T: GemmFloat>(inputs: HeadProductInputs<B>) -> FloatTensor<B> {
    let (device, dtype) = (inputs.a.device(), inputs.a.dtype());
    let product = inputs.product;
    let dims = HeadDims::of(&inputs.a.shape(), &inputs.weight.shape(), product);
    let a = B::lend_float::<T>("head product input", &inputs.a);
    let w = B::lend_float::<T>("head product weight", &inputs.weight);
    let out = product_kernel(&a, &w, dims, product.map, T::from_f64(product.scale));
    let shape = Shape::from(vec![dims.rows, dims.output_width(product.map)]);
    cpu_float_from::<B, T>(out, shape, dtype, &device)
}

fn cpu_backward<B: HostLend>(
    inputs: HeadProductInputs<B>,
    grad: FloatTensor<B>,
) -> [FloatTensor<B>; 2] {
    in_precision!(inputs.a.dtype(), cpu_backward_in(inputs, grad))
}

fn cpu_backward_in<B: HostLend, T: GemmFloat>(
    inputs: HeadProductInputs<B>,
    grad: FloatTensor<B>,
) -> [FloatTensor<B>; 2] {
    let device = inputs.a.device();
    let product = inputs.product;
    let dims = HeadDims::of(&inputs.a.shape(), &inputs.weight.shape(), product);
    let (sa, ta) = (inputs.a.shape(), inputs.a.dtype());
    let (sw, tw) = (inputs.weight.shape(), inputs.weight.dtype());
    let g = B::lend_float::<T>("head product gradient", &grad);
    let a = B::lend_float::<T>("head product input", &inputs.a);
    let w = B::lend_float::<T>("head product weight", &inputs.weight);
    let (da, dw) = backward_kernel(&a, &w, &g, dims, product.map, T::from_f64(product.scale));
    [
        cpu_float_from::<B, T>(da, sa, ta, &device),
        cpu_float_from::<B, T>(dw, sw, tw, &device),
    ]
}

/// Implements the op for a CPU backend through the shared slice kernels.
macro_rules! cpu_head_product_backend {
    ($backend:ty) => {
        impl HeadProductOps for $backend {
            fn head_product(
                a: FloatTensor<Self>,
                weight: FloatTensor<Self>,
                product: HeadProduct,
            ) -> FloatTensor<Self> {
                cpu_forward::<Self>(HeadProductInputs { a, weight, product })
            }
        }

        impl HeadProductKernels for $backend {
            fn head_product_forward(inputs: HeadProductInputs<Self>) -> FloatTensor<Self> {
                cpu_forward::<Self>(inputs)
            }

            fn head_product_backward(
                inputs: HeadProductInputs<Self>,
                grad: FloatTensor<Self>,
            ) -> [FloatTensor<Self>; 2] {
                cpu_backward::<Self>(inputs, grad)
            }
        }
    };
}

cpu_head_product_backend!(NdArray);
cpu_head_product_backend!(Flex);

#[derive(Debug)]
struct HeadProductBackward;

impl<B: HeadProductKernels> Backward<B, 2> for HeadProductBackward {
    type State = HeadProductInputs<B>;

    fn backward(
        self,
        ops: Ops<Self::State, 2>,
        grads: &mut Gradients,
        _checkpointer: &mut Checkpointer,
    ) {
        gradient_per_input::<B, _, 2>(ops, grads, B::head_product_backward);
    }
}

impl<B: HeadProductOps + HeadProductKernels, C: CheckpointStrategy> HeadProductOps
    for Autodiff<B, C>
{
    fn head_product(
        a: FloatTensor<Self>,
        weight: FloatTensor<Self>,
        product: HeadProduct,
    ) -> FloatTensor<Self> {
        let (a, a_node) = a.into_parts();
        let (weight, w_node) = weight.into_parts();
        record::<B, C, _, _, 2>(
            HeadProductBackward,
            [a_node, w_node],
            HeadProductInputs { a, weight, product },
            B::head_product_forward,
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::tensor::{Device, Distribution};
    use lifegom_render::testing::read;

    /// The products as Burn tensor ops: per head, a column block of `a` times a column block of
    /// the weight (transposed for the adjoint), concatenated.
    fn reference(a: Tensor<2>, w: Tensor<2>, product: HeadProduct) -> Tensor<2> {
        let [d, cols] = w.dims();
        let (heads, dk) = (product.heads, cols / product.heads);
        let blocks = (0..heads)
            .map(|h| {
                let w_h = w.clone().slice([0..d, h * dk..(h + 1) * dk]);
                match product.map {
                    HeadMap::Forward => a
                        .clone()
                        .slice([0..a.dims()[0], h * d..(h + 1) * d])
                        .matmul(w_h),
                    HeadMap::Adjoint => a
                        .clone()
                        .slice([0..a.dims()[0], h * dk..(h + 1) * dk])
                        .matmul(w_h.transpose()),
                }
            })
            .collect();
        Tensor::cat(blocks, 1) * product.scale
    }

    /// Values and the gradients of both inputs against [`reference`], for both maps, one and
    /// several heads, sizes below and above [`PARALLEL_MACS`].
    fn matches_tensor_ops(device: &Device) {
        let ad = device.clone().autodiff();
        for (rows, heads, d, dk, scale) in [
            (5usize, 1usize, 4usize, 4usize, 1.0f64),
            (9, 3, 6, 2, 0.5),
            (1_300, 4, 144, 36, 2.0),
        ] {
            for map in [HeadMap::Forward, HeadMap::Adjoint] {
                let product = HeadProduct { heads, map, scale };
                let in_width = match map {
                    HeadMap::Forward => heads * d,
                    HeadMap::Adjoint => heads * dk,
                };
                let out_width = heads * d + heads * dk - in_width;
                let a = Tensor::<2>::random([rows, in_width], Distribution::Normal(0.0, 1.0), &ad)
                    .require_grad();
                let w = Tensor::<2>::random([d, heads * dk], Distribution::Normal(0.0, 1.0), &ad)
                    .require_grad();
                let mix =
                    Tensor::<2>::random([rows, out_width], Distribution::Normal(0.0, 1.0), &ad);
                let run = |ours: bool| {
                    let out = if ours {
                        head_product(a.clone(), w.clone(), product)
                    } else {
                        reference(a.clone(), w.clone(), product)
                    };
                    let grads = (out.clone() * mix.clone()).sum().backward();
                    [
                        read(out),
                        read(a.grad(&grads).expect("input gradient")),
                        read(w.grad(&grads).expect("weight gradient")),
                    ]
                };
                let (ours, theirs) = (run(true), run(false));
                for (k, what) in ["output", "input gradient", "weight gradient"]
                    .iter()
                    .enumerate()
                {
                    assert_eq!(ours[k].len(), theirs[k].len(), "{what}");
                    let scale = theirs[k].iter().fold(1.0f32, |m, v| m.max(v.abs()));
                    for (i, (x, y)) in ours[k].iter().zip(&theirs[k]).enumerate() {
                        assert!(
                            (x - y).abs() <= 2e-5 * scale,
                            "{map:?} {rows}×{heads}×{d}×{dk} {what}[{i}]: {x} vs {y}"
                        );
                    }
                }
            }
        }
    }

    lifegom_render::cpu_backend_tests!(head_product_matches_tensor_ops => matches_tensor_ops);
}
