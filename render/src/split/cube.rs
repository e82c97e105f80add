//! The column split and its backward on Burn's CubeCL backend (see [`super`]): one thread per
//! element of the source, which finds its block by comparing its column with the blocks' end
//! columns, and copies one element into, or out of, that block. A split of one row whose blocks
//! all start where a binding may is views of the source instead, with no launch.

use burn::backend::TensorMetadata;
use burn::backend::ops::FloatTensorOps;
use burn::backend::tensor::FloatTensor;
use burn::tensor::Slice;
use burn_cubecl::CubeBackend;
use burn_cubecl::cubecl;
use burn_cubecl::cubecl::prelude::*;

use super::op::{ColumnBlocks, JoinKernels, MAX_BLOCKS, SplitOps};
use crate::cube::host::{THREADS_1D, arg, cast_to, count_1d, prepare, tensor_arg, tensor_f32};

#[cube(launch)]
#[allow(clippy::too_many_arguments)]
fn split_columns_kernel(
    source: &[f32],
    b0: &mut [f32],
    b1: &mut [f32],
    b2: &mut [f32],
    b3: &mut [f32],
    rows: usize,
    width: usize,
    end0: usize,
    end1: usize,
    end2: usize,
) {
    let e = ABSOLUTE_POS;
    if e < rows * width {
        let row = e / width;
        let col = e % width;
        let value = source[e];
        if col < end0 {
            b0[row * end0 + col] = value;
        } else if col < end1 {
            b1[row * (end1 - end0) + col - end0] = value;
        } else if col < end2 {
            b2[row * (end2 - end1) + col - end1] = value;
        } else {
            b3[row * (width - end2) + col - end2] = value;
        }
    }
}

/// `given` has bit `i` set when block `i`'s gradient is bound; the others read as zeros.
#[cube(launch)]
#[allow(clippy::too_many_arguments)]
fn join_columns_kernel(
    b0: &[f32],
    b1: &[f32],
    b2: &[f32],
    b3: &[f32],
    out: &mut [f32],
    given: u32,
    rows: usize,
    width: usize,
    end0: usize,
    end1: usize,
    end2: usize,
) {
    let e = ABSOLUTE_POS;
    if e < rows * width {
        let row = e / width;
        let col = e % width;
        let mut value = 0.0f32;
        if col < end0 {
            if given & 1 != 0 {
                value = b0[row * end0 + col];
            }
        } else if col < end1 {
            if given & 2 != 0 {
                value = b1[row * (end1 - end0) + col - end0];
            }
        } else if col < end2 {
            if given & 4 != 0 {
                value = b2[row * (end2 - end1) + col - end1];
            }
        } else if given & 8 != 0 {
            value = b3[row * (width - end2) + col - end2];
        }
        out[e] = value;
    }
}

impl SplitOps for CubeBackend {
    fn split_columns(
        t: FloatTensor<Self>,
        blocks: ColumnBlocks,
    ) -> (
        FloatTensor<Self>,
        FloatTensor<Self>,
        FloatTensor<Self>,
        FloatTensor<Self>,
    ) {
        let dtype = t.dtype();
        let rows = t.shape()[0];
        let width = blocks.total();
        assert_eq!(t.shape()[1], width, "the blocks tile the columns");
        let (client, device) = (t.client.clone(), t.device.clone());
        let t = prepare(t);
        let [end0, end1, end2] = blocks.ends();
        // One row: each block is a run of the buffer, a view where every block starts where a
        // binding may (a weight's row blocks, seen as `[1, rows·cols]`): no launch.
        let starts = [0, end0, end1, end2];
        let alignment = client.properties().memory.alignment as usize;
        if rows == 1
            && (0..MAX_BLOCKS)
                .all(|i| blocks.width(i) == 0 || (4 * starts[i]).is_multiple_of(alignment))
        {
            let mut views = (0..MAX_BLOCKS).map(|i| {
                let view = if blocks.width(i) == 0 {
                    tensor_f32(&client, &device, client.empty(4), &blocks.shape(rows, i))
                } else {
                    let end = starts[i] + blocks.width(i);
                    Self::float_slice(t.clone(), &[Slice::from(0..1), Slice::from(starts[i]..end)])
                };
                cast_to(view, dtype)
            });
            let mut next = || views.next().expect("one view per slot");
            return (next(), next(), next(), next());
        }
        let sizes: [usize; MAX_BLOCKS] = std::array::from_fn(|i| rows * blocks.width(i));
        let outs = sizes.map(|n| client.empty(4 * n.max(1)));
        if rows * width > 0 {
            split_columns_kernel::launch(
                &client,
                count_1d(rows * width),
                CubeDim::new_1d(THREADS_1D),
                tensor_arg(&t),
                arg(&outs[0], sizes[0].max(1)),
                arg(&outs[1], sizes[1].max(1)),
                arg(&outs[2], sizes[2].max(1)),
                arg(&outs[3], sizes[3].max(1)),
                rows,
                width,
                end0,
                end1,
                end2,
            );
        }
        let mut blocks_out = outs.into_iter().enumerate().map(|(i, h)| {
            let shape = blocks.shape(rows, i);
            cast_to(tensor_f32(&client, &device, h, &shape), dtype)
        });
        let mut next = || blocks_out.next().expect("one handle per slot");
        let (b0, b1, b2, b3) = (next(), next(), next(), next());
        (b0, b1, b2, b3)
    }

    fn join_columns(
        b0: FloatTensor<Self>,
        b1: FloatTensor<Self>,
        b2: FloatTensor<Self>,
        b3: FloatTensor<Self>,
        blocks: ColumnBlocks,
    ) -> FloatTensor<Self> {
        let rows = b0.shape()[0];
        let given = [b0, b1, b2, b3]
            .into_iter()
            .take(blocks.count())
            .map(Some)
            .collect();
        <Self as JoinKernels>::join_given_columns(given, blocks, rows)
    }
}

impl JoinKernels for CubeBackend {
    fn join_given_columns(
        blocks: Vec<Option<FloatTensor<Self>>>,
        widths: ColumnBlocks,
        rows: usize,
    ) -> FloatTensor<Self> {
        let first = blocks
            .iter()
            .flatten()
            .next()
            .expect("a block's gradient")
            .clone();
        let dtype = first.dtype();
        let (client, device) = (first.client.clone(), first.device.clone());
        let first = prepare(first);
        let mut given = 0u32;
        let bound: Vec<_> = (0..MAX_BLOCKS)
            .map(|i| match blocks.get(i).cloned().flatten() {
                Some(b) => {
                    given |= 1 << i;
                    prepare(b)
                }
                // Absent blocks are bound to a given one and never read.
                None => first.clone(),
            })
            .collect();
        let width = widths.total();
        let out = client.empty(4 * (rows * width).max(1));
        let [end0, end1, end2] = widths.ends();
        if rows * width > 0 {
            join_columns_kernel::launch(
                &client,
                count_1d(rows * width),
                CubeDim::new_1d(THREADS_1D),
                tensor_arg(&bound[0]),
                tensor_arg(&bound[1]),
                tensor_arg(&bound[2]),
                tensor_arg(&bound[3]),
                arg(&out, rows * width),
                given,
                rows,
                width,
                end0,
                end1,
                end2,
            );
        }
        cast_to(tensor_f32(&client, &device, out, &[rows, width]), dtype)
    }
}
