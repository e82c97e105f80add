//! Shared layers' parameter gradients on Burn's CubeCL backend, read straight from the rows
//! their passes filed (see [`super`], design.md §7.5): one launch per layer, plus one sum over
//! the chunks for all the layers formed together whose rows are split.
//!
//! The gradient is `[Xᵀ; 1ᵀ]·(G·diag(s))`: its first `in` rows are `∂W = Xᵀ·G`, its last, when
//! the bias takes a gradient, `∂b = Σ_rows G` (a row of ones in `Xᵀ`), with `G`'s columns
//! scaled by a folded BatchNorm's `s` (design.md §7.5). `X` and `G` are every pass's rows one
//! after the other; the kernel never forms them. A row's pass is found by comparing the row
//! with the passes' end rows (up to [`PASS_PARTS`] passes per launch), and the ones and the
//! scale are applied where the rows are staged, so the stacked copies of `X` and `G` that a
//! library product needs are never written. A convolution's passes file their input images, and
//! `X`'s rows are then the images' patch columns, read where they are staged as the forward
//! product reads them (`crate::conv_norm`): the columns are never written at all.
//!
//! The reduction over rows is long (every pass's points) and the output small, so the rows
//! are cut into chunks ([`crate::split_k`]): the cubes of chunk `z` write partial gradient
//! `z`, and a sum over the chunks follows (`chunk_sum_kernel`, one launch for every chunked
//! layer of the batch, each element's chunks added in order). The layers' gradients are
//! written into one buffer, each `∂W` and bias row at an aligned offset, and handed over as
//! views of it. Within a chunk the kernel is the forward product's
//! (`super::product`): a cube of 16 × 16 threads owns a 64 × 64 block of the gradient and walks
//! the chunk's rows 16 at a time, staging the slices of `X` and `G` in shared memory with
//! neighbouring threads reading neighbouring columns of a row; each thread sums a 4 × 4 grid
//! of outputs in a fixed order, so results do not depend on scheduling.

use burn::backend::TensorMetadata;
use burn::tensor::Shape;
use burn_cubecl::CubeBackend;
use burn_cubecl::cubecl;
use burn_cubecl::cubecl::prelude::*;
use burn_cubecl::cubecl::server::Handle;
use burn_cubecl::tensor::CubeTensor;
use lifegom_render::cube::host::{
    ComputeClient, THREADS_1D, arg, cast_to, prepare, tensor_arg, tensor_f32, u32_bytes,
};
use lifegom_render::cube::image::{ImageLayout, ImageLayoutLaunch, dense, image_layout};

use crate::gemm_conv::cube::{Grid, GridLaunch, grid_arg, patch_value};
use crate::gemm_conv::op::Patches;

use super::op::{Formed, GradientKernels, PASS_PARTS, ParameterRows};
use super::product::{DEPTH, PER_THREAD, SIDE, THREADS, TILE, multiply_staged};

/// The sizes of one launch: its passes' rows, the widths and the chunks.
#[derive(CubeType, CubeLaunch)]
struct GradientDims {
    /// Rows of the launch's passes together.
    filled: usize,
    /// `X`'s width `in` (0 when the weight takes no gradient).
    inputs: usize,
    /// The gradient's rows: `in`, plus one for the bias.
    out_rows: usize,
    /// `G`'s width `out`.
    cols: usize,
    /// Rows per chunk.
    chunk_rows: usize,
    /// The launch's first chunk among all the layer's partial gradients.
    first_chunk: usize,
    /// Where the layer's first partial gradient starts in the bound buffer (elements).
    origin: usize,
    /// The row the bias row is written at (`inputs`, or further on in a gradient whose bias
    /// row starts where a binding may).
    bias_at: usize,
    /// Rows end after passes 0, 1 and 2 (the last part takes the rest).
    end0: usize,
    end1: usize,
    end2: usize,
}

/// Element `(row, col)` of the patch columns of images `p0…p3` (layouts `l0…l3`, one window
/// `grid`), their rows one after the other.
#[cube]
#[allow(clippy::too_many_arguments, unused_assignments)]
fn pass_patch(
    p0: &[f32],
    p1: &[f32],
    p2: &[f32],
    p3: &[f32],
    layouts: &PassLayouts,
    grid: &Grid,
    row: usize,
    col: usize,
    dims: &GradientDims,
) -> f32 {
    let mut value = 0.0f32;
    if row < dims.end0 {
        value = patch_value(p0, &layouts.l0, grid, row, col);
    } else if row < dims.end1 {
        value = patch_value(p1, &layouts.l1, grid, row - dims.end0, col);
    } else if row < dims.end2 {
        value = patch_value(p2, &layouts.l2, grid, row - dims.end1, col);
    } else {
        value = patch_value(p3, &layouts.l3, grid, row - dims.end2, col);
    }
    value
}

/// The layouts of a launch's images, when `X` is their patch columns.
#[derive(CubeType, CubeLaunch)]
struct PassLayouts {
    l0: ImageLayout,
    l1: ImageLayout,
    l2: ImageLayout,
    l3: ImageLayout,
}

/// Element `(row, col)` of the rows of parts `p0…p3`, each `width` wide, one after the other.
#[cube]
#[allow(clippy::too_many_arguments, unused_assignments)]
fn pass_element(
    p0: &[f32],
    p1: &[f32],
    p2: &[f32],
    p3: &[f32],
    row: usize,
    col: usize,
    width: usize,
    dims: &GradientDims,
) -> f32 {
    let mut value = 0.0f32;
    if row < dims.end0 {
        value = p0[row * width + col];
    } else if row < dims.end1 {
        value = p1[(row - dims.end0) * width + col];
    } else if row < dims.end2 {
        value = p2[(row - dims.end1) * width + col];
    } else {
        value = p3[(row - dims.end2) * width + col];
    }
    value
}

/// Partial gradient `CUBE_POS_Z` (module docs): `partials[z, i, j] = Σ_rows A[i, r]·B[r, j]` over
/// the chunk's rows, with `A = [Xᵀ; 1ᵀ]` (the ones only when `bias_row`) and `B = G·diag(s)`
/// (`scale` read only when `scaled`). With `x_patches`, `X`'s rows are the patch columns of the
/// images `x0…x3` (`layouts`, `grid`), read where they are staged.
#[cube(launch)]
#[allow(clippy::too_many_arguments)]
fn pass_gradient_kernel(
    x0: &[f32],
    x1: &[f32],
    x2: &[f32],
    x3: &[f32],
    g0: &[f32],
    g1: &[f32],
    g2: &[f32],
    g3: &[f32],
    scale: &[f32],
    partials: &mut [f32],
    dims: &GradientDims,
    layouts: &PassLayouts,
    grid: &Grid,
    #[comptime] x_patches: bool,
    #[comptime] scaled: bool,
    #[comptime] bias_row: bool,
) {
    let mut a_tile = Shared::<[f32]>::new_slice(DEPTH * TILE);
    let mut b_tile = Shared::<[f32]>::new_slice(DEPTH * TILE);
    let tx = UNIT_POS_X as usize;
    let ty = UNIT_POS_Y as usize;
    let unit = ty * SIDE + tx;
    let i0 = CUBE_POS_Y as usize * TILE;
    let j0 = CUBE_POS_X as usize * TILE;
    let chunk = CUBE_POS_Z as usize;
    let begin = chunk * dims.chunk_rows;
    let end = usize::min(begin + dims.chunk_rows, dims.filled);
    let mut acc = Array::<f32>::new(PER_THREAD * PER_THREAD);
    #[unroll]
    for i in 0..PER_THREAD * PER_THREAD {
        acc[i] = 0.0f32;
    }
    let mut r0 = begin;
    while r0 < end {
        // Both slices: entry `e` is row `r0 + e / TILE`, column `e % TILE` of the block.
        #[unroll]
        for l in 0..TILE * DEPTH / THREADS {
            let e = unit + l * THREADS;
            let rr = e / TILE;
            let c = e % TILE;
            let row = r0 + rr;
            let (i, j) = (i0 + c, j0 + c);
            let mut a = 0.0f32;
            let mut b = 0.0f32;
            if row < end {
                if i < dims.inputs {
                    if x_patches {
                        a = pass_patch(x0, x1, x2, x3, layouts, grid, row, i, dims);
                    } else {
                        a = pass_element(x0, x1, x2, x3, row, i, dims.inputs, dims);
                    }
                } else if bias_row && i == dims.inputs {
                    a = 1.0f32;
                }
                if j < dims.cols {
                    b = pass_element(g0, g1, g2, g3, row, j, dims.cols, dims);
                    if scaled {
                        b *= scale[j];
                    }
                }
            }
            a_tile[rr * TILE + c] = a;
            b_tile[rr * TILE + c] = b;
        }
        sync_cube();
        multiply_staged(&a_tile, TILE, &b_tile, &mut acc, tx, ty);
        sync_cube();
        r0 += DEPTH;
    }
    let base = (dims.first_chunk + chunk) * dims.out_rows;
    #[unroll]
    for i in 0..PER_THREAD {
        let row = i0 + ty + i * SIDE;
        #[unroll]
        for j in 0..PER_THREAD {
            let col = j0 + tx + j * SIDE;
            if row < dims.out_rows && col < dims.cols {
                let mut at = row;
                if row == dims.inputs {
                    at = dims.bias_at;
                }
                partials[dims.origin + (base + at) * dims.cols + col] = acc[i * PER_THREAD + j];
            }
        }
    }
}

/// `X`'s width for an input of shape `x`: its last axis, or an image's patch width.
pub(super) fn input_width(x: &Shape, patches: Option<Patches>) -> usize {
    match patches {
        Some(patches) => patches.columns_shape(x)[1],
        None => x[x.num_dims() - 1],
    }
}

/// Chunks of `rows` rows at `chunk_rows` each; a group without rows still has one, which
/// writes zeros.
fn chunks_of(rows: usize, chunk_rows: usize) -> usize {
    rows.div_ceil(chunk_rows.max(1)).max(1)
}

/// Floats between offsets where every runtime accepts a binding to start (WebGPU's limit is a
/// power of two of at most 256 bytes): each layer's gradient and its bias row start at
/// multiples of it, so that both are views of one buffer.
const VIEW_ALIGN: usize = 64;

/// The row of a layer's bias row in the buffer: the first at or after `inputs` whose offset is
/// a multiple of [`VIEW_ALIGN`] floats.
fn bias_row_at(inputs: usize, cols: usize) -> usize {
    (inputs..=inputs + VIEW_ALIGN)
        .find(|r| (r * cols).is_multiple_of(VIEW_ALIGN))
        .unwrap_or(inputs)
}

/// Entries per layer of [`chunk_sum_kernel`]'s table.
const TABLE_ENTRIES: usize = 6;

/// Sums each chunked layer's partial gradients over its chunks, in chunk order: `table` holds
/// per layer (`CUBE_POS_Y`) the origin of its partials, its chunks, a partial's length, the
/// length of `∂W`'s part, and where `∂W` and the bias row go in `output`.
#[cube(launch)]
fn chunk_sum_kernel(partials: &[f32], table: &[u32], output: &mut [f32]) {
    let entry = TABLE_ENTRIES * CUBE_POS_Y as usize;
    let origin = table[entry] as usize;
    let chunks = table[entry + 1] as usize;
    let len = table[entry + 2] as usize;
    let weights = table[entry + 3] as usize;
    let weight_at = table[entry + 4] as usize;
    let bias_at = table[entry + 5] as usize;
    let stride = CUBE_COUNT_X as usize * CUBE_DIM_X as usize;
    let mut e = CUBE_POS_X as usize * CUBE_DIM_X as usize + UNIT_POS_X as usize;
    while e < len {
        let mut sum = 0.0f32;
        for z in 0..chunks {
            sum += partials[origin + z * len + e];
        }
        if e < weights {
            output[weight_at + e] = sum;
        } else {
            output[bias_at + e - weights] = sum;
        }
        e += stride;
    }
}

/// One layer's rows prepared for its launches ([`GradientKernels::pass_gradients`]).
struct LayerRows {
    xs: Vec<CubeTensor>,
    gs: Vec<CubeTensor>,
    /// A frozen BatchNorm's `s`, or a stand-in never read.
    scale: CubeTensor,
    scaled: bool,
    patches: Option<Patches>,
    bias_row: bool,
    chunk_rows: usize,
    /// `X`'s width, `G`'s width, and the gradient's rows.
    inputs: usize,
    cols: usize,
    out_rows: usize,
    /// Passes per launch: the first pass of each group of [`PASS_PARTS`].
    groups: Vec<usize>,
    /// Chunks over all the groups.
    chunks: usize,
    /// The row of the bias row in the layer's gradient as handed over: `inputs`, or the first
    /// row after it that starts where a binding may (see [`GradientKernels::pass_gradients`]).
    bias_at: usize,
    dtype: burn::tensor::DType,
}

impl LayerRows {
    fn new(rows: ParameterRows<CubeBackend>) -> Self {
        let ParameterRows {
            inputs: xs,
            patches,
            grads: gs,
            scale,
            bias_row,
            chunk_rows,
        } = rows;
        assert!(
            !gs.is_empty() && (xs.is_empty() || xs.len() == gs.len()),
            "every pass files its gradient, and its input when the weight takes a gradient"
        );
        let dtype = gs[0].dtype();
        let inputs = xs.first().map_or(0, |x| input_width(&x.shape(), patches));
        let cols = gs[0].shape()[1];
        // Images are read in the layout they come in (the previous layer's is channels-last).
        let xs: Vec<CubeTensor> = match patches {
            Some(_) => xs.into_iter().map(dense).collect(),
            None => xs.into_iter().map(prepare).collect(),
        };
        let gs: Vec<CubeTensor> = gs.into_iter().map(prepare).collect();
        // Without a scale or inputs the kernel reads none: the first gradient is bound instead.
        let scaled = scale.is_some();
        let scale = scale.map_or_else(|| gs[0].clone(), prepare);
        let xs = if xs.is_empty() {
            vec![gs[0].clone()]
        } else {
            xs
        };
        let groups: Vec<usize> = (0..gs.len()).step_by(PASS_PARTS).collect();
        let mut layer = Self {
            xs,
            gs,
            scale,
            scaled,
            patches,
            bias_row,
            chunk_rows,
            inputs,
            cols,
            out_rows: inputs + usize::from(bias_row),
            groups,
            chunks: 0,
            bias_at: bias_row_at(inputs, cols),
            dtype,
        };
        layer.chunks = layer
            .groups
            .iter()
            .map(|&g| chunks_of(layer.group_rows(g), chunk_rows))
            .sum();
        layer
    }

    /// The gradient's elements, without the bias row's padding.
    fn len(&self) -> usize {
        self.out_rows * self.cols
    }

    /// The rows the layer takes in the buffer: `∂W`'s, then the bias row at `bias_at`.
    fn handed_rows(&self) -> usize {
        if self.bias_row {
            self.bias_at + 1
        } else {
            self.inputs
        }
    }

    /// Rows of the passes launched with pass `g`.
    fn group_rows(&self, g: usize) -> usize {
        self.gs[g..(g + PASS_PARTS).min(self.gs.len())]
            .iter()
            .map(|t| t.shape()[0])
            .sum()
    }

    /// Launches the layer's chunks, writing partial gradient `z` at `origin + z·len` of
    /// `target` (`target_len` elements), the bias row at row `bias_at`; one chunk writes the
    /// gradient as handed over (`bias_at` = [`Self::bias_at`]), several their partials
    /// (`bias_at` = `inputs`).
    fn launch(
        &self,
        client: &ComputeClient,
        (target, target_len): (&Handle, usize),
        origin: usize,
        bias_at: usize,
    ) {
        let (xs, gs, patches) = (&self.xs, &self.gs, self.patches);
        let image = xs.first().map(|x| x.shape());
        let grid = || match (patches, &image) {
            (Some(patches), Some(image)) => grid_arg(image, patches),
            _ => GridLaunch::new(0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0),
        };
        let blocks = |n: usize| n.div_ceil(TILE) as u32;
        let mut first_chunk = 0;
        for &g in &self.groups {
            let parts = g..(g + PASS_PARTS).min(gs.len());
            let filled = self.group_rows(g);
            let group_chunks = chunks_of(filled, self.chunk_rows);
            // Rows end after each pass; the ends of unused parts are the last row's end.
            let mut ends = [filled; PASS_PARTS];
            let mut end = 0;
            for (slot, t) in ends.iter_mut().zip(&gs[parts.clone()]) {
                end += t.shape()[0];
                *slot = end;
            }
            // Unused parts are bound to one of the group's and never read (the inputs'
            // stand-in, when the weight takes no gradient, is one tensor).
            let index = |all: &[CubeTensor], i: usize| {
                (parts.start + i).min(parts.end - 1).min(all.len() - 1)
            };
            let part = |all: &[CubeTensor], i: usize| tensor_arg(&all[index(all, i)]);
            let layout = |i: usize| match patches {
                Some(_) => image_layout(&xs[index(xs, i)]),
                None => ImageLayoutLaunch::new(0, 0, 0, 0),
            };
            if self.out_rows > 0 && self.cols > 0 {
                pass_gradient_kernel::launch(
                    client,
                    CubeCount::Static(
                        blocks(self.cols),
                        blocks(self.out_rows),
                        group_chunks as u32,
                    ),
                    CubeDim::new_2d(SIDE as u32, SIDE as u32),
                    part(xs, 0),
                    part(xs, 1),
                    part(xs, 2),
                    part(xs, 3),
                    part(gs, 0),
                    part(gs, 1),
                    part(gs, 2),
                    part(gs, 3),
                    tensor_arg(&self.scale),
                    arg(target, target_len),
                    GradientDimsLaunch::new(
                        filled,
                        self.inputs,
                        self.out_rows,
                        self.cols,
                        self.chunk_rows.max(1),
                        first_chunk,
                        origin,
                        bias_at,
                        ends[0],
                        ends[1],
                        ends[2],
                    ),
                    PassLayoutsLaunch::new(layout(0), layout(1), layout(2), layout(3)),
                    grid(),
                    patches.is_some(),
                    self.scaled,
                    self.bias_row,
                );
            }
            first_chunk += group_chunks;
        }
    }
}

impl GradientKernels for CubeBackend {
    fn pass_gradients(layers: Vec<ParameterRows<Self>>) -> Vec<Formed<Self>> {
        let Some(first) = layers.first() else {
            return Vec::new();
        };
        let client = first.grads[0].client.clone();
        // Every `∂W` and bias row is a view of one buffer, so each starts where a binding may.
        let align = (client.properties().memory.alignment as usize / size_of::<f32>())
            .max(VIEW_ALIGN)
            .next_power_of_two();
        let layers: Vec<LayerRows> = layers.into_iter().map(LayerRows::new).collect();
        let device = layers[0].gs[0].device.clone();
        let mut starts = Vec::with_capacity(layers.len());
        let mut total: usize = 0;
        for layer in &layers {
            let start = total.next_multiple_of(align);
            starts.push(start);
            total = start + layer.handed_rows() * layer.cols;
        }
        // Partial gradients of the layers with more than one chunk, one after the other.
        let mut table = Vec::new();
        let mut partial_total = 0;
        for (layer, &start) in layers.iter().zip(&starts) {
            if layer.chunks > 1 {
                let (len, weights) = (layer.len(), layer.inputs * layer.cols);
                let bias_at = start + layer.bias_at * layer.cols;
                table.extend(
                    [partial_total, layer.chunks, len, weights, start, bias_at].map(|v| v as u32),
                );
                partial_total += layer.chunks * len;
            }
        }
        let output = client.empty(size_of::<f32>() * total.max(1));
        let partials = client.empty(size_of::<f32>() * partial_total.max(1));
        let mut partial_origin = 0;
        for (layer, &start) in layers.iter().zip(&starts) {
            if layer.chunks > 1 {
                let target = (&partials, partial_total);
                layer.launch(&client, target, partial_origin, layer.inputs);
                partial_origin += layer.chunks * layer.len();
            } else {
                layer.launch(&client, (&output, total), start, layer.bias_at);
            }
        }
        let summed = table.len() / TABLE_ENTRIES;
        if summed > 0 {
            let longest = table
                .chunks(TABLE_ENTRIES)
                .map(|t| t[2] as usize)
                .max()
                .unwrap_or(1);
            let cubes = longest.div_ceil(THREADS_1D as usize).clamp(1, 1 << 12) as u32;
            let table = client.create_from_slice(&u32_bytes(&table));
            chunk_sum_kernel::launch(
                &client,
                CubeCount::Static(cubes, summed as u32, 1),
                CubeDim::new_1d(THREADS_1D),
                arg(&partials, partial_total),
                arg(&table, TABLE_ENTRIES * summed),
                arg(&output, total),
            );
        }
        // `∂W` and the bias row as views of the buffer: each starts aligned, and a binding's
        // end needs no alignment.
        let view = |start: usize, shape: &[usize], dtype| {
            let len: usize = shape.iter().product();
            let handle = output
                .clone()
                .offset_start((size_of::<f32>() * start) as u64)
                .offset_end((size_of::<f32>() * (total - start - len)) as u64);
            cast_to(tensor_f32(&client, &device, handle, shape), dtype)
        };
        layers
            .iter()
            .zip(&starts)
            .map(|(layer, &start)| Formed {
                weight: (layer.inputs > 0)
                    .then(|| view(start, &[layer.inputs, layer.cols], layer.dtype)),
                bias: layer.bias_row.then(|| {
                    view(
                        start + layer.bias_at * layer.cols,
                        &[layer.cols],
                        layer.dtype,
                    )
                }),
            })
            .collect()
    }
}
