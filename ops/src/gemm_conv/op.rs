//! The window of a convolution, and the gather of its patch columns' gradient as a backend
//! kernel for `Cube` and `Fusion` (see [`super`]).

use burn::backend::Backend;
use burn::backend::fusion::{Fusion, FusionBackend};
use burn::backend::tensor::FloatTensor;
use burn::tensor::Shape;
use lifegom_render::cube::deferred::{Input, Value, array, deferred, float_like};

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

    /// The patch columns `[N·H_out·W_out, C·kh·kw]` of `x` `[N, C, H, W]` (module docs of
    /// [`super`]).
    pub fn columns_shape(&self, x: &Shape) -> Shape {
        let [h, w] = self.output_size(x[2], x[3]);
        Shape::new([x[0] * h * w, x[1] * self.kernel[0] * self.kernel[1]])
    }
}

/// What a backend implements so that a convolution's product can hand its columns' gradient
/// back to the image (`crate::shared_linear`).
#[doc(hidden)]
pub trait PatchKernels: Backend {
    /// The gradient of an input of shape `input` given its columns' gradient: each input
    /// element's sum over the columns that read it (a gather, one thread per input element).
    fn patch_columns_backward(
        columns_grad: FloatTensor<Self>,
        input: Shape,
        patches: Patches,
    ) -> FloatTensor<Self>;
}

impl<B: FusionBackend + PatchKernels> PatchKernels for Fusion<B> {
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
