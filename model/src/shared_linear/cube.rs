//! The stacking of a shared layer's rows on Burn's CubeCL backend: one launch writes `X` and
//! `G` (see [`super`]). One thread per element of the wider of the two: it finds its row's
//! pass by comparing the row with the passes' end rows, and copies one element of `X` and one
//! of `G` where they exist, the latter times its column's scale for a folded layer. Rows past
//! the passes' (the padding of a split-k weight gradient, `super::op`) are written as zeros.
//! Columns past the inputs' (the bias's, `super::op::BIAS_COLUMNS`) are a column of ones on the
//! passes' rows, then zeros.

use burn::backend::TensorMetadata;
use burn::backend::tensor::FloatTensor;
use burn_cubecl::CubeBackend;
use burn_cubecl::cubecl;
use burn_cubecl::cubecl::prelude::*;
use lifegom_render::cube::host::{
    THREADS_1D, arg, cast_to, count_1d, prepare, tensor_arg, tensor_f32,
};

use super::op::{STACK_PARTS, StackKernels};

/// Element `e` of the stack of up to four parts `p0…p3` of width `width`, whose rows end at
/// `end0…end2` (the last part takes the rest).
#[cube]
#[allow(clippy::too_many_arguments, unused_assignments)]
fn stacked_element(
    p0: &[f32],
    p1: &[f32],
    p2: &[f32],
    p3: &[f32],
    e: usize,
    width: usize,
    end0: usize,
    end1: usize,
    end2: usize,
) -> f32 {
    let row = e / width;
    let col = e % width;
    let mut value = 0.0f32;
    if row < end0 {
        value = p0[row * width + col];
    } else if row < end1 {
        value = p1[(row - end0) * width + col];
    } else if row < end2 {
        value = p2[(row - end1) * width + col];
    } else {
        value = p3[(row - end2) * width + col];
    }
    value
}

#[cube(launch)]
#[allow(clippy::too_many_arguments)]
fn stack_rows_kernel(
    x0: &[f32],
    x1: &[f32],
    x2: &[f32],
    x3: &[f32],
    g0: &[f32],
    g1: &[f32],
    g2: &[f32],
    g3: &[f32],
    scale: &[f32],
    x_out: &mut [f32],
    g_out: &mut [f32],
    scaled: u32,
    rows: usize,
    filled: usize,
    x_width: usize,
    x_out_width: usize,
    g_width: usize,
    end0: usize,
    end1: usize,
    end2: usize,
) {
    let e = ABSOLUTE_POS;
    if e < rows * x_out_width {
        let row = e / x_out_width;
        let col = e % x_out_width;
        let mut x = 0.0f32;
        if row < filled {
            if col < x_width {
                x = stacked_element(
                    x0,
                    x1,
                    x2,
                    x3,
                    row * x_width + col,
                    x_width,
                    end0,
                    end1,
                    end2,
                );
            } else if col == x_width {
                x = 1.0;
            }
        }
        x_out[e] = x;
    }
    if e < rows * g_width {
        let mut g = 0.0f32;
        if e / g_width < filled {
            g = stacked_element(g0, g1, g2, g3, e, g_width, end0, end1, end2);
            if scaled != 0 {
                g *= scale[e % g_width];
            }
        }
        g_out[e] = g;
    }
}

impl StackKernels for CubeBackend {
    fn stack_pass_rows(
        xs: Vec<FloatTensor<Self>>,
        gs: Vec<FloatTensor<Self>>,
        scale: Option<FloatTensor<Self>>,
        padded_rows: usize,
        extra_columns: usize,
    ) -> (FloatTensor<Self>, FloatTensor<Self>) {
        assert!(
            !gs.is_empty() && gs.len() <= STACK_PARTS && xs.len() == gs.len(),
            "1 to {STACK_PARTS} passes of inputs and gradients"
        );
        let dtype = gs[0].dtype();
        let (client, device) = (gs[0].client.clone(), gs[0].device.clone());
        let x_width = xs[0].shape()[1];
        let x_out_width = x_width + extra_columns;
        let g_width = gs[0].shape()[1];
        // Rows end after each pass; the ends of unused parts are the last row's end.
        let filled: usize = gs.iter().map(|g| g.shape()[0]).sum();
        assert!(padded_rows >= filled, "padding adds rows");
        let rows = padded_rows;
        let mut ends = [filled; STACK_PARTS];
        let mut end = 0;
        for (slot, g) in ends.iter_mut().zip(&gs) {
            end += g.shape()[0];
            *slot = end;
        }
        let xs: Vec<_> = xs.into_iter().map(prepare).collect();
        let gs: Vec<_> = gs.into_iter().map(prepare).collect();
        // Without a scale the kernel reads none: the first gradient is bound in its place.
        let scaled = u32::from(scale.is_some());
        let scale = scale.map_or_else(|| gs[0].clone(), prepare);
        // Unused parts are bound to the first one and never read.
        let part = |parts: &[burn_cubecl::tensor::CubeTensor], i: usize| {
            tensor_arg(parts.get(i).unwrap_or(&parts[0]))
        };
        let x_out = client.empty(4 * (rows * x_out_width).max(1));
        let g_out = client.empty(4 * (rows * g_width).max(1));
        let units = rows * x_out_width.max(g_width);
        if units > 0 {
            stack_rows_kernel::launch(
                &client,
                count_1d(units),
                CubeDim::new_1d(THREADS_1D),
                part(&xs, 0),
                part(&xs, 1),
                part(&xs, 2),
                part(&xs, 3),
                part(&gs, 0),
                part(&gs, 1),
                part(&gs, 2),
                part(&gs, 3),
                tensor_arg(&scale),
                arg(&x_out, rows * x_out_width),
                arg(&g_out, rows * g_width),
                scaled,
                rows,
                filled,
                x_width,
                x_out_width,
                g_width,
                ends[0],
                ends[1],
                ends[2],
            );
        }
        (
            cast_to(
                tensor_f32(&client, &device, x_out, &[rows, x_out_width]),
                dtype,
            ),
            cast_to(tensor_f32(&client, &device, g_out, &[rows, g_width]), dtype),
        )
    }
}
