//! The image encoder's convolution and the BatchNorm after it as one shared layer on CubeCL
//! devices (design.md §7.1).
//!
//! A convolution without bias is a product of its patch columns and its weight
//! ([`crate::gemm_conv`]), and a BatchNorm on its running statistics is a per-channel affine map
//! `x·s + t`: together, one product with a folded weight and bias,
//!
//! ```text
//! BN(conv(x)) = columns(x)·(Wᵀ·diag(s)) + (β − μ·s)        s = γ/√(σ²+ε)
//! ```
//!
//! [`ConvNorm`] runs it so, with the ReLU after it, or a residual block's `relu(· + shortcut)`,
//! in one launch per pass: the product reads the patch columns from the image where it stages
//! them (an implicit-GEMM convolution), so they are never written forward, where the convolution
//! and the norm as two ops took a launch for the columns, one for the product and one for the
//! norm, and the block's sum a fourth. The fold is a [`SharedLinear`] made once per
//! reconstruction and used by every encoder pass; `γ` and `β` train, so its backward turns the
//! passes' unscaled weight gradient into `∂W`, `∂γ` and `∂β` in one launch
//! ([`crate::shared_linear::op::SharedLinearOps::trained_fold`]). The weight gradient's kernel
//! reads the passes' patch columns from their images too, so the columns are never written; the
//! product node keeps the image, not the columns (`C·kh·kw` floats per output pixel: 0.5 GB for
//! the stem at the paper's setting).
//!
//! The CPU backends never use it, nor CubeCL devices running Burn's direct convolution
//! (`LIFEGOM_CONV=direct`, [`crate::gemm_conv::ConvKernel`]).

use burn::nn::BatchNorm;
use burn::nn::conv::Conv2d;
use burn::tensor::{Device, Tensor};

use crate::activation::Activation;
use crate::gemm_conv::op::Patches;
use crate::shared_linear::SharedLinear;

/// One convolution and its BatchNorm as a shared layer (module docs). Make one per layer and
/// reconstruction, and use it for every pass.
#[derive(Debug, Clone)]
pub struct ConvNorm {
    patches: Patches,
    layer: SharedLinear,
}

impl ConvNorm {
    /// The convolution `conv` (its window `patches`) and the BatchNorm `bn` after it, on
    /// `device` (a CubeCL device).
    ///
    /// # Panics
    ///
    /// On a CPU backend, or if the BN's width is not the convolution's output channels.
    pub fn new(conv: &Conv2d, bn: &BatchNorm, patches: Patches, device: &Device) -> Self {
        let [c_out, c_in, kh, kw] = conv.weight.dims();
        let weight = conv.weight.val().reshape([c_out, c_in * kh * kw]);
        Self {
            patches,
            layer: SharedLinear::trained_fold(weight, bn, device),
        }
    }

    /// `act(BN(conv(x)))` for `x` `[N, C, H, W]`: `[N, C_out, H_out, W_out]`, channels-last in
    /// memory as the convolutions answer.
    pub fn apply(&self, x: Tensor<4>, activation: Activation) -> Tensor<4> {
        let grid = self.grid(&x);
        let rows = self
            .layer
            .forward_patches(x, self.patches, None, activation);
        self.image(rows, grid)
    }

    /// `relu(BN(conv(x)) + shortcut)`, a residual block's end, with `shortcut` the output's
    /// shape.
    ///
    /// # Panics
    ///
    /// If `shortcut` is not the output's shape.
    pub fn apply_residual_relu(&self, x: Tensor<4>, shortcut: Tensor<4>) -> Tensor<4> {
        let grid = self.grid(&x);
        let [n, c, h, w] = shortcut.dims();
        assert_eq!(
            [n, h, w],
            grid,
            "a shortcut has the convolution's output shape"
        );
        let residual = shortcut.permute([0, 2, 3, 1]).reshape([n * h * w, c]);
        let rows = self
            .layer
            .forward_patches(x, self.patches, Some(residual), Activation::Relu);
        self.image(rows, grid)
    }

    /// The output grid `[N, H_out, W_out]` for `x`.
    fn grid(&self, x: &Tensor<4>) -> [usize; 3] {
        let [n, _, h, w] = x.dims();
        let [h_out, w_out] = self.patches.output_size(h, w);
        [n, h_out, w_out]
    }

    /// The product's rows `[(n, y, x), C_out]` as the NCHW view of channels-last memory.
    fn image(&self, rows: Tensor<2>, [n, h, w]: [usize; 3]) -> Tensor<4> {
        let c = rows.dims()[1];
        rows.reshape([n, h, w, c]).permute([0, 3, 1, 2])
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::module::{Param, RunningState};
    use burn::nn::conv::Conv2dConfig;
    use burn::nn::{BatchNormConfig, PaddingConfig2d};
    use burn::tensor::TensorData;
    use lifegom_render::testing::{Rng, assert_close_to_scale, read, wgpu_test_device};

    use crate::split_k::force_split_k_rows;

    /// What follows the norm in a test.
    #[derive(Debug, Clone, Copy, PartialEq)]
    enum Ending {
        Plain(Activation),
        ResidualRelu,
    }

    /// `passes` passes of one convolution (`kernel`, `stride`, padding `kernel / 2`, 3 → 5
    /// channels) and its BatchNorm over different `[2, 3, h, w]` images (every other one
    /// channels-last in memory, as convolutions hand them on), each pass's loss weighing its
    /// output differently, on `device`: the outputs and the gradients of the images, the
    /// shortcuts (with a residual), the weight, `γ` and `β`. `composed` runs Burn's convolution
    /// and the tensor ops the CPU backends run.
    fn run(
        device: &Device,
        passes: usize,
        [kernel, stride]: [usize; 2],
        [h, w]: [usize; 2],
        ending: Ending,
        composed: bool,
    ) -> Vec<Vec<f32>> {
        let device = device.clone().autodiff();
        let (n, c_in, c) = (2, 3, 5);
        let mut rng = Rng::new(43);
        let mut draw = |len: usize, lo: f32, hi: f32| -> Vec<f32> {
            (0..len).map(|_| rng.range_f32(lo, hi)).collect()
        };
        let vector = |v: Vec<f32>| Tensor::<1>::from_data(TensorData::new(v, [c]), &device);
        let pad = kernel / 2;
        let mut conv = Conv2dConfig::new([c_in, c], [kernel, kernel])
            .with_stride([stride, stride])
            .with_padding(PaddingConfig2d::Explicit(pad, pad, pad, pad))
            .with_bias(false)
            .init(&device);
        conv.weight = Param::from_tensor(Tensor::from_data(
            TensorData::new(
                draw(c * c_in * kernel * kernel, -0.5, 0.5),
                [c, c_in, kernel, kernel],
            ),
            &device,
        ));
        let mut bn = BatchNormConfig::new(c).init(&device);
        bn.gamma = Param::from_tensor(vector(draw(c, -1.5, 1.5)));
        bn.beta = Param::from_tensor(vector(draw(c, -0.5, 0.5)));
        bn.running_mean = RunningState::new(vector(draw(c, -0.5, 0.5)));
        bn.running_var = RunningState::new(vector(draw(c, 0.2, 2.0)));
        let image = |values: Vec<f32>, [n, c, h, w]: [usize; 4], channels_last: bool| {
            let x = if channels_last {
                Tensor::<4>::from_data(TensorData::new(values, [n, h, w, c]), &device)
                    .permute([0, 3, 1, 2])
            } else {
                Tensor::from_data(TensorData::new(values, [n, c, h, w]), &device)
            };
            x.require_grad()
        };
        let images: Vec<Tensor<4>> = (0..passes)
            .map(|pass| {
                image(
                    draw(n * c_in * h * w, -1.0, 1.0),
                    [n, c_in, h, w],
                    pass % 2 == 1,
                )
            })
            .collect();
        let [h_out, w_out] = [(h - 1) / stride + 1, (w - 1) / stride + 1];
        let shortcuts: Vec<Tensor<4>> = (0..passes)
            .map(|pass| {
                let shape = [n, c, h_out, w_out];
                image(draw(n * c * h_out * w_out, -1.0, 1.0), shape, pass % 2 == 0)
            })
            .collect();
        let patches = crate::gemm_conv::op::Patches {
            kernel: [kernel; 2],
            stride: [stride; 2],
            padding: [pad; 2],
        };
        let layer = (!composed).then(|| ConvNorm::new(&conv, &bn, patches, &device));
        let mut loss = Tensor::<1>::zeros([1], &device);
        let mut outputs = Vec::new();
        for (pass, (x, shortcut)) in images.iter().zip(&shortcuts).enumerate() {
            let y = match (&layer, ending) {
                (Some(layer), Ending::Plain(activation)) => layer.apply(x.clone(), activation),
                (Some(layer), Ending::ResidualRelu) => {
                    layer.apply_residual_relu(x.clone(), shortcut.clone())
                }
                (None, ending) => {
                    let scale = bn.gamma.val() / (bn.running_var.value() + bn.epsilon).sqrt();
                    let shift = bn.beta.val() - bn.running_mean.value() * scale.clone();
                    let y = conv.forward(x.clone()) * scale.reshape([1, c, 1, 1])
                        + shift.reshape([1, c, 1, 1]);
                    match ending {
                        Ending::Plain(Activation::Identity) => y,
                        Ending::Plain(Activation::Relu) => crate::activation::relu(y),
                        Ending::ResidualRelu => crate::activation::relu(y + shortcut.clone()),
                    }
                }
            };
            assert_eq!(y.dims(), [n, c, h_out, w_out]);
            loss = loss + (y.clone() * (1.0 + pass as f32)).sin().sum();
            outputs.push(read(y));
        }
        let grads = loss.backward();
        let grad_of = |t: &Tensor<4>, what: &str| {
            read(
                t.grad(&grads)
                    .unwrap_or_else(|| panic!("{what}'s gradient")),
            )
        };
        outputs.extend(images.iter().map(|x| grad_of(x, "an image")));
        if ending == Ending::ResidualRelu {
            outputs.extend(shortcuts.iter().map(|r| grad_of(r, "a shortcut")));
        }
        outputs.push(grad_of(&conv.weight.val(), "the weight"));
        outputs.push(read(bn.gamma.val().grad(&grads).expect("γ's gradient")));
        outputs.push(read(bn.beta.val().grad(&grads).expect("β's gradient")));
        outputs
    }

    /// On lavapipe the shared product equals Burn's convolution and the tensor ops on Flex, for
    /// one pass, three (one gradient launch) and six (two), with every ending, a 3×3 window of
    /// stride 2 and a 1×1 of stride 1, the weight gradient's rows whole and in chunks of 16:
    /// outputs and the gradients of the images, the shortcuts, the weight, `γ` and `β`. Images
    /// of 9 × 11 pixels leave every edge of the windows and tiles uneven; at 8 × 12 an image's
    /// bytes fill its buffer, so a channels-last one reaches the kernels in its own layout (a
    /// smaller tensor than its buffer is copied to row-major order first,
    /// `lifegom_render::cube::image::dense`).
    #[test]
    fn conv_norm_matches_composition_wgpu() {
        let Some(device) = wgpu_test_device() else {
            return;
        };
        let endings = [
            Ending::Plain(Activation::Identity),
            Ending::Plain(Activation::Relu),
            Ending::ResidualRelu,
        ];
        for size in [[9, 11], [8, 12]] {
            for window in [[3, 2], [1, 1]] {
                for ending in endings {
                    for (passes, chunk_rows) in [(1, None), (3, Some(16)), (6, None)] {
                        let want = run(&Device::flex(), passes, window, size, ending, true);
                        force_split_k_rows(chunk_rows);
                        let got = run(&device, passes, window, size, ending, false);
                        force_split_k_rows(None);
                        assert_eq!(want.len(), got.len());
                        for (i, (a, b)) in got.iter().zip(&want).enumerate() {
                            let what = format!(
                                "{size:?} pixels, {window:?}, {ending:?}, {passes} passes, part {i}"
                            );
                            assert_close_to_scale(a, b, 1e-5, &what);
                        }
                    }
                }
            }
        }
    }
}
