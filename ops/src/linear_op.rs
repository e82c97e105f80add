//! Linear layers with a bias as one custom op on the CPU backends (design.md §1.4).
//!
//! `y = x·W + b` for `x` `[.., I]`, `W` `[I, O]` (Burn's layout), `b` `[O]`. Burn's `Linear` runs
//! as a matrix product plus a broadcast bias add, and on Flex every product's output is a zeroed
//! byte buffer that is then copied once more into an aligned allocation; the autodiff backward
//! repeats that for both of its products and reduces the bias gradient as a third op. The
//! fusion block alone calls twelve of them per call, so on the quickstart's training step that
//! bookkeeping was about 35 ms of one core's time (BENCHMARKS.md, 2026-11-25: "where the serial
//! time is").
//!
//! Here the forward writes the bias into the output rows and accumulates `x·W` onto them with
//! one `gemm` call; the backward is `∂x = g·Wᵀ`, `∂W = xᵀ·g` (the transposes are strides, not
//! copies) and `∂b = Σ_rows g`, each written once into a buffer of its own. Products above
//! [`PARALLEL_MACS`] multiply-adds run on rayon's threads. `gemm` reduces each output element
//! in a fixed order whatever the thread count, and the bias gradient sums fixed blocks of rows
//! in block order, so results are deterministic. Layers without a bias keep Burn's
//! `Linear::forward`, which is also the reference the op is tested against; on CubeCL devices a
//! layer with a bias is a [`SharedLinear`] (see [`affine`]).

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
use burn::nn::Linear;
use burn::tensor::{Element, Shape, Tensor};
use bytemuck::Pod;
use rayon::prelude::*;

use lifegom_render::device::runs_on_host;
use lifegom_render::host_buffer;
use lifegom_render::in_precision;
use lifegom_render::op_backward::{gradient_per_input, record};
use lifegom_render::readback::{HostLend, cpu_float_from};

use crate::shared_linear::SharedLinear;

/// Products of at least this many multiply-adds run on rayon's threads; smaller ones cost less
/// on the calling thread than a hand-off. Burn's Flex uses `192³` ≈ 7.1 M, which leaves the
/// Point Transformer's and the heads' ~1–5 M products on one of two cores.
pub const PARALLEL_MACS: usize = 1 << 21;

/// Rows per block of the bias gradient's sum: blocks are summed in parallel, then added in block
/// order.
const BIAS_ROWS_PER_BLOCK: usize = 2048;

/// `layer` applied to `x` `[.., I]`: the custom op on the CPU backends when the layer has a
/// bias, else Burn's own `Linear::forward`.
pub fn forward<const D: usize>(layer: &Linear, x: Tensor<D>) -> Tensor<D> {
    affine(x, layer.weight.val(), layer.bias.as_ref().map(|b| b.val()))
}

/// `x·weight + bias` for `x` `[.., I]`, `weight` `[I, O]`, `bias` `[O]` on any device: the
/// custom op on the CPU backends when there is a bias; on CubeCL devices a shared layer used
/// once ([`SharedLinear`]), whose weight and bias gradients are formed split-k
/// ([`crate::split_k`]: Burn's autodiff gives a long reduction to a handful of cubes); else
/// Burn's `linear`.
pub fn affine<const D: usize>(
    x: Tensor<D>,
    weight: Tensor<2>,
    bias: Option<Tensor<1>>,
) -> Tensor<D> {
    match bias {
        Some(bias) if runs_on_host(&x.device()) => linear(x, weight, bias),
        Some(bias) => SharedLinear::new(weight, bias).forward(x),
        None => burn::tensor::module::linear(x, weight, None),
    }
}

/// `x·weight + bias` for `x` `[.., I]`, `weight` `[I, O]`, `bias` `[O]`, through the custom op
/// (CPU backends only; callers route, see [`forward`] and [`affine`]).
pub fn linear<const D: usize>(x: Tensor<D>, weight: Tensor<2>, bias: Tensor<1>) -> Tensor<D> {
    Tensor::from_dispatch(<burn::backend::Dispatch as HostLinearOps>::host_linear(
        x.into_dispatch(),
        weight.into_dispatch(),
        bias.into_dispatch(),
    ))
}

/// `x·W + b` over the last dimension of `x`; the output keeps `x`'s leading dimensions.
#[backend_extension(NdArray, Flex, Autodiff)]
pub trait HostLinearOps: Backend {
    /// The affine map.
    fn host_linear(
        x: FloatTensor<Self>,
        weight: FloatTensor<Self>,
        bias: FloatTensor<Self>,
    ) -> FloatTensor<Self>;
}

/// The op's inputs on one backend: what the forward takes and the node keeps.
#[derive(Debug, Clone)]
pub struct LinearInputs<B: Backend> {
    x: FloatTensor<B>,
    weight: FloatTensor<B>,
    bias: FloatTensor<B>,
}

/// What a backend implements so that `Autodiff<B>` can differentiate the op.
#[doc(hidden)]
pub trait LinearKernels: Backend {
    /// The forward.
    fn linear_forward(inputs: LinearInputs<Self>) -> FloatTensor<Self>;
    /// `[∂x, ∂W, ∂b]` given `∂y`.
    fn linear_backward(
        inputs: LinearInputs<Self>,
        grad: FloatTensor<Self>,
    ) -> [FloatTensor<Self>; 3];
}

/// The float types the kernels run in (`f32`, and `f64` for the precision tests).
trait GemmFloat: Element + Pod + Copy + Send + Sync + Default + std::ops::AddAssign {
    const ONE: Self;
}
impl GemmFloat for f32 {
    const ONE: Self = 1.0;
}
impl GemmFloat for f64 {
    const ONE: Self = 1.0;
}

/// A row-major or transposed view for [`gemm_into`]: element `(r, c)` at `r·row + c·col`.
#[derive(Clone, Copy)]
struct View<'a, T> {
    data: &'a [T],
    row: usize,
    col: usize,
}

impl<'a, T> View<'a, T> {
    /// A row-major matrix `width` elements wide.
    fn row_major(data: &'a [T], width: usize) -> Self {
        Self {
            data,
            row: width,
            col: 1,
        }
    }

    /// The transpose of a row-major matrix `width` elements wide: its data, strides swapped.
    fn transposed(data: &'a [T], width: usize) -> Self {
        Self {
            data,
            row: 1,
            col: width,
        }
    }
}

/// `dst` `[m, n]` (row-major) `+= lhs·rhs` (when `accumulate`, else `=`), `lhs` `[m, k]`, `rhs`
/// `[k, n]`.
fn gemm_into<T: GemmFloat>(
    dst: &mut [T],
    (m, n, k): (usize, usize, usize),
    lhs: View<'_, T>,
    rhs: View<'_, T>,
    accumulate: bool,
) {
    assert!(dst.len() >= m * n, "linear: output buffer too small");
    let last = |v: View<'_, T>, rows: usize, cols: usize| {
        (rows > 0 && cols > 0).then(|| (rows - 1) * v.row + (cols - 1) * v.col)
    };
    assert!(
        last(lhs, m, k).is_none_or(|i| i < lhs.data.len())
            && last(rhs, k, n).is_none_or(|i| i < rhs.data.len()),
        "linear: operand views out of bounds"
    );
    if m == 0 || n == 0 {
        return;
    }
    if k == 0 {
        if !accumulate {
            dst[..m * n].fill(T::default());
        }
        return;
    }
    let parallelism = if m.saturating_mul(n).saturating_mul(k) >= PARALLEL_MACS {
        gemm::Parallelism::Rayon(0)
    } else {
        gemm::Parallelism::None
    };
    // SAFETY: every index gemm reads is `r·row + c·col` for `r < rows`, `c < cols` of a view,
    // at most the last index checked above, and it writes `dst[i·n + j]` for `i < m`, `j < n`
    // within the checked length. `dst` is borrowed mutably, so nothing else aliases it. `T` is
    // f32 or f64, which gemm supports.
    unsafe {
        gemm::gemm(
            m,
            n,
            k,
            dst.as_mut_ptr(),
            1,
            n as isize,
            accumulate,
            lhs.data.as_ptr(),
            lhs.col as isize,
            lhs.row as isize,
            rhs.data.as_ptr(),
            rhs.col as isize,
            rhs.row as isize,
            T::ONE,
            T::ONE,
            false,
            false,
            false,
            parallelism,
        );
    }
}

/// `x` `[rows, I]`, `w` `[I, O]`, `b` `[O]` → `[rows, O]`.
fn forward_kernel<T: GemmFloat>(x: &[T], w: &[T], b: &[T]) -> Vec<T> {
    let (i, o) = (w.len() / b.len().max(1), b.len());
    let rows = x.len() / i.max(1);
    let mut out = host_buffer::repeated(b, rows);
    gemm_into(
        &mut out,
        (rows, o, i),
        View::row_major(x, i),
        View::row_major(w, o),
        true,
    );
    out
}

/// Gradients of [`forward_kernel`] given `g` `[rows, O]`: `(∂x, ∂W, ∂b)`.
///
/// `∂x` and `(∂W, ∂b)` are independent: above [`PARALLEL_MACS`] they are computed side by side
/// (`rayon::join`), so that allocating and zeroing the large `∂x` on one thread overlaps the
/// `∂W` product on the other instead of running while that core waits.
fn backward_kernel<T: GemmFloat>(x: &[T], w: &[T], g: &[T], o: usize) -> (Vec<T>, Vec<T>, Vec<T>) {
    let i = w.len() / o.max(1);
    let rows = g.len() / o.max(1);
    let input_grad = || {
        // ∂x = g·Wᵀ: Wᵀ[c][r] = W[r][c] is W read with its strides swapped.
        let mut dx = vec![T::default(); rows * i];
        gemm_into(
            &mut dx,
            (rows, i, o),
            View::row_major(g, o),
            View::transposed(w, o),
            false,
        );
        dx
    };
    let parameter_grads = || {
        // ∂W = xᵀ·g.
        let mut dw = vec![T::default(); i * o];
        gemm_into(
            &mut dw,
            (i, o, rows),
            View::transposed(x, i),
            View::row_major(g, o),
            false,
        );
        (dw, bias_grad(g, o))
    };
    let (dx, (dw, db)) = if rows.saturating_mul(i).saturating_mul(o) >= PARALLEL_MACS {
        rayon::join(input_grad, parameter_grads)
    } else {
        (input_grad(), parameter_grads())
    };
    (dx, dw, db)
}

/// `∂b = Σ_rows g` for `g` `[rows, O]`, in fixed blocks of rows added in block order.
fn bias_grad<T: GemmFloat>(g: &[T], o: usize) -> Vec<T> {
    let partials: Vec<Vec<T>> = g
        .par_chunks(BIAS_ROWS_PER_BLOCK * o.max(1))
        .map(|block| {
            let mut sum = vec![T::default(); o];
            for row in block.chunks_exact(o.max(1)) {
                for (s, &v) in sum.iter_mut().zip(row) {
                    *s += v;
                }
            }
            sum
        })
        .collect();
    let mut db = vec![T::default(); o];
    for partial in partials {
        for (s, v) in db.iter_mut().zip(partial) {
            *s += v;
        }
    }
    db
}

fn output_shape(x: &Shape, out_features: usize) -> Shape {
    let mut dims = x.to_vec();
    if let Some(last) = dims.last_mut() {
        *last = out_features;
    }
    Shape::from(dims)
}

fn cpu_forward<B: HostLend>(inputs: LinearInputs<B>) -> FloatTensor<B> {
    in_precision!(inputs.x.dtype(), cpu_forward_in(inputs))
}

fn cpu_forward_in<B: HostLend, T: GemmFloat>(inputs: LinearInputs<B>) -> FloatTensor<B> {
    let (device, dtype) = (inputs.x.device(), inputs.x.dtype());
    let shape = output_shape(&inputs.x.shape(), inputs.bias.shape()[0]);
    let x = B::lend_float::<T>("linear input", &inputs.x);
    let w = B::lend_float::<T>("linear weight", &inputs.weight);
    let b = B::lend_float::<T>("linear bias", &inputs.bias);
    cpu_float_from::<B, T>(forward_kernel(&x, &w, &b), shape, dtype, &device)
}

fn cpu_backward<B: HostLend>(inputs: LinearInputs<B>, grad: FloatTensor<B>) -> [FloatTensor<B>; 3] {
    in_precision!(inputs.x.dtype(), cpu_backward_in(inputs, grad))
}

fn cpu_backward_in<B: HostLend, T: GemmFloat>(
    inputs: LinearInputs<B>,
    grad: FloatTensor<B>,
) -> [FloatTensor<B>; 3] {
    let device = inputs.x.device();
    let shapes = [&inputs.x, &inputs.weight, &inputs.bias].map(|t| (t.shape(), t.dtype()));
    let o = inputs.bias.shape()[0];
    let g = B::lend_float::<T>("linear gradient", &grad);
    let x = B::lend_float::<T>("linear input", &inputs.x);
    let w = B::lend_float::<T>("linear weight", &inputs.weight);
    let (dx, dw, db) = backward_kernel(&x, &w, &g, o);
    let [(sx, tx), (sw, tw), (sb, tb)] = shapes;
    [
        cpu_float_from::<B, T>(dx, sx, tx, &device),
        cpu_float_from::<B, T>(dw, sw, tw, &device),
        cpu_float_from::<B, T>(db, sb, tb, &device),
    ]
}

/// Implements the op for a CPU backend through the shared slice kernels.
macro_rules! cpu_linear_backend {
    ($backend:ty) => {
        impl HostLinearOps for $backend {
            fn host_linear(
                x: FloatTensor<Self>,
                weight: FloatTensor<Self>,
                bias: FloatTensor<Self>,
            ) -> FloatTensor<Self> {
                cpu_forward::<Self>(LinearInputs { x, weight, bias })
            }
        }

        impl LinearKernels for $backend {
            fn linear_forward(inputs: LinearInputs<Self>) -> FloatTensor<Self> {
                cpu_forward::<Self>(inputs)
            }

            fn linear_backward(
                inputs: LinearInputs<Self>,
                grad: FloatTensor<Self>,
            ) -> [FloatTensor<Self>; 3] {
                cpu_backward::<Self>(inputs, grad)
            }
        }
    };
}

cpu_linear_backend!(NdArray);
cpu_linear_backend!(Flex);

#[derive(Debug)]
struct LinearBackward;

impl<B: LinearKernels> Backward<B, 3> for LinearBackward {
    type State = LinearInputs<B>;

    fn backward(
        self,
        ops: Ops<Self::State, 3>,
        grads: &mut Gradients,
        _checkpointer: &mut Checkpointer,
    ) {
        gradient_per_input::<B, _, 3>(ops, grads, B::linear_backward);
    }
}

impl<B: HostLinearOps + LinearKernels, C: CheckpointStrategy> HostLinearOps for Autodiff<B, C> {
    fn host_linear(
        x: FloatTensor<Self>,
        weight: FloatTensor<Self>,
        bias: FloatTensor<Self>,
    ) -> FloatTensor<Self> {
        let (x, x_node) = x.into_parts();
        let (weight, w_node) = weight.into_parts();
        let (bias, b_node) = bias.into_parts();
        let inputs = LinearInputs { x, weight, bias };
        record::<B, C, _, _, 3>(
            LinearBackward,
            [x_node, w_node, b_node],
            inputs,
            B::linear_forward,
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::nn::LinearConfig;
    use burn::tensor::{Device, Distribution};
    use lifegom_render::testing::read;

    /// The op equals Burn's `Linear::forward`, values and the gradients of the input, the
    /// weight and the bias, for 2-D and 3-D inputs, at sizes below and above
    /// [`PARALLEL_MACS`].
    fn matches_burn_linear(device: &Device) {
        let ad = device.clone().autodiff();
        for (lead, i, o) in [
            (vec![1usize], 1usize, 1usize),
            (vec![7], 5, 3),
            (vec![13, 3], 16, 24),
            (vec![2_500], 144, 64),
        ] {
            let layer = LinearConfig::new(i, o).init(&ad);
            let rows: usize = lead.iter().product();
            let x =
                Tensor::<2>::random([rows, i], Distribution::Normal(0.0, 1.0), &ad).require_grad();
            let w = Tensor::<2>::random([rows, o], Distribution::Normal(0.0, 1.0), &ad);
            let check = |y2: Tensor<2>, grads: &burn::tensor::Gradients| {
                [
                    read(y2),
                    read(x.grad(grads).expect("input gradient")),
                    read(layer.weight.val().grad(grads).expect("weight gradient")),
                    read(
                        layer
                            .bias
                            .as_ref()
                            .expect("bias")
                            .val()
                            .grad(grads)
                            .expect("bias gradient"),
                    ),
                ]
            };
            let results = [true, false].map(|ours| {
                let y = if lead.len() == 2 {
                    let x3 = x.clone().reshape([lead[0], lead[1], i]);
                    let y3 = if ours {
                        forward(&layer, x3)
                    } else {
                        layer.forward(x3)
                    };
                    y3.reshape([rows, o])
                } else if ours {
                    forward(&layer, x.clone())
                } else {
                    layer.forward(x.clone())
                };
                let grads = (y.clone() * w.clone()).sum().backward();
                check(y, &grads)
            });
            for (k, name) in [
                "output",
                "input gradient",
                "weight gradient",
                "bias gradient",
            ]
            .iter()
            .enumerate()
            {
                let (a, b) = (&results[0][k], &results[1][k]);
                assert_eq!(a.len(), b.len(), "{name}");
                let scale = b.iter().fold(1.0f32, |m, v| m.max(v.abs()));
                let diff = a
                    .iter()
                    .zip(b)
                    .fold(0.0f32, |m, (p, q)| m.max((p - q).abs()));
                assert!(
                    diff <= 2e-5 * scale,
                    "{lead:?}×{i}→{o} {name}: max diff {diff:.2e} (scale {scale:.2e})"
                );
            }
        }
    }

    lifegom_render::cpu_backend_tests!(linear_op_matches_burn_linear => matches_burn_linear);

    /// The kernels in `f64` against a direct triple loop, including the transposed strides of
    /// the backward.
    #[test]
    fn kernels_match_direct_sums() {
        let mut rng = lifegom_render::rng::Rng::new(3);
        let (rows, i, o) = (9usize, 4usize, 6usize);
        let mut random = |n: usize| (0..n).map(|_| rng.range(-1.0, 1.0)).collect::<Vec<f64>>();
        let (x, w, b, g) = (random(rows * i), random(i * o), random(o), random(rows * o));
        let y = forward_kernel(&x, &w, &b);
        let (dx, dw, db) = backward_kernel(&x, &w, &g, o);
        for r in 0..rows {
            for c in 0..o {
                let direct = b[c] + (0..i).map(|k| x[r * i + k] * w[k * o + c]).sum::<f64>();
                assert!((y[r * o + c] - direct).abs() < 1e-12, "y[{r}][{c}]");
            }
            for k in 0..i {
                let direct: f64 = (0..o).map(|c| g[r * o + c] * w[k * o + c]).sum();
                assert!((dx[r * i + k] - direct).abs() < 1e-12, "dx[{r}][{k}]");
            }
        }
        for k in 0..i {
            for c in 0..o {
                let direct: f64 = (0..rows).map(|r| x[r * i + k] * g[r * o + c]).sum();
                assert!((dw[k * o + c] - direct).abs() < 1e-12, "dw[{k}][{c}]");
            }
        }
        for c in 0..o {
            let direct: f64 = (0..rows).map(|r| g[r * o + c]).sum();
            assert!((db[c] - direct).abs() < 1e-12, "db[{c}]");
        }
    }
}
