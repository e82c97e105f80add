//! Row gathers as one custom op on the CPU backends (design.md §1.4).
//!
//! `y[i] = x[index[i]]` over the first dimension. Burn's `select` backward is a `select_add`
//! of the gradient into zeros, which Flex runs as one loop on the calling thread; the model's
//! gathers (neighbours in the Point Transformer, face corners in the heads, subdivision corners)
//! run about a dozen of them per feedback step, and their backwards cost ~8 ms of one core per
//! quickstart step while the other waited (BENCHMARKS.md, session 11).
//!
//! Here the backward inverts the index first, a stable counting sort giving every row of `x`
//! the positions that read it in ascending order, and then sums each row's gradient rows on
//! rayon's threads, starting from zero and in that order: the additions `select_add` makes, so
//! the gradient is the same to the bit. The forward copies rows on rayon's threads. The node
//! keeps only the index, not `x`.

// NdArray is deprecated in Burn 0.22 in favour of Flex; ndarray is the CI backend the project
// requires (design.md §1.4).
#![allow(deprecated)]

use std::ops::AddAssign;

use burn::backend::TensorMetadata;
use burn::backend::autodiff::checkpoint::base::Checkpointer;
use burn::backend::autodiff::checkpoint::strategy::CheckpointStrategy;
use burn::backend::autodiff::grads::Gradients;
use burn::backend::autodiff::ops::{Backward, Ops, OpsKind};
use burn::backend::tensor::{FloatTensor, IntTensor};
use burn::backend::{Autodiff, Backend, Flex, NdArray, backend_extension};
use burn::tensor::{DType, Element, Shape};
use bytemuck::Pod;
use rayon::prelude::*;

use crate::op_backward::gradient_per_input;
use crate::readback::{HostLend, cpu_float_from};

/// Elements (rows × width) per rayon task.
const ELEMENTS_PER_TASK: usize = 1 << 14;

/// Gathers (and gradients) of fewer elements run on the calling thread: below this a hand-off
/// and the backward's index inversion cost more than they save (`op-bench`).
const PARALLEL_ELEMENTS: usize = 1 << 17;

/// `x` `[R, ..]` gathered by `index` `[n]` along the first dimension: `[n, ..]`. An index
/// outside `[0, R)` gathers a row of zeros (callers pass valid ones; this keeps a bad one from
/// panicking). The gradient flows to `x`.
#[backend_extension(NdArray, Flex, Autodiff)]
pub trait HostGatherOps: Backend {
    /// The gather.
    fn gather_rows(x: FloatTensor<Self>, index: IntTensor<Self>) -> FloatTensor<Self>;
}

/// What the backward needs: the index, and `x`'s shape and type.
#[derive(Debug, Clone)]
pub struct GatherState<B: Backend> {
    index: IntTensor<B>,
    shape: Shape,
    dtype: DType,
}

/// The float types the kernels run in (`f32`, and `f64` for the precision tests).
trait RowFloat: Element + Pod + Default + AddAssign + Send + Sync {}
impl RowFloat for f32 {}
impl RowFloat for f64 {}

/// Rows per rayon task for rows of `width` elements (at least one).
fn rows_per_task(width: usize) -> usize {
    (ELEMENTS_PER_TASK / width.max(1)).max(1)
}

/// Row `r` of `rows` rows, if `r` is one.
fn row(r: i32, rows: usize) -> Option<usize> {
    usize::try_from(r).ok().filter(|&r| r < rows)
}

/// `[n, width]` rows of `x` (`[rows, width]`) at `index`.
fn forward_kernel<T: RowFloat>(x: &[T], width: usize, index: &[i32]) -> Vec<T> {
    let rows = x.len() / width.max(1);
    let mut y = vec![T::default(); index.len() * width];
    if width == 0 {
        return y;
    }
    let copy = |(block, index): (&mut [T], &[i32])| {
        for (dst, &r) in block.chunks_exact_mut(width).zip(index) {
            if let Some(r) = row(r, rows) {
                dst.copy_from_slice(&x[r * width..(r + 1) * width]);
            }
        }
    };
    let per_task = rows_per_task(width);
    if y.len() < PARALLEL_ELEMENTS {
        copy((&mut y, index));
    } else {
        y.par_chunks_mut(per_task * width)
            .zip(index.par_chunks(per_task))
            .for_each(copy);
    }
    y
}

/// The gradient of [`forward_kernel`] for `rows` rows of `x`, given `g` `[n, width]`.
fn backward_kernel<T: RowFloat>(g: &[T], width: usize, index: &[i32], rows: usize) -> Vec<T> {
    let mut dx = vec![T::default(); rows * width];
    if width == 0 {
        return dx;
    }
    if g.len().max(dx.len()) < PARALLEL_ELEMENTS {
        // `select_add`'s own loop.
        for (i, &r) in index.iter().enumerate() {
            if let Some(r) = row(r, rows) {
                let dst = &mut dx[r * width..(r + 1) * width];
                for (d, &v) in dst.iter_mut().zip(&g[i * width..(i + 1) * width]) {
                    *d += v;
                }
            }
        }
        return dx;
    }
    // Stable counting sort of the positions by the row they read: `readers[start[r]..start[r +
    // 1]]` are the positions reading row `r`, ascending.
    let mut start = vec![0usize; rows + 1];
    for r in index.iter().filter_map(|&r| row(r, rows)) {
        start[r + 1] += 1;
    }
    for r in 0..rows {
        start[r + 1] += start[r];
    }
    let mut next = start.clone();
    let mut readers = vec![0usize; start[rows]];
    for (i, r) in index.iter().enumerate() {
        if let Some(r) = row(*r, rows) {
            readers[next[r]] = i;
            next[r] += 1;
        }
    }
    let sum = |(first, block): (usize, &mut [T])| {
        for (r, dst) in (first..).zip(block.chunks_exact_mut(width)) {
            for &i in &readers[start[r]..start[r + 1]] {
                for (d, &v) in dst.iter_mut().zip(&g[i * width..(i + 1) * width]) {
                    *d += v;
                }
            }
        }
    };
    let per_task = rows_per_task(width);
    dx.par_chunks_mut(per_task * width)
        .enumerate()
        .for_each(|(task, block)| sum((task * per_task, block)));
    dx
}

/// `x`'s shape as `(rows, width)`.
fn rows_and_width(shape: &Shape) -> (usize, usize) {
    let dims = shape.to_vec();
    let rows = dims.first().copied().unwrap_or(1);
    (rows, dims.iter().skip(1).product())
}

fn cpu_forward<B: HostLend>(x: FloatTensor<B>, index: IntTensor<B>) -> FloatTensor<B> {
    in_precision!(x.dtype(), cpu_forward_in(x, index))
}

fn cpu_forward_in<B: HostLend, T: RowFloat>(
    x: FloatTensor<B>,
    index: IntTensor<B>,
) -> FloatTensor<B> {
    let (device, dtype, shape) = (x.device(), x.dtype(), x.shape());
    let (_, width) = rows_and_width(&shape);
    let values = B::lend_float::<T>("gathered tensor", &x);
    let index = B::lend_int("gather index", &index);
    let mut out = shape.to_vec();
    out[0] = index.len();
    let y = forward_kernel(&values, width, &index);
    cpu_float_from::<B, T>(y, out, dtype, &device)
}

fn cpu_backward<B: HostLend>(state: GatherState<B>, grad: FloatTensor<B>) -> [FloatTensor<B>; 1] {
    in_precision!(state.dtype, cpu_backward_in(state, grad))
}

fn cpu_backward_in<B: HostLend, T: RowFloat>(
    state: GatherState<B>,
    grad: FloatTensor<B>,
) -> [FloatTensor<B>; 1] {
    let device = grad.device();
    let (rows, width) = rows_and_width(&state.shape);
    let g = B::lend_float::<T>("gather gradient", &grad);
    let index = B::lend_int("gather index", &state.index);
    let dx = backward_kernel(&g, width, &index, rows);
    [cpu_float_from::<B, T>(
        dx,
        state.shape,
        state.dtype,
        &device,
    )]
}

impl HostGatherOps for NdArray {
    fn gather_rows(x: FloatTensor<Self>, index: IntTensor<Self>) -> FloatTensor<Self> {
        cpu_forward::<Self>(x, index)
    }
}

impl HostGatherOps for Flex {
    fn gather_rows(x: FloatTensor<Self>, index: IntTensor<Self>) -> FloatTensor<Self> {
        cpu_forward::<Self>(x, index)
    }
}

#[derive(Debug)]
struct GatherBackward;

impl<B: HostLend> Backward<B, 1> for GatherBackward {
    type State = GatherState<B>;

    fn backward(
        self,
        ops: Ops<Self::State, 1>,
        grads: &mut Gradients,
        _checkpointer: &mut Checkpointer,
    ) {
        gradient_per_input::<B, _, 1>(ops, grads, cpu_backward::<B>);
    }
}

impl<B: HostGatherOps + HostLend, C: CheckpointStrategy> HostGatherOps for Autodiff<B, C> {
    fn gather_rows(x: FloatTensor<Self>, index: IntTensor<Self>) -> FloatTensor<Self> {
        let (x, node) = x.into_parts();
        match GatherBackward
            .prepare::<C>([node])
            .compute_bound()
            .stateful()
        {
            OpsKind::Tracked(prep) => {
                let state = GatherState {
                    index: index.clone(),
                    shape: x.shape(),
                    dtype: x.dtype(),
                };
                prep.finish(state, B::gather_rows(x, index))
            }
            OpsKind::UnTracked(prep) => prep.finish(B::gather_rows(x, index)),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::tensor::{Device, Distribution, Int, Tensor, TensorData};

    use crate::testing::read;

    fn gather<const D: usize>(x: Tensor<D>, index: Tensor<1, Int>) -> Tensor<D> {
        Tensor::from_dispatch(<burn::backend::Dispatch as HostGatherOps>::gather_rows(
            x.into_dispatch(),
            index.into_dispatch(),
        ))
    }

    fn bits(v: Vec<f32>) -> Vec<u32> {
        v.into_iter().map(f32::to_bits).collect()
    }

    /// Values and gradients equal Burn's `select` to the bit, for small (one-thread) and large
    /// (rayon) gathers with repeated, unused and out-of-order rows, in 2-D and 3-D, and a
    /// gradient of `-0` stays `-0` where a row is read once (zeros + `-0` is `+0`, as in
    /// `select_add`).
    fn equals_select(device: &Device) {
        let ad = device.clone().autodiff();
        for (rows, n, inner) in [(5, 7, [3, 1]), (300, 20_000, [4, 2]), (1, 3, [2, 1])] {
            let width: usize = inner.iter().product();
            let x = Tensor::<3>::random([rows, inner[0], inner[1]], Distribution::Default, &ad)
                .require_grad();
            // Skips the last row, repeats the others out of order.
            let index: Vec<i64> = (0..n as i64)
                .map(|i| (i * 7919) % (rows as i64 - 1).max(1))
                .collect();
            let index = Tensor::<1, Int>::from_data(TensorData::new(index, [n]), &ad);
            let mut g: Vec<f32> = (0..n * width).map(|i| (i as f32 * 0.37).sin()).collect();
            g[0] = -0.0;
            let g = Tensor::<3>::from_data(TensorData::new(g, [n, inner[0], inner[1]]), &ad);
            let ours = gather(x.clone(), index.clone());
            let burns = x.clone().select(0, index);
            assert_eq!(
                bits(read(ours.clone())),
                bits(read(burns.clone())),
                "{rows} rows"
            );
            let d_ours = read(x.grad(&(ours * g.clone()).sum().backward()).unwrap());
            let d_burns = read(x.grad(&(burns * g).sum().backward()).unwrap());
            assert_eq!(bits(d_ours), bits(d_burns), "{rows} rows, gradient");
        }
    }

    /// An index outside the rows gathers zeros and takes no gradient, in `f64`.
    #[test]
    fn bad_indices_gather_zeros() {
        let x = [1.0f64, 2.0, 3.0, 4.0];
        let y = forward_kernel(&x, 2, &[1, -1, 5, 0]);
        assert_eq!(y, [3.0, 4.0, 0.0, 0.0, 0.0, 0.0, 1.0, 2.0]);
        let dx = backward_kernel(&[1.0f64; 8], 2, &[1, -1, 5, 1], 2);
        assert_eq!(dx, [0.0, 0.0, 2.0, 2.0]);
    }

    crate::cpu_backend_tests!(gather_equals_select => equals_select);
}
