//! Convolutions as one matrix product on CubeCL devices (design.md §1.4).
//!
//! Burn 0.22.1's CubeCL backend, without its `autotune` feature (which tunes for minutes per
//! process, BENCHMARKS.md session 19), runs every convolution with its direct kernel: at the
//! paper's setting the image encoder's ResNet-18 at 1024² took 530 of a reconstruction's
//! 1,147 ms of device time on an H200, where the same arithmetic as products runs at
//! 20 TFLOP/s. [`conv2d`] computes a convolution without bias as
//!
//! ```text
//! columns[(n, y, x), (c, ky, kx)] = x[n, c, y·sy + ky − py, x·sx + kx − px]   (0 outside)
//! y[n, :, y, x] = W[C_out, C·kh·kw] · columns[(n, y, x), :]ᵀ
//! ```
//!
//! the patch columns (im2col) in one launch and one product, whose `[N·H_out·W_out, C_out]`
//! rows are the output channels-last: an NCHW view of them is the result, as Burn's own
//! convolutions answer (the `op` and `cube` modules). Its backward is `∂columns = ∂y·W`, gathered back onto the input in one
//! launch (each input element sums the column entries that read it), and
//! `∂W = ∂yᵀ·columns`, a product over every output pixel: split-k ([`crate::split_k`]), in
//! chunks that divide the pixels. The columns take `C·kh·kw` floats per output pixel (at most
//! 0.5 GB for the stem at 1024² and three views), so the autodiff node keeps the input and
//! rebuilds them in the backward.
//!
//! The CPU backends, and layers with a bias, groups or dilation, keep Burn's `Conv2d::forward`,
//! which is also what the op is tested against; so do CubeCL devices with
//! `LIFEGOM_CONV=direct` ([`ConvKernel`]), for benchmarks to compare against.

pub(crate) mod cube;
pub mod op;

use burn::nn::PaddingConfig2d;
use burn::nn::conv::Conv2d;
use std::sync::OnceLock;

use burn::tensor::{Device, Tensor};
use lifegom_render::device::{env_switch, runs_on_host};

use op::{GemmConvOps, Patches};

/// Which kernels run the convolutions on CubeCL devices.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ConvKernel {
    /// Patch columns and one product ([`conv2d`]; the default).
    Gemm,
    /// Burn's direct convolution (`LIFEGOM_CONV=direct`).
    Direct,
}

impl ConvKernel {
    /// This process's choice, read from `LIFEGOM_CONV` once: `direct` for Burn's kernel, else
    /// the product (an unknown value says so on stderr).
    pub fn current() -> Self {
        static KERNEL: OnceLock<ConvKernel> = OnceLock::new();
        *KERNEL.get_or_init(|| {
            env_switch(
                "LIFEGOM_CONV",
                ("gemm", ConvKernel::Gemm),
                ("direct", ConvKernel::Direct),
            )
        })
    }

    /// What `device` runs with: this process's choice on CubeCL devices, `None` on the host
    /// backends (always Burn's convolution).
    pub fn on_device(device: &Device) -> Option<Self> {
        (!runs_on_host(device)).then(Self::current)
    }

    /// The name printed in benchmark JSON (`conv_kernel` field).
    pub fn name(self) -> &'static str {
        match self {
            ConvKernel::Gemm => "gemm",
            ConvKernel::Direct => "direct",
        }
    }
}

/// `layer` applied to `x` `[N, C, H, W]`: as patch columns and one product on CubeCL devices
/// when the layer has no bias, one group, no dilation and symmetric padding (module docs), else
/// Burn's `Conv2d::forward`.
pub fn conv2d(layer: &Conv2d, x: Tensor<4>) -> Tensor<4> {
    match patches(layer) {
        Some(patches)
            if ConvKernel::on_device(&x.device()) == Some(ConvKernel::Gemm)
                && patches.fits(x.dims()[2], x.dims()[3]) =>
        {
            gemm_conv2d(x, layer.weight.val(), patches)
        }
        // Burn's convolution answers (or refuses) a window wider than the padded input.
        _ => layer.forward(x),
    }
}

/// The window of `layer` when this device runs it as patch columns and a product
/// ([`ConvKernel::Gemm`] on a CubeCL device) and the window fits `x`: where the encoder runs the
/// layer and its BatchNorm as one shared product ([`crate::conv_norm`]).
pub(crate) fn gemm_patches(layer: &Conv2d, x: &Tensor<4>) -> Option<Patches> {
    let patches = patches(layer)?;
    let dims = x.dims();
    (ConvKernel::on_device(&x.device()) == Some(ConvKernel::Gemm) && patches.fits(dims[2], dims[3]))
        .then_some(patches)
}

/// The layer's window when the op can run it.
fn patches(layer: &Conv2d) -> Option<Patches> {
    if layer.bias.is_some() || layer.groups != 1 || layer.dilation != [1, 1] {
        return None;
    }
    let padding = match layer.padding {
        PaddingConfig2d::Valid => [0, 0],
        PaddingConfig2d::Explicit(top, left, bottom, right) if top == bottom && left == right => {
            [top, left]
        }
        _ => return None,
    };
    Some(Patches {
        kernel: layer.kernel_size,
        stride: layer.stride,
        padding,
    })
}

/// The op on any device (the CPU backends do not implement it).
fn gemm_conv2d(x: Tensor<4>, weight: Tensor<4>, patches: Patches) -> Tensor<4> {
    Tensor::from_dispatch(<burn::backend::Dispatch as GemmConvOps>::gemm_conv2d(
        x.into_dispatch(),
        weight.into_dispatch(),
        patches,
    ))
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::nn::conv::Conv2dConfig;
    use burn::tensor::TensorData;
    use lifegom_render::device::DeviceChoice;
    use lifegom_render::testing::{Rng, assert_close_to_scale, read, wgpu_test_device};

    use crate::split_k::force_split_k_rows;

    /// How a test input is laid out in memory.
    #[derive(Debug, Clone, Copy, PartialEq, Eq)]
    enum Memory {
        RowMajor,
        /// An NCHW view of NHWC memory, as a convolution hands its output on.
        ChannelsLast,
    }

    /// `(output, ∂x, ∂W)` of `Σ y·r` for a fixed `r`, with `conv2d` (`ours`) or Burn's conv.
    fn run(
        device: &Device,
        (kernel, stride, pad): (usize, usize, usize),
        [n, c, h, w]: [usize; 4],
        c_out: usize,
        memory: Memory,
        ours: bool,
    ) -> [Vec<f32>; 3] {
        let ad = device.clone().autodiff();
        let mut rng = Rng::new(11);
        let mut draw =
            |len: usize| -> Vec<f32> { (0..len).map(|_| rng.range_f32(-1.0, 1.0)).collect() };
        let mut layer = Conv2dConfig::new([c, c_out], [kernel, kernel])
            .with_stride([stride, stride])
            .with_padding(PaddingConfig2d::Explicit(pad, pad, pad, pad))
            .with_bias(false)
            .init(&ad);
        let weight = Tensor::<4>::from_data(
            TensorData::new(
                draw(c_out * c * kernel * kernel),
                [c_out, c, kernel, kernel],
            ),
            &ad,
        )
        .require_grad();
        layer.weight = burn::module::Param::from_tensor(weight.clone());
        let values = draw(n * c * h * w);
        // Channels-last in memory, as the previous layer hands its output on, or row-major.
        let x = if memory == Memory::ChannelsLast {
            Tensor::<4>::from_data(TensorData::new(values, [n, h, w, c]), &ad).permute([0, 3, 1, 2])
        } else {
            Tensor::<4>::from_data(TensorData::new(values, [n, c, h, w]), &ad)
        }
        .require_grad();
        let y = if ours && !runs_on_host(device) {
            // The op itself, whatever `LIFEGOM_CONV` says.
            gemm_conv2d(
                x.clone(),
                layer.weight.val(),
                patches(&layer).expect("a window"),
            )
        } else if ours {
            conv2d(&layer, x.clone())
        } else {
            layer.forward(x.clone())
        };
        let r = Tensor::<4>::from_data(
            TensorData::new(draw(y.dims().iter().product()), y.dims()),
            &ad,
        );
        let grads = (y.clone() * r).sum().backward();
        [
            read(y),
            read(x.grad(&grads).expect("an input gradient")),
            read(weight.grad(&grads).expect("a weight gradient")),
        ]
    }

    /// On lavapipe the op's output and both gradients equal Burn's convolution on Flex within
    /// float summation order, for the encoder's windows (the 7×7 stride-2 stem, 3×3 with
    /// stride 1 and 2, the 1×1 stride-2 shortcut) on odd, non-square inputs whose windows
    /// leave pixels unread, on inputs smaller than the window (most taps read padding: the
    /// late stages of a small image), with the weight gradient as one product and split-k
    /// (chunks forced to 8 rows: the exact divisor rule's chunks), on row-major inputs and on
    /// channels-last ones (how a layer's output reaches the next: read in place), with the
    /// patch columns kept from the forward and rebuilt in the backward.
    #[test]
    fn conv2d_matches_burn_wgpu() {
        let Some(device) = wgpu_test_device() else {
            return;
        };
        let flex = DeviceChoice::Flex.device();
        let windows = [(7, 2, 3), (3, 1, 1), (3, 2, 1), (1, 2, 0)];
        let cases = windows
            .iter()
            .flat_map(|&window| [(window, [2, 3, 13, 10]), (window, [1, 2, 3, 2])])
            // A 1×1 image: every tap but the centre reads padding.
            .chain([((3, 1, 1), [1, 4, 1, 1])]);
        for ((kernel, stride, pad), shape) in cases {
            let window = (kernel, stride, pad);
            for (split, memory, kept) in [
                (Some(0), Memory::RowMajor, op::KEPT_COLUMNS_BYTES),
                (Some(8), Memory::RowMajor, op::KEPT_COLUMNS_BYTES),
                (Some(8), Memory::ChannelsLast, op::KEPT_COLUMNS_BYTES),
                (Some(0), Memory::ChannelsLast, 0),
                (Some(8), Memory::RowMajor, 0),
            ] {
                let want = run(&flex, window, shape, 5, memory, false);
                force_split_k_rows(split);
                op::keep_columns_up_to(kept);
                let got = run(&device, window, shape, 5, memory, true);
                op::keep_columns_up_to(op::KEPT_COLUMNS_BYTES);
                force_split_k_rows(None);
                for (i, what) in ["output", "∂x", "∂W"].iter().enumerate() {
                    let what = format!(
                        "{kernel}×{kernel} /{stride} pad {pad} on {shape:?}, split {split:?}, \
                         {memory:?}, columns kept up to {kept} B: {what}"
                    );
                    assert_close_to_scale(&got[i], &want[i], 2e-5, &what);
                    assert!(got[i].iter().all(|v| v.is_finite()), "{what}: finite");
                }
            }
        }
    }

    /// On the CPU backends [`conv2d`] is Burn's convolution, to the bit.
    #[test]
    fn host_conv_is_burns() {
        for choice in DeviceChoice::CPU {
            let device = choice.device();
            let a = run(&device, (3, 2, 1), [1, 2, 7, 6], 3, Memory::RowMajor, true);
            let b = run(&device, (3, 2, 1), [1, 2, 7, 6], 3, Memory::RowMajor, false);
            assert_eq!(a, b, "{choice:?}");
        }
    }
}
