//! Image tensors `[N, C, H, W]` read in the layout they come in.
//!
//! Burn's convolutions, and the image encoder's own (`lifegom_ops::gemm_conv`), answer an NCHW
//! view of channels-last memory; the ops after them (BatchNorm, the next convolution's patch
//! columns) would each copy such an image to row-major order before a kernel that indexes flat
//! buffers could read it: a launch per layer and pass, each way. A kernel that takes an
//! [`ImageLayout`] reads any layout whose strides are a permutation of a contiguous one
//! ([`dense`]) at the offset [`ImageLayout::at`] gives, so the image is handed over as it is.

use burn::backend::TensorMetadata;
use burn::backend::tensor::FloatTensor;
use burn::tensor::DType;
use burn_cubecl::CubeBackend;
use burn_cubecl::tensor::CubeTensor;

use super::host::prepare;

pub use layout::{ImageLayout, ImageLayoutLaunch};

// The derives add undocumented launch and expansion twins of the record.
#[allow(missing_docs)]
mod layout {
    use burn_cubecl::cubecl;
    use burn_cubecl::cubecl::prelude::*;

    /// Where element `(n, c, y, x)` of an image tensor is: its strides along each axis.
    #[derive(CubeType, CubeLaunch)]
    pub struct ImageLayout {
        /// Stride of the image axis.
        pub n: usize,
        /// Stride of the channel axis.
        pub c: usize,
        /// Stride of the row axis.
        pub h: usize,
        /// Stride of the column axis.
        pub w: usize,
    }

    #[cube]
    impl ImageLayout {
        /// The offset of image `n`, channel `c`, row `y`, column `x`.
        pub fn at(&self, n: usize, c: usize, y: usize, x: usize) -> usize {
            n * self.n + c * self.c + y * self.h + x * self.w
        }

        /// The offset of image `n`, channel `c` and pixel `pixel` (row-major over a `width`-wide
        /// image).
        pub fn at_pixel(&self, n: usize, c: usize, pixel: usize, width: usize) -> usize {
            n * self.n + c * self.c + (pixel / width) * self.h + (pixel % width) * self.w
        }
    }
}

/// `t` as it is when it is `f32` and its layout a permutation of a contiguous one over a buffer
/// of its own, else a row-major copy ([`prepare`]): either way every element of the buffer is
/// one element of the tensor, and [`image_layout`] says which.
pub fn dense(t: FloatTensor<CubeBackend>) -> CubeTensor {
    let shape = t.meta.shape().to_vec();
    let strides = t.meta.strides().to_vec();
    let mut axes: Vec<usize> = (0..shape.len()).filter(|&a| shape[a] > 1).collect();
    axes.sort_by_key(|&a| strides[a]);
    let mut expected = 1;
    let permuted = axes.iter().all(|&a| {
        let ok = strides[a] == expected;
        expected *= shape[a];
        ok
    });
    if permuted && t.dtype() == DType::F32 && t.is_contiguous_buffer() {
        t
    } else {
        prepare(t)
    }
}

/// The strides of a 4-D `t` as the kernels' [`ImageLayout`].
///
/// # Panics
///
/// If `t` is not 4-D.
pub fn image_layout(t: &CubeTensor) -> ImageLayoutLaunch {
    let s = t.meta.strides();
    assert_eq!(s.len(), 4, "an image tensor is [N, C, H, W]");
    ImageLayoutLaunch::new(s[0], s[1], s[2], s[3])
}
