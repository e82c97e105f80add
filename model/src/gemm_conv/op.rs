//! The convolution as a Burn backend extension, and its autodiff node (see [`super`]).
//!
//! Listed for `Cube`, `Fusion` and `Autodiff`. The forward (the `cube` module) is the patch
//! columns, one product, and a view of its `[N, H_out, W_out, C_out]` rows as Burn's
//! `[N, C_out, H_out, W_out]`; Burn's fusion runs it as one op. The autodiff node keeps the
//! input and the weight, and the columns only when they are small ([`KEPT_COLUMNS_BYTES`]):
//! larger ones are rebuilt in the backward, one memory-bound launch, rather than held from the
//! forward to the backward for every layer (0.5 GB for the stem at the paper's setting); small
//! ones cost less to keep than a launch to rebuild.

use std::cell::Cell;

use burn::backend::autodiff::checkpoint::base::Checkpointer;
use burn::backend::autodiff::checkpoint::strategy::CheckpointStrategy;
use burn::backend::autodiff::grads::Gradients;
use burn::backend::autodiff::ops::{Backward, Ops, OpsKind};
use burn::backend::fusion::{Fusion, FusionBackend};
use burn::backend::tensor::FloatTensor;
use burn::backend::{Autodiff, Backend, TensorMetadata, backend_extension};
use burn::tensor::Shape;
use lifegom_render::cube::deferred::{Input, Value, array, deferred, float_like};

use crate::split_k::SplitK;

/// A convolution's window: kernel size, stride and symmetric zero padding, per axis `[y, x]`
/// (dilation 1, one group).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Patches {
    /// `[kh, kw]`.
    pub kernel: [usize; 2],
    /// `[sy, sx]`, each at least 1.
    pub stride: [usize; 2],
    /// `[py, px]` zeros on both sides of each axis.
    pub padding: [usize; 2],
}

impl Patches {
    /// Whether the window fits the padded input `[H, W]` (an output of at least one pixel).
    pub fn fits(&self, height: usize, width: usize) -> bool {
        height + 2 * self.padding[0] >= self.kernel[0]
            && width + 2 * self.padding[1] >= self.kernel[1]
    }

    /// `[H_out, W_out]` for an input of `[H, W]` the window [fits](Self::fits).
    pub fn output_size(&self, height: usize, width: usize) -> [usize; 2] {
        let out = |size: usize, axis: usize| {
            (size + 2 * self.padding[axis]).saturating_sub(self.kernel[axis]) / self.stride[axis]
                + 1
        };
        [out(height, 0), out(width, 1)]
    }

    /// The convolution's output `[N, C_out, H_out, W_out]` for `x` `[N, C, H, W]` and `weight`
    /// `[C_out, C, kh, kw]`.
    pub fn output_shape(&self, x: &Shape, weight: &Shape) -> Shape {
        let [h, w] = self.output_size(x[2], x[3]);
        Shape::new([x[0], weight[0], h, w])
    }

    /// The patch columns `[N·H_out·W_out, C·kh·kw]` of `x` `[N, C, H, W]` (module docs of
    /// [`super`]).
    pub fn columns_shape(&self, x: &Shape) -> Shape {
        let [h, w] = self.output_size(x[2], x[3]);
        Shape::new([x[0] * h * w, x[1] * self.kernel[0] * self.kernel[1]])
    }
}

/// `conv2d(x, weight)` without bias, as a product of patch columns and the weight (see
/// [`super`]). `x` `[N, C, H, W]`, `weight` `[C_out, C, kh, kw]`; output
/// `[N, C_out, H_out, W_out]`. Callers check shapes ([`super::conv2d`]).
#[backend_extension(Cube, Fusion, Autodiff)]
pub trait GemmConvOps: Backend {
    /// The convolution.
    #[fusion(dtype = x, shape = patches.output_shape(x, weight))]
    fn gemm_conv2d(
        x: FloatTensor<Self>,
        weight: FloatTensor<Self>,
        patches: Patches,
    ) -> FloatTensor<Self>;
}

/// What a backend implements so that the op and its autodiff node can run on it.
#[doc(hidden)]
pub trait PatchKernels: Backend {
    /// The patch columns of `x` `[N, C, H, W]`: row `(n, y, x)` of the output grid, column
    /// `(c, ky, kx)` of the window, zero where the window reads the padding
    /// ([`Patches::columns_shape`]).
    fn patch_columns(x: FloatTensor<Self>, patches: Patches) -> FloatTensor<Self>;

    /// The gradient of an input of shape `input` given its columns' gradient: each input
    /// element's sum over the columns that read it (a gather, one thread per input element).
    fn patch_columns_backward(
        columns_grad: FloatTensor<Self>,
        input: Shape,
        patches: Patches,
    ) -> FloatTensor<Self>;
}

/// The largest patch columns an autodiff node keeps from the forward for its weight gradient
/// (module docs): every layer of the quickstart's encoder, none of the paper setting's first
/// stages.
pub const KEPT_COLUMNS_BYTES: usize = 16 << 20;

thread_local! {
    /// [`keep_columns_up_to`]'s choice on this thread.
    static KEPT_BYTES: Cell<usize> = const { Cell::new(KEPT_COLUMNS_BYTES) };
}

/// Sets the largest patch columns that convolutions run on the calling thread keep for their
/// backward ([`KEPT_COLUMNS_BYTES`] by default; 0 rebuilds every layer's). For tests.
pub fn keep_columns_up_to(bytes: usize) {
    KEPT_BYTES.with(|kept| kept.set(bytes));
}

/// The convolution's output `out` (`[N, C_out, H_out, W_out]`) from its patch columns and
/// `weight` `[C_out, C, kh, kw]`: one product, whose `[N·H_out·W_out, C_out]` rows are viewed
/// as NCHW (see [`super`]).
pub(crate) fn columns_product<B: Backend>(
    columns: FloatTensor<B>,
    weight: FloatTensor<B>,
    out: Shape,
) -> FloatTensor<B> {
    let [n, c_out, h, w] = [out[0], out[1], out[2], out[3]];
    let width = columns.shape()[1];
    let weight = B::float_reshape(weight, Shape::new([c_out, width]));
    let rows = B::float_matmul(columns, B::float_transpose(weight));
    let nhwc = B::float_reshape(rows, Shape::new([n, h, w, c_out]));
    // Channels-last in memory, as Burn's own convolutions answer: the next ops (the encoder's
    // norms) read any layout, and a copy to row-major order would be a launch per layer.
    B::float_permute(nhwc, &[0, 3, 1, 2])
}

/// The node's state: the op's inputs, and the patch columns when kept (module docs).
#[derive(Debug, Clone)]
pub struct ConvInputs<B: Backend> {
    x: FloatTensor<B>,
    weight: FloatTensor<B>,
    patches: Patches,
    columns: Option<FloatTensor<B>>,
}

#[derive(Debug)]
struct ConvBackward;

impl<B: PatchKernels> Backward<B, 2> for ConvBackward {
    type State = ConvInputs<B>;

    fn backward(
        self,
        ops: Ops<Self::State, 2>,
        grads: &mut Gradients,
        _checkpointer: &mut Checkpointer,
    ) {
        let grad = grads.consume::<B>(&ops.node);
        let [x_parent, weight_parent] = ops.parents;
        let ConvInputs {
            x,
            weight,
            patches,
            columns,
        } = ops.state;
        let weight_shape = weight.shape();
        let c_out = weight_shape[0];
        let x_shape = x.shape();
        let rows = patches.columns_shape(&x_shape)[0];
        // `∂y` as rows `(n, y, x)` of `C_out` columns, the layout of the forward's product.
        let grad_rows = B::float_reshape(
            B::float_permute(grad, &[0, 2, 3, 1]),
            Shape::new([rows, c_out]),
        );
        let weight_rows = B::float_reshape(
            weight,
            Shape::new([c_out, weight_shape.num_elements() / c_out.max(1)]),
        );
        if let Some(parent) = weight_parent {
            let columns = columns.unwrap_or_else(|| B::patch_columns(x, patches));
            let width = columns.shape()[1];
            let split = SplitK::plan_exact(rows, width, c_out);
            // `∂Wᵀ = columnsᵀ·∂y` `[C·kh·kw, C_out]`.
            let dw = split.weight_gradient::<B>(columns, grad_rows.clone());
            let dw = B::float_reshape(B::float_transpose(dw), weight_shape);
            grads.register::<B>(parent.id, dw);
        }
        if let Some(parent) = x_parent {
            let columns_grad = B::float_matmul(grad_rows, weight_rows);
            grads.register::<B>(
                parent.id,
                B::patch_columns_backward(columns_grad, x_shape, patches),
            );
        }
    }
}

impl<B: GemmConvOps + PatchKernels, C: CheckpointStrategy> GemmConvOps for Autodiff<B, C> {
    fn gemm_conv2d(
        x: FloatTensor<Self>,
        weight: FloatTensor<Self>,
        patches: Patches,
    ) -> FloatTensor<Self> {
        let (x, x_node) = x.into_parts();
        let (weight, weight_node) = weight.into_parts();
        let inputs = ConvInputs::<B> {
            x,
            weight,
            patches,
            columns: None,
        };
        match ConvBackward
            .prepare::<C>([x_node, weight_node])
            .compute_bound()
            .stateful()
        {
            OpsKind::Tracked(prep) => {
                let x_shape = inputs.x.shape();
                let columns_bytes =
                    patches.columns_shape(&x_shape).num_elements() * size_of::<f32>();
                if columns_bytes > KEPT_BYTES.with(Cell::get) {
                    let out = B::gemm_conv2d(inputs.x.clone(), inputs.weight.clone(), patches);
                    return prep.finish(inputs, out);
                }
                let out_shape = patches.output_shape(&x_shape, &inputs.weight.shape());
                let columns = B::patch_columns(inputs.x.clone(), patches);
                let out = columns_product::<B>(columns.clone(), inputs.weight.clone(), out_shape);
                let columns = Some(columns);
                prep.finish(ConvInputs { columns, ..inputs }, out)
            }
            OpsKind::UnTracked(prep) => {
                prep.finish(B::gemm_conv2d(inputs.x, inputs.weight, patches))
            }
        }
    }
}

impl<B: FusionBackend + PatchKernels> PatchKernels for Fusion<B> {
    fn patch_columns(x: FloatTensor<Self>, patches: Patches) -> FloatTensor<Self> {
        let spec = float_like::<B>(&x, patches.columns_shape(&x.shape()));
        let [columns] = array(deferred::<B, _>(
            "patch_columns",
            vec![Input::Float(x)],
            vec![spec],
            move |v| {
                let [x] = array(v);
                vec![Value::Float(B::patch_columns(x.float(), patches))]
            },
        ));
        columns
    }

    fn patch_columns_backward(
        columns_grad: FloatTensor<Self>,
        input: Shape,
        patches: Patches,
    ) -> FloatTensor<Self> {
        let spec = float_like::<B>(&columns_grad, input.clone());
        let [dx] = array(deferred::<B, _>(
            "patch_columns_backward",
            vec![Input::Float(columns_grad)],
            vec![spec],
            move |v| {
                let [g] = array(v);
                vec![Value::Float(B::patch_columns_backward(
                    g.float(),
                    input.clone(),
                    patches,
                ))]
            },
        ));
        dx
    }
}
