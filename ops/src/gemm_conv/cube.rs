//! The patch columns' arithmetic on Burn's CubeCL backend (see [`super`]).
//!
//! [`patch_value`] is element `(row, col)` of the columns, read from the image in the layout it
//! comes in ([`lifegom_render::cube::image`]: the previous layer's output is a channels-last
//! view, which a row-major copy would cost a launch per layer and pass); the shared layers'
//! product and gradient kernels call it where they stage their operands. The backward gathers
//! the columns' gradient onto the image: one thread per input element visits the `kh·kw` window
//! positions that could cover it and adds the column gradient of each output position whose
//! window does (`y + py − ky` a multiple of the stride and inside the output), so no two
//! threads write one element and no atomics are needed. It writes the image's gradient
//! channels-last, as the products write their outputs, so that the previous layer's backward
//! product reads it as rows without a copy.

use burn::backend::TensorMetadata;
use burn::backend::ops::FloatTensorOps;
use burn::backend::tensor::FloatTensor;
use burn::tensor::Shape;
use burn_cubecl::CubeBackend;
use burn_cubecl::cubecl;
use burn_cubecl::cubecl::prelude::*;
use lifegom_render::cube::host::{
    THREADS_1D, arg, cast_to, count_1d, prepare, tensor_arg, tensor_f32,
};
use lifegom_render::cube::image::ImageLayout;

use super::op::{PatchKernels, Patches};

/// The window and grid of one call, as the kernels read them (also the shared layers' product
/// when it reads its rows as patches, `crate::shared_linear`).
#[derive(CubeLaunch, CubeType)]
pub(crate) struct Grid {
    channels: usize,
    height: usize,
    width: usize,
    out_height: usize,
    out_width: usize,
    kernel_y: usize,
    kernel_x: usize,
    stride_y: usize,
    stride_x: usize,
    pad_y: usize,
    pad_x: usize,
}

/// Element `(row, col)` of the patch columns of `x`: output pixel `row = (n, y, x)`, window entry
/// `col = (c, ky, kx)`, zero where the window reads the padding.
#[cube]
pub(crate) fn patch_value(
    x: &[f32],
    x_layout: &ImageLayout,
    grid: &Grid,
    row: usize,
    col: usize,
) -> f32 {
    let window = grid.kernel_y * grid.kernel_x;
    let plane = grid.out_height * grid.out_width;
    let n = row / plane;
    let p = row % plane;
    let c = col / window;
    let k = col % window;
    // Padded coordinates: the window's pixel is inside the image when both lie in
    // `[pad, pad + size)`.
    let y = (p / grid.out_width) * grid.stride_y + k / grid.kernel_x;
    let x_ = (p % grid.out_width) * grid.stride_x + k % grid.kernel_x;
    let mut value = 0.0f32;
    if y >= grid.pad_y
        && y < grid.pad_y + grid.height
        && x_ >= grid.pad_x
        && x_ < grid.pad_x + grid.width
    {
        value = x[x_layout.at(n, c, y - grid.pad_y, x_ - grid.pad_x)];
    }
    value
}

// `%` rather than `is_multiple_of`, which CubeCL's kernel language does not have.
#[allow(clippy::manual_is_multiple_of)]
#[cube(launch)]
fn patch_columns_backward_kernel(columns_grad: &[f32], dx: &mut [f32], grid: Grid, units: usize) {
    let e = ABSOLUTE_POS;
    if e < units {
        let window = grid.kernel_y * grid.kernel_x;
        let width = grid.channels * window;
        // `∂x` is written channels-last, `e = ((n·H + y)·W + x)·C + c`.
        let c = e % grid.channels;
        let pixel = e / grid.channels;
        let n = pixel / (grid.height * grid.width);
        // Padded coordinates of this input element.
        let y = (pixel / grid.width) % grid.height + grid.pad_y;
        let x_ = pixel % grid.width + grid.pad_x;
        let mut sum = 0.0f32;
        for ky in 0..grid.kernel_y {
            if y >= ky && (y - ky) % grid.stride_y == 0 {
                let oy = (y - ky) / grid.stride_y;
                if oy < grid.out_height {
                    for kx in 0..grid.kernel_x {
                        if x_ >= kx && (x_ - kx) % grid.stride_x == 0 {
                            let ox = (x_ - kx) / grid.stride_x;
                            if ox < grid.out_width {
                                let row = (n * grid.out_height + oy) * grid.out_width + ox;
                                sum += columns_grad
                                    [row * width + c * window + ky * grid.kernel_x + kx];
                            }
                        }
                    }
                }
            }
        }
        dx[e] = sum;
    }
}

/// The kernels' [`Grid`] for an input of shape `input`.
pub(crate) fn grid_arg(input: &Shape, patches: Patches) -> GridLaunch {
    let [out_height, out_width] = patches.output_size(input[2], input[3]);
    GridLaunch::new(
        input[1],
        input[2],
        input[3],
        out_height,
        out_width,
        patches.kernel[0],
        patches.kernel[1],
        patches.stride[0],
        patches.stride[1],
        patches.padding[0],
        patches.padding[1],
    )
}

impl PatchKernels for CubeBackend {
    fn patch_columns_backward(
        columns_grad: FloatTensor<Self>,
        input: Shape,
        patches: Patches,
    ) -> FloatTensor<Self> {
        let dtype = columns_grad.dtype();
        let units = input.num_elements();
        let (client, device) = (columns_grad.client.clone(), columns_grad.device.clone());
        let columns_grad = prepare(columns_grad);
        let out = client.empty(4 * units.max(1));
        if units > 0 {
            patch_columns_backward_kernel::launch(
                &client,
                count_1d(units),
                CubeDim::new_1d(THREADS_1D),
                tensor_arg(&columns_grad),
                arg(&out, units),
                grid_arg(&input, patches),
                units,
            );
        }
        // Channels-last, answered as the `[N, C, H, W]` view (as the products answer their
        // rows): the previous layer's `∂x` product then reads its gradient's rows in place.
        let [n, c, h, w] = input.dims::<4>();
        let rows = tensor_f32(&client, &device, out, &[n, h, w, c]);
        cast_to(Self::float_permute(rows, &[0, 3, 1, 2]), dtype)
    }
}
