//! The shared layer's products on Burn's CubeCL backend, with the layer's bias and activation in
//! the same launch (design.md §1.4).
//!
//! Burn's fused-matmul path would run `act(x·W + b)` as one kernel, but without `autotune` it
//! tries only its cooperative-matrix kernel, which `f32` products cannot use on the devices we
//! have; its fallback is Burn's product and then one elementwise kernel for the bias and the
//! activation, forward, and one for the activation's mask before `∂x`'s product, backward. Here
//! each is one launch:
//!
//! - forward, `y = act(x·W + b)` ([`Activation`]), or `y = relu(x·W + b + r)` for a residual
//!   block's last layer;
//! - backward through a ReLU, `∂x = (g ⊙ [y > 0])·Wᵀ`, which also writes the masked
//!   `g ⊙ [y > 0]` for the parameters' gradient (the shared layer files it, `super::op`), plus
//!   the gradient another op hands `x` (a residual block's, [`crate::handoff`]).
//!
//! One kernel, `affine_product_kernel`, computes `out = epilogue(A·B)` for a row-major `A`
//! `[rows, inner]` and a strided `B` (`W` as stored, or `Wᵀ` as a view of it). Each cube of
//! 16 × 16 threads owns a [`TILE`] × [`TILE`] block of the output and walks the inner axis
//! [`DEPTH`] at a time: its threads stage the `A` and `B` slices in shared memory (neighbouring
//! threads read neighbouring addresses of the row-major operands), then each thread accumulates
//! a 4 × 4 grid of outputs, rows `ty + 16·i` and columns `tx + 16·j`, so that neighbouring
//! threads write neighbouring columns. The masked variant multiplies `A` by its mask where it is
//! staged; the cubes of the first column of blocks, which together stage every element of `A`
//! once, also write it out. Each output is one thread's sum over the inner axis in a fixed
//! order: results do not depend on scheduling.

use burn::backend::TensorMetadata;
use burn::backend::ops::FloatTensorOps;
use burn::backend::tensor::FloatTensor;
use burn::tensor::{DType, Shape};
use burn_cubecl::CubeBackend;
use burn_cubecl::cubecl;
use burn_cubecl::cubecl::prelude::*;
use burn_cubecl::tensor::CubeTensor;
use lifegom_render::cube::host::{arg, cast_to, prepare, tensor_arg, tensor_f32};
use lifegom_render::cube::image::{ImageLayout, ImageLayoutLaunch, dense, image_layout};

use crate::gemm_conv::cube::{Grid, GridLaunch, grid_arg, patch_value};
use crate::gemm_conv::op::Patches;

use super::op::{Ledger, OutputMap, ProductKernels, SharedLinearOps};
use crate::activation::Activation;
use crate::activation::cube::activate;
use crate::handoff::Handoff;

/// Output rows and columns of a cube's block.
pub(super) const TILE: usize = 64;

/// Inner-axis entries staged per step.
pub(super) const DEPTH: usize = 16;

/// Threads along each axis of a cube.
pub(super) const SIDE: usize = 16;

/// Outputs per thread along each axis (`TILE / SIDE`).
pub(super) const PER_THREAD: usize = 4;

/// Threads of a cube.
pub(super) const THREADS: usize = SIDE * SIDE;

/// Row stride of the staged `A` slice: one more than a block's rows, so that the threads
/// staging one row's `DEPTH` entries write to distinct shared-memory banks.
const A_STRIDE: usize = TILE + 1;

/// The sizes and `B`'s strides.
#[derive(CubeType, CubeLaunch)]
struct ProductDims {
    rows: usize,
    inner: usize,
    cols: usize,
    /// `B[k, n]` is at `k·b_inner_stride + n·b_col_stride`.
    b_inner_stride: usize,
    b_col_stride: usize,
}

/// Adds the product of one staged step to thread `(tx, ty)`'s 4 × 4 outputs: `acc[i·4 + j] +=
/// Σ_kk a_tile[kk·a_stride + ty + 16·i]·b_tile[kk·TILE + tx + 16·j]`, the inner entries in
/// order. Shared by this module's kernel and the parameters' gradient kernel (`super::gradient`).
#[cube]
pub(super) fn multiply_staged(
    a_tile: &Shared<[f32]>,
    #[comptime] a_stride: usize,
    b_tile: &Shared<[f32]>,
    acc: &mut Array<f32>,
    tx: usize,
    ty: usize,
) {
    for kk in 0..DEPTH {
        let mut av = Array::<f32>::new(PER_THREAD);
        let mut bv = Array::<f32>::new(PER_THREAD);
        #[unroll]
        for i in 0..PER_THREAD {
            av[i] = a_tile[kk * a_stride + ty + i * SIDE];
            bv[i] = b_tile[kk * TILE + tx + i * SIDE];
        }
        #[unroll]
        for i in 0..PER_THREAD {
            #[unroll]
            for j in 0..PER_THREAD {
                acc[i * PER_THREAD + j] += av[i] * bv[j];
            }
        }
    }
}

/// `out = epilogue(A·B)` (module docs). With `a_patches`, `A` is the patch columns of the image
/// `a` (`a_layout`, `grid`), read where it is staged (`mask` is then not read). `mask` and
/// `masked_out` are read and written only when
/// `masked`, `a_scale` (`[inner]`, scaling `A`'s columns where they are staged, after the mask)
/// only when `a_scaled`, `bias` only when `biased`, `scale` and `shift` (`[cols]`, a frozen
/// BatchNorm's map after the bias) only when `normed`, `residual` (`[rows, cols]`, added before
/// the activation) only when `residual_added`.
#[cube(launch)]
#[allow(clippy::too_many_arguments)]
fn affine_product_kernel(
    a: &[f32],
    a_layout: &ImageLayout,
    grid: &Grid,
    mask: &[f32],
    a_scale: &[f32],
    b: &[f32],
    bias: &[f32],
    scale: &[f32],
    shift: &[f32],
    residual: &[f32],
    out: &mut [f32],
    masked_out: &mut [f32],
    dims: &ProductDims,
    #[comptime] a_patches: bool,
    #[comptime] masked: bool,
    #[comptime] a_scaled: bool,
    #[comptime] biased: bool,
    #[comptime] normed: bool,
    #[comptime] residual_added: bool,
    #[comptime] activation: Activation,
) {
    let mut a_tile = Shared::<[f32]>::new_slice(DEPTH * A_STRIDE);
    let mut b_tile = Shared::<[f32]>::new_slice(DEPTH * TILE);
    let tx = UNIT_POS_X as usize;
    let ty = UNIT_POS_Y as usize;
    let unit = ty * SIDE + tx;
    let row0 = CUBE_POS_Y as usize * TILE;
    let col0 = CUBE_POS_X as usize * TILE;
    let writes_masked = CUBE_POS_X == 0;
    let mut acc = Array::<f32>::new(PER_THREAD * PER_THREAD);
    #[unroll]
    for i in 0..PER_THREAD * PER_THREAD {
        acc[i] = 0.0f32;
    }
    let mut k0 = 0usize;
    while k0 < dims.inner {
        // `A`'s block: entry `e` is row `e / DEPTH`, inner index `e % DEPTH`.
        #[unroll]
        for l in 0..TILE * DEPTH / THREADS {
            let e = unit + l * THREADS;
            let r = e / DEPTH;
            let kk = e % DEPTH;
            let (row, k) = (row0 + r, k0 + kk);
            let mut v = 0.0f32;
            if row < dims.rows && k < dims.inner {
                if a_patches {
                    v = patch_value(a, a_layout, grid, row, k);
                } else {
                    let at = row * dims.inner + k;
                    v = a[at];
                    if masked {
                        v = select(mask[at] <= 0.0f32, 0.0f32, v);
                        if writes_masked {
                            masked_out[at] = v;
                        }
                    }
                }
                if a_scaled {
                    v *= a_scale[k];
                }
            }
            a_tile[kk * A_STRIDE + r] = v;
        }
        // `B`'s block: entry `e` is inner index `e / TILE`, column `e % TILE`.
        #[unroll]
        for l in 0..TILE * DEPTH / THREADS {
            let e = unit + l * THREADS;
            let kk = e / TILE;
            let c = e % TILE;
            let (k, col) = (k0 + kk, col0 + c);
            let mut v = 0.0f32;
            if k < dims.inner && col < dims.cols {
                v = b[k * dims.b_inner_stride + col * dims.b_col_stride];
            }
            b_tile[kk * TILE + c] = v;
        }
        sync_cube();
        multiply_staged(&a_tile, A_STRIDE, &b_tile, &mut acc, tx, ty);
        sync_cube();
        k0 += DEPTH;
    }
    #[unroll]
    for i in 0..PER_THREAD {
        let row = row0 + ty + i * SIDE;
        #[unroll]
        for j in 0..PER_THREAD {
            let col = col0 + tx + j * SIDE;
            if row < dims.rows && col < dims.cols {
                let mut v = acc[i * PER_THREAD + j];
                if biased {
                    v += bias[col];
                }
                if normed {
                    v = v * scale[col] + shift[col];
                }
                if residual_added {
                    v += residual[row * dims.cols + col];
                }
                out[row * dims.cols + col] = activate(v, activation);
            }
        }
    }
}

/// `B` of a product: the weight `W` `[in, out]` as stored, or its transpose.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum WeightSide {
    /// `x·W`.
    AsStored,
    /// `g·Wᵀ`.
    Transposed,
}

/// How `A` is read: as the patch columns of an image `[N, C, H, W]` (`a` in its own layout,
/// [`dense`]), or through a ReLU's mask (its output, `[rows, inner]`); then scaled per column
/// (`[inner]`); every tensor prepared.
#[derive(Default)]
struct Prologue<'t> {
    patches: Option<Patches>,
    mask: Option<&'t CubeTensor>,
    scale: Option<&'t CubeTensor>,
}

/// What a product adds to `A·B` before its activation, and the activation; every tensor
/// prepared.
struct Epilogue<'t> {
    /// `[cols]`.
    bias: Option<&'t CubeTensor>,
    /// A frozen BatchNorm's `(s, t)`, each `[cols]`: `v·s + t` after the bias.
    norm: Option<(&'t CubeTensor, &'t CubeTensor)>,
    /// `[rows, cols]`.
    residual: Option<&'t CubeTensor>,
    activation: Activation,
}

/// `(epilogue(prologue(A)·B), A ⊙ [mask > 0] when masked)` for `a` `[rows, inner]` and the
/// layer's weight, all prepared.
fn launch_product(
    a: &CubeTensor,
    prologue: Prologue<'_>,
    weight: &CubeTensor,
    side: WeightSide,
    epilogue: Epilogue<'_>,
) -> (CubeTensor, Option<CubeTensor>) {
    let Prologue {
        patches,
        mask,
        scale: a_scale,
    } = prologue;
    let Epilogue {
        bias,
        norm,
        residual,
        activation,
    } = epilogue;
    let (client, device) = (&a.client, &a.device);
    let [rows, inner] = match patches {
        Some(patches) => {
            let columns = patches.columns_shape(&a.shape());
            [columns[0], columns[1]]
        }
        None => [a.shape()[0], a.shape()[1]],
    };
    // Unused records are zeros, never read.
    let (a_layout, grid) = match patches {
        Some(patches) => (image_layout(a), grid_arg(&a.shape(), patches)),
        None => (
            ImageLayoutLaunch::new(0, 0, 0, 0),
            GridLaunch::new(0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0),
        ),
    };
    let [w_in, w_out] = [weight.shape()[0], weight.shape()[1]];
    let (cols, b_inner_stride, b_col_stride) = match side {
        WeightSide::AsStored => (w_out, w_out, 1),
        WeightSide::Transposed => (w_in, 1, w_out),
    };
    assert_eq!(
        inner,
        match side {
            WeightSide::AsStored => w_in,
            WeightSide::Transposed => w_out,
        },
        "a product's inner widths"
    );
    let out = client.empty(4 * (rows * cols).max(1));
    let masked = mask.is_some();
    let masked_out = masked.then(|| client.empty(4 * (rows * inner).max(1)));
    if rows > 0 && cols > 0 {
        // Unused bindings are bound to `A` and never read or written.
        let mask_arg = tensor_arg(mask.unwrap_or(a));
        let masked_arg = masked_out
            .as_ref()
            .map_or_else(|| tensor_arg(a), |h| arg(h, rows * inner));
        let blocks = |n: usize| n.div_ceil(TILE) as u32;
        affine_product_kernel::launch(
            client,
            CubeCount::Static(blocks(cols), blocks(rows), 1),
            CubeDim::new_2d(SIDE as u32, SIDE as u32),
            tensor_arg(a),
            a_layout,
            grid,
            mask_arg,
            tensor_arg(a_scale.unwrap_or(a)),
            tensor_arg(weight),
            tensor_arg(bias.unwrap_or(a)),
            tensor_arg(norm.map_or(a, |(scale, _)| scale)),
            tensor_arg(norm.map_or(a, |(_, shift)| shift)),
            tensor_arg(residual.unwrap_or(a)),
            arg(&out, rows * cols),
            masked_arg,
            ProductDimsLaunch::new(rows, inner, cols, b_inner_stride, b_col_stride),
            patches.is_some(),
            masked,
            a_scale.is_some(),
            bias.is_some(),
            norm.is_some(),
            residual.is_some(),
            activation,
        );
    }
    let masked_out = masked_out.map(|h| tensor_f32(client, device, h, &[rows, inner]));
    (tensor_f32(client, device, out, &[rows, cols]), masked_out)
}

/// `x` `[.., c]` as `[rows, c]`, prepared (a view of the prepared tensor: no launch).
fn rows_of(x: FloatTensor<CubeBackend>) -> CubeTensor {
    let x = prepare(x);
    let shape = x.shape();
    let c = shape[shape.num_dims() - 1];
    let rows = shape.num_elements() / c.max(1);
    CubeBackend::float_reshape(x, Shape::new([rows, c]))
}

/// `t` `[rows, last]` as `shape` with its last axis `last`, in `dtype`.
fn shaped(t: CubeTensor, shape: &Shape, last: usize, dtype: DType) -> CubeTensor {
    let mut dims = shape.to_vec();
    if let Some(d) = dims.last_mut() {
        *d = last;
    }
    cast_to(CubeBackend::float_reshape(t, Shape::from(dims)), dtype)
}

/// `act(map(x·W) [+ r])` for `x` `[.., in]`, `W` `[in, out]`, the bias `b` and a frozen
/// BatchNorm's `s`, `t` (each `[out]`, read as `map` says) and the residual `r` `[.., out]` when
/// given → `[.., out]`; with `patches`, `x` is an image `[N, C, H, W]` whose patch columns are
/// the rows (→ `[N·H_out·W_out, out]`).
#[allow(clippy::too_many_arguments)]
fn affine(
    x: FloatTensor<CubeBackend>,
    patches: Option<Patches>,
    weight: FloatTensor<CubeBackend>,
    bias: FloatTensor<CubeBackend>,
    scale: FloatTensor<CubeBackend>,
    shift: FloatTensor<CubeBackend>,
    map: OutputMap,
    residual: Option<FloatTensor<CubeBackend>>,
    activation: Activation,
) -> FloatTensor<CubeBackend> {
    let dtype = x.dtype();
    let weight = prepare(weight);
    let shape = match patches {
        Some(patches) => Shape::new([patches.columns_shape(&x.shape())[0], weight.shape()[1]]),
        None => x.shape(),
    };
    // An image is read in the layout it comes in (the previous layer's is channels-last).
    let a = match patches {
        Some(_) => dense(x),
        None => rows_of(x),
    };
    let biased = map != OutputMap::Normed;
    let bias = biased.then(|| prepare(bias));
    let norm = (map != OutputMap::Biased).then(|| (prepare(scale), prepare(shift)));
    let residual = residual.map(rows_of);
    let cols = weight.shape()[1];
    let epilogue = Epilogue {
        bias: bias.as_ref(),
        norm: norm.as_ref().map(|(s, t)| (s, t)),
        residual: residual.as_ref(),
        activation,
    };
    let prologue = Prologue {
        patches,
        ..Prologue::default()
    };
    let (out, _) = launch_product(&a, prologue, &weight, WeightSide::AsStored, epilogue);
    shaped(out, &shape, cols, dtype)
}

impl SharedLinearOps for CubeBackend {
    fn shared_linear(
        x: FloatTensor<Self>,
        patches: Option<Patches>,
        weight: FloatTensor<Self>,
        bias: FloatTensor<Self>,
        scale: FloatTensor<Self>,
        shift: FloatTensor<Self>,
        map: OutputMap,
        _ledger: Ledger,
        activation: Activation,
        _handoff: Handoff,
    ) -> FloatTensor<Self> {
        affine(
            x, patches, weight, bias, scale, shift, map, None, activation,
        )
    }

    fn shared_linear_residual(
        x: FloatTensor<Self>,
        patches: Option<Patches>,
        weight: FloatTensor<Self>,
        bias: FloatTensor<Self>,
        scale: FloatTensor<Self>,
        shift: FloatTensor<Self>,
        map: OutputMap,
        residual: FloatTensor<Self>,
        _ledger: Ledger,
        _handoff: Handoff,
    ) -> FloatTensor<Self> {
        affine(
            x,
            patches,
            weight,
            bias,
            scale,
            shift,
            map,
            Some(residual),
            Activation::Relu,
        )
    }

    fn trained_fold(
        weight: FloatTensor<Self>,
        gamma: FloatTensor<Self>,
        beta: FloatTensor<Self>,
        mean: FloatTensor<Self>,
        var: FloatTensor<Self>,
        epsilon: f32,
        _ledger: Ledger,
    ) -> (FloatTensor<Self>, FloatTensor<Self>) {
        super::trained_fold::trained_fold(weight, gamma, beta, mean, var, epsilon)
    }
}

impl ProductKernels for CubeBackend {
    fn x_gradient(
        grad: FloatTensor<Self>,
        output: Option<FloatTensor<Self>>,
        weight: FloatTensor<Self>,
        scale: Option<FloatTensor<Self>>,
        addend: Option<FloatTensor<Self>>,
    ) -> (FloatTensor<Self>, Option<FloatTensor<Self>>) {
        let dtype = grad.dtype();
        let shape = grad.shape();
        let g = rows_of(grad);
        let mask = output.map(rows_of);
        let scale = scale.map(prepare);
        let weight = prepare(weight);
        let addend = addend.map(rows_of);
        let d_in = weight.shape()[0];
        let prologue = Prologue {
            patches: None,
            mask: mask.as_ref(),
            scale: scale.as_ref(),
        };
        let epilogue = Epilogue {
            bias: None,
            norm: None,
            residual: addend.as_ref(),
            activation: Activation::Identity,
        };
        let (dx, masked) = launch_product(&g, prologue, &weight, WeightSide::Transposed, epilogue);
        let out = shape[shape.num_dims() - 1];
        (
            shaped(dx, &shape, d_in, dtype),
            masked.map(|m| shaped(m, &shape, out, dtype)),
        )
    }
}
