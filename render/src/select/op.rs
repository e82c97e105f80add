//! The row gather as a Burn backend extension for CubeCL devices (design.md §5.7).
//!
//! [`RowGatherOps`] is listed for `Cube` and `Autodiff` only: the CPU backends keep Burn's own
//! `select`, whose backward is correct and fast there, and [`super::select_rows`] never routes
//! them here. The forward is Burn's gather kernel (one thread per output element); what this op
//! replaces is the backward. The autodiff node keeps the indices and the source's row count, not
//! the source, and its backward is [`RowGatherKernels::scatter_add_rows`].

use burn::backend::TensorMetadata;
use burn::backend::autodiff::checkpoint::base::Checkpointer;
use burn::backend::autodiff::checkpoint::strategy::CheckpointStrategy;
use burn::backend::autodiff::grads::Gradients;
use burn::backend::autodiff::ops::{Backward, Ops, OpsKind};
use burn::backend::fusion::custom::TensorSpec;
use burn::backend::fusion::{Fusion, FusionBackend};
use burn::backend::tensor::{FloatTensor, IntTensor};
use burn::backend::{Autodiff, Backend, backend_extension};
use burn::tensor::DType;

use crate::cube::deferred::{Input, Output, Value, array, deferred};
use crate::op_backward::gradient_per_input;

/// `tensor.select(dim, indices)` with a parallel backward.
///
/// `tensor` is `[..., R, ...]` with `R` rows along `dim`; `indices` is `[N]` (int); the output
/// is `tensor`'s shape with `N` along `dim`, row `i` being row `indices[i]`. Gradients flow to
/// `tensor`; an index outside `0..R` reads what Burn's `select` reads and contributes no
/// gradient.
#[backend_extension(Cube, Fusion, Autodiff)]
pub trait RowGatherOps: Backend {
    /// Gathers rows along `dim`.
    #[fusion(dtype = tensor, shape = {
        let mut shape = tensor.clone();
        shape[*dim] = indices[0];
        shape
    })]
    fn gather_rows(
        tensor: FloatTensor<Self>,
        dim: usize,
        indices: IntTensor<Self>,
    ) -> FloatTensor<Self>;
}

/// What a backend implements so that `Autodiff<B>` can differentiate the gather.
#[doc(hidden)]
pub trait RowGatherKernels: Backend {
    /// The source's gradient `[..., rows, ...]` (zeros, plus every row of `grad` — the output's
    /// gradient, `[..., N, ...]` — added at its index along `dim`), in `dtype`.
    fn scatter_add_rows(
        grad: FloatTensor<Self>,
        dim: usize,
        indices: IntTensor<Self>,
        rows: usize,
        dtype: DType,
    ) -> FloatTensor<Self>;
}

/// What the autodiff node keeps: the indices, the axis, the source's row count and dtype.
#[derive(Debug, Clone)]
pub struct GatherState<B: Backend> {
    indices: IntTensor<B>,
    dim: usize,
    rows: usize,
    dtype: DType,
}

#[derive(Debug)]
struct GatherBackward;

impl<B: RowGatherKernels> Backward<B, 1> for GatherBackward {
    type State = GatherState<B>;

    fn backward(
        self,
        ops: Ops<Self::State, 1>,
        grads: &mut Gradients,
        _checkpointer: &mut Checkpointer,
    ) {
        gradient_per_input::<B, _, 1>(ops, grads, |state, grad| {
            [B::scatter_add_rows(
                grad,
                state.dim,
                state.indices,
                state.rows,
                state.dtype,
            )]
        });
    }
}

impl<B: RowGatherOps + RowGatherKernels, C: CheckpointStrategy> RowGatherOps for Autodiff<B, C> {
    fn gather_rows(
        tensor: FloatTensor<Self>,
        dim: usize,
        indices: IntTensor<Self>,
    ) -> FloatTensor<Self> {
        let (tensor, node) = tensor.into_parts();
        let state = GatherState {
            rows: tensor.shape()[dim],
            dtype: tensor.dtype(),
            indices: indices.clone(),
            dim,
        };
        match GatherBackward
            .prepare::<C>([node])
            .compute_bound()
            .stateful()
        {
            OpsKind::Tracked(prep) => prep.finish(state, B::gather_rows(tensor, dim, indices)),
            OpsKind::UnTracked(prep) => prep.finish(B::gather_rows(tensor, dim, indices)),
        }
    }
}

impl<B: FusionBackend + RowGatherKernels> RowGatherKernels for Fusion<B> {
    fn scatter_add_rows(
        grad: FloatTensor<Self>,
        dim: usize,
        indices: IntTensor<Self>,
        rows: usize,
        dtype: DType,
    ) -> FloatTensor<Self> {
        let mut shape = grad.shape();
        shape[dim] = rows;
        let spec = Output::Float(TensorSpec::new(shape, dtype));
        let inputs = vec![Input::Float(grad), Input::Int(indices)];
        let [out] = array(deferred::<B, _>(
            "scatter_add_rows",
            inputs,
            vec![spec],
            move |v| {
                let [grad, indices] = array(v);
                vec![Value::Float(B::scatter_add_rows(
                    grad.float(),
                    dim,
                    indices.int(),
                    rows,
                    dtype,
                ))]
            },
        ));
        out
    }
}
