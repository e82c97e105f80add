//! The convolution as a Burn backend extension, and its autodiff node (see [`super`]).
//!
//! Listed for `Cube`, `Fusion` and `Autodiff`. The forward (the `cube` module) is the patch
//! columns, one product, and a view of its `[N, H_out, W_out, C_out]` rows as Burn's
//! `[N, C_out, H_out, W_out]`; Burn's fusion runs it as one op. The autodiff node keeps the
//! input and the weight (handles, not the columns: they are rebuilt in the backward, one
//! memory-bound launch, rather than held from the forward to the backward for every layer).

use burn::backend::autodiff::checkpoint::base::Checkpointer;
use burn::backend::autodiff::checkpoint::strategy::CheckpointStrategy;
use burn::backend::autodiff::grads::Gradients;
use burn::backend::autodiff::ops::{Backward, Ops};
use burn::backend::fusion::{Fusion, FusionBackend};
use burn::backend::tensor::FloatTensor;
use burn::backend::{Autodiff, Backend, TensorMetadata, backend_extension};
use burn::tensor::Shape;
use lifegom_render::cube::deferred::{Input, Value, array, deferred, float_like};
use lifegom_render::op_backward::record;

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

/// The node's state: the op's inputs.
#[derive(Debug, Clone)]
pub struct ConvInputs<B: Backend> {
    x: FloatTensor<B>,
    weight: FloatTensor<B>,
    patches: Patches,
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
        let ConvInputs { x, weight, patches } = ops.state;
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
            let columns = B::patch_columns(x, patches);
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
        record::<B, C, _, _, 2>(
            ConvBackward,
            [x_node, weight_node],
            ConvInputs { x, weight, patches },
            |s| B::gemm_conv2d(s.x, s.weight, s.patches),
        )
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
