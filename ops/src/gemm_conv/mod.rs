//! Convolutions as products on CubeCL devices (design.md §1.4, §7.1).
//!
//! Burn 0.22.1's CubeCL backend, without its `autotune` feature (which tunes for minutes per
//! process, BENCHMARKS.md "On a GPU (NVIDIA H200, 2026-11-27)"), runs every convolution with its
//! direct kernel: at the paper's setting the image encoder's ResNet-18 at 1024² took 530 of a
//! reconstruction's 1,147 ms of device time on an H200, where the same arithmetic as products
//! runs at 20 TFLOP/s. A convolution without bias is the product of its patch columns (im2col)
//! and its weight,
//!
//! ```text
//! columns[(n, y, x), (c, ky, kx)] = x[n, c, y·sy + ky − py, x·sx + kx − px]   (0 outside)
//! y[n, :, y, x] = W[C_out, C·kh·kw] · columns[(n, y, x), :]ᵀ
//! ```
//!
//! whose `[N·H_out·W_out, C_out]` rows are the output channels-last. The encoder runs each
//! convolution and the BatchNorm after it as one shared product that reads the columns from the
//! image where it stages them, forward and for the weight gradient ([`crate::conv_norm`]): this
//! module holds the window ([`op::Patches`]), the column arithmetic those kernels share
//! (`cube::patch_value`), and the backward's gather of the columns' gradient onto the input
//! ([`op::PatchKernels::patch_columns_backward`]: each input element sums the column entries
//! that read it). Until b406b80 (2026-11-28) the convolution was an op of its own here, the
//! columns written by one launch and multiplied by Burn's matmul.
//!
//! The CPU backends, layers with a bias, groups or dilation, and CubeCL devices with
//! `LIFEGOM_CONV=direct` ([`ConvKernel`], for benchmarks to compare against) keep Burn's
//! `Conv2d::forward`.

pub(crate) mod cube;
pub mod op;

use burn::nn::PaddingConfig2d;
use burn::nn::conv::Conv2d;
use std::sync::OnceLock;

use burn::tensor::{Device, Tensor};
use lifegom_render::device::{env_switch, runs_on_host};

use op::Patches;

/// Which kernels run the convolutions on CubeCL devices.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ConvKernel {
    /// Patch columns and one product (the default; [`crate::conv_norm`]).
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

/// The window of `layer` when this device runs it as patch columns and a product
/// ([`ConvKernel::Gemm`] on a CubeCL device) and the window fits `x`: where the encoder runs the
/// layer and its BatchNorm as one shared product ([`crate::conv_norm`]).
pub fn gemm_patches(layer: &Conv2d, x: &Tensor<4>) -> Option<Patches> {
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

#[cfg(test)]
mod tests {
    use super::*;
    use burn::nn::conv::Conv2dConfig;

    /// The window of a layer the products can run, and none for one they cannot: a bias,
    /// groups, dilation or lopsided padding; on the CPU backends no layer runs as products.
    #[test]
    fn windows_of_layers() {
        let device = Device::flex();
        let conv = |config: Conv2dConfig| config.with_bias(false).init(&device);
        let stem = conv(
            Conv2dConfig::new([3, 8], [7, 7])
                .with_stride([2, 2])
                .with_padding(PaddingConfig2d::Explicit(3, 3, 3, 3)),
        );
        assert_eq!(
            patches(&stem),
            Some(Patches {
                kernel: [7, 7],
                stride: [2, 2],
                padding: [3, 3],
            })
        );
        let valid = conv(Conv2dConfig::new([3, 8], [1, 1]));
        assert_eq!(patches(&valid).map(|p| p.padding), Some([0, 0]));
        let biased = Conv2dConfig::new([3, 8], [3, 3]).init(&device);
        assert_eq!(patches(&biased), None);
        let lopsided = conv(
            Conv2dConfig::new([3, 8], [3, 3]).with_padding(PaddingConfig2d::Explicit(1, 1, 0, 0)),
        );
        assert_eq!(patches(&lopsided), None);
        let grouped = conv(Conv2dConfig::new([4, 8], [3, 3]).with_groups(2));
        assert_eq!(patches(&grouped), None);
        let dilated = conv(Conv2dConfig::new([3, 8], [3, 3]).with_dilation([2, 2]));
        assert_eq!(patches(&dilated), None);
        let x = Tensor::<4>::zeros([1, 3, 16, 16], &device);
        assert_eq!(
            gemm_patches(&stem, &x),
            None,
            "the CPU backends run Burn's convolution"
        );
        assert_eq!(stem.weight.dims(), [8, 3, 7, 7]);
    }
}
