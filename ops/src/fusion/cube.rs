//! The residual LayerNorm `LN(x + r)·γ + β` on Burn's CubeCL backend (design.md §7.4): the same
//! formulas as the CPU slice code (`super::kernels`) in `f32`, in three kernels.
//!
//! - `residual_layer_norm_kernel`: one cube per row. Its threads stride over the channels
//!   (neighbouring threads read neighbouring channels) and reduce the row's sums in shared memory:
//!   the mean and `1/√(var + ε)` of `z = x + r`, then every thread writes its channels of the
//!   normalised, scaled and shifted row.
//! - `layer_norm_backward_kernel`: one cube per chunk of rows walks its rows in order; for each it
//!   recomputes the statistics the same way and writes `∂z = rstd·(a − mean(a) − x̂·mean(a·x̂))`
//!   with `a = g·γ`, and each thread adds `g·x̂` and `g` of its channels onto the chunk's sums;
//!   `layer_norm_columns_total_kernel` adds the chunks' sums in order: `∂γ` and `∂β`, with no
//!   atomics. (Until 5ddcc72, 2026-11-29, a kernel of its own, one thread per channel and chunk,
//!   formed the chunks' sums from statistics the rows' kernel wrote: one launch more per call.)
//!
//! An earlier version ran one thread per row (forward) and one per channel (the column sums):
//! a thread per row reads its row alone, so a warp's loads touch as many cache lines as it has
//! threads, and a thread per channel leaves a GPU nearly idle at a thousand channels. At the paper
//! preset those kernels took 49 ms of a reconstruction and 205 ms of a training step on an H200
//! (BENCHMARKS.md, "On a GPU (NVIDIA H200, 2026-11-27)").
//!
//! Burn's `LayerNorm` composition is about ten launches forward and fifteen backward per call.
//!
//! With dropout on the residual (`LN(x + Dropout(r))`, [`super::op::AddDroppedLayerNormOps`]),
//! every read of `r[e]` is multiplied by the mask's value at `e`, which the kernels hash from the
//! element's index and a key made of one uniform draw ([`crate::dropout`], "masks drawn inside a
//! kernel"); the backward recomputes it and writes `∂r = ∂z·m` beside `∂x = ∂z`. Two launches
//! fewer per mask forward than Burn's dropout (its generator, then the multiply), and the
//! multiply's backward is gone too.

use burn::backend::TensorMetadata;
use burn::backend::tensor::FloatTensor;
use burn::tensor::{DType, Shape};
use burn_cubecl::cubecl;
use burn_cubecl::cubecl::prelude::*;
use burn_cubecl::tensor::CubeTensor;
use burn_cubecl::{CubeBackend, CubeDevice};
use lifegom_render::cube::host::{
    ComputeClient, THREADS_1D, arg, cast_to, count_1d, count_cubes, prepare, tensor_arg, tensor_f32,
};

use super::op::{
    AddDroppedLayerNormOps, AddLayerNormOps, DropoutSlot, LayerNormEpsilon, LayerNormGrads,
    LayerNormInputs, LayerNormKernels,
};

/// Threads of a row kernel's cube (a power of two: the shared-memory sum halves it).
const ROW_THREADS: u32 = 64;

/// Rows of one chunk of the backward, whose column sums are added up afterwards.
const ROWS_PER_CHUNK: usize = 64;

/// The row a row kernel's cube works on (launched with [`count_cubes`]`(rows)`).
#[cube]
fn row_of_cube() -> usize {
    (CUBE_POS_Y * CUBE_COUNT_X + CUBE_POS_X) as usize
}

/// The sum of `value` over the cube's threads, returned to every thread. A fixed tree, so the
/// result does not depend on scheduling. `shared` holds one slot per thread; the closing barrier
/// lets the next call reuse it.
#[cube]
pub(super) fn cube_sum(shared: &mut Shared<[f32]>, value: f32) -> f32 {
    let unit = UNIT_POS as usize;
    shared[unit] = value;
    sync_cube();
    let mut active = CUBE_DIM as usize;
    while active > 1 {
        active /= 2;
        if unit < active {
            let other = shared[unit + active];
            shared[unit] += other;
        }
        sync_cube();
    }
    let total = shared[0];
    sync_cube();
    total
}

/// A kernel-drawn dropout mask's parameters (unused without dropout).
#[derive(CubeType, CubeLaunch)]
struct MaskParams {
    /// The draw that seeds the mask.
    slot: usize,
    /// `keep·2³²`: bits below it keep the element.
    threshold: u32,
    /// `1/keep`.
    scale: f32,
}

/// The 32-bit finaliser of [`crate::dropout::mix32`], in CubeCL.
#[cube]
fn mix32(value: u32) -> u32 {
    let mut x = value;
    x ^= x >> 16u32;
    x *= 0x7feb_352du32;
    x ^= x >> 15u32;
    x *= 0x846c_a68bu32;
    x ^ (x >> 16u32)
}

/// The mask's key ([`crate::dropout::kernel_mask_key`]); zero without dropout.
#[cube]
fn mask_key(draws: &[f32], mask: &MaskParams, #[comptime] dropped: bool) -> u32 {
    let mut key = 0u32;
    if comptime!(dropped) {
        key = mix32(u32::cast_from(draws[mask.slot] * 16_777_216.0f32));
    }
    key
}

/// The mask's value at element `e`, `0` or `1/keep` ([`crate::dropout::kernel_mask`]); `1`
/// without dropout.
#[cube]
fn mask_at(key: u32, e: usize, mask: &MaskParams, #[comptime] dropped: bool) -> f32 {
    let mut value = 1.0f32;
    if comptime!(dropped) {
        value = 0.0f32;
        if mix32(mix32(u32::cast_from(e)) ^ key) < mask.threshold {
            value = mask.scale;
        }
    }
    value
}

/// `z[e] = x[e] + r[e]·m[e]`.
#[cube]
fn summed(
    x: &[f32],
    r: &[f32],
    e: usize,
    key: u32,
    mask: &MaskParams,
    #[comptime] dropped: bool,
) -> f32 {
    x[e] + r[e] * mask_at(key, e, mask, dropped)
}

/// A row's mean and reciprocal standard deviation.
#[derive(CubeType, Clone, Copy)]
struct RowStats {
    mean: f32,
    rstd: f32,
}

/// The statistics of row `row` of `z = x + r·m`, computed by the whole cube.
#[cube]
#[allow(clippy::too_many_arguments)]
fn row_stats(
    x: &[f32],
    r: &[f32],
    shared: &mut Shared<[f32]>,
    row: usize,
    d: usize,
    epsilon: f32,
    key: u32,
    mask: &MaskParams,
    #[comptime] dropped: bool,
) -> RowStats {
    let base = row * d;
    let step = CUBE_DIM as usize;
    let mut sum = 0.0f32;
    let mut c = UNIT_POS as usize;
    while c < d {
        sum += summed(x, r, base + c, key, mask, dropped);
        c += step;
    }
    let mean = cube_sum(shared, sum) / f32::cast_from(d);
    let mut deviation = 0.0f32;
    c = UNIT_POS as usize;
    while c < d {
        let centred = summed(x, r, base + c, key, mask, dropped) - mean;
        deviation += centred * centred;
        c += step;
    }
    let var = cube_sum(shared, deviation) / f32::cast_from(d);
    RowStats {
        mean,
        rstd: 1.0f32 / f32::sqrt(var + epsilon),
    }
}

/// One cube of [`ROW_THREADS`] per row.
#[cube(launch)]
#[allow(clippy::too_many_arguments)]
fn residual_layer_norm_kernel(
    x: &[f32],
    r: &[f32],
    gamma: &[f32],
    beta: &[f32],
    draws: &[f32],
    out: &mut [f32],
    rows: usize,
    d: usize,
    epsilon: f32,
    mask: &MaskParams,
    #[comptime] dropped: bool,
) {
    let mut shared = Shared::<[f32]>::new_slice(ROW_THREADS as usize);
    let row = row_of_cube();
    let key = mask_key(draws, mask, dropped);
    // The same for every thread of the cube, so the barriers inside are reached by all.
    if row < rows {
        let stats = row_stats(x, r, &mut shared, row, d, epsilon, key, mask, dropped);
        let base = row * d;
        let mut c = UNIT_POS as usize;
        while c < d {
            let z = summed(x, r, base + c, key, mask, dropped);
            out[base + c] = (z - stats.mean) * stats.rstd * gamma[c] + beta[c];
            c += CUBE_DIM as usize;
        }
    }
}

/// One cube of [`ROW_THREADS`] per chunk of [`ROWS_PER_CHUNK`] rows, the rows in order: each
/// row's statistics and `∂z` by the whole cube (and `∂r = ∂z·m` with dropout), and the chunk's
/// `Σ g·x̂` and `Σ g` per channel (at `[chunk·d + c]` of `partial_gx` and `partial_g`), each
/// channel's sums kept by the thread that handles the channel in every row.
#[cube(launch)]
#[allow(clippy::too_many_arguments)]
fn layer_norm_backward_kernel(
    x: &[f32],
    r: &[f32],
    gamma: &[f32],
    grad: &[f32],
    draws: &[f32],
    dz: &mut [f32],
    dr: &mut [f32],
    partial_gx: &mut [f32],
    partial_g: &mut [f32],
    rows: usize,
    chunks: usize,
    d: usize,
    epsilon: f32,
    mask: &MaskParams,
    #[comptime] dropped: bool,
) {
    let mut shared = Shared::<[f32]>::new_slice(ROW_THREADS as usize);
    let chunk = row_of_cube();
    let step = CUBE_DIM as usize;
    let key = mask_key(draws, mask, dropped);
    // The same for every thread of the cube, so the barriers inside are reached by all.
    if chunk < chunks {
        let first = chunk * ROWS_PER_CHUNK;
        let last = min(first + ROWS_PER_CHUNK, rows);
        let sums = chunk * d;
        let mut c = UNIT_POS as usize;
        while c < d {
            partial_gx[sums + c] = 0.0f32;
            partial_g[sums + c] = 0.0f32;
            c += step;
        }
        for row in first..last {
            let stats = row_stats(x, r, &mut shared, row, d, epsilon, key, mask, dropped);
            let base = row * d;
            let mut sum_a = 0.0f32;
            let mut sum_ax = 0.0f32;
            c = UNIT_POS as usize;
            while c < d {
                let xhat = (summed(x, r, base + c, key, mask, dropped) - stats.mean) * stats.rstd;
                let a = grad[base + c] * gamma[c];
                sum_a += a;
                sum_ax += a * xhat;
                c += step;
            }
            let n = f32::cast_from(d);
            let mean_a = cube_sum(&mut shared, sum_a) / n;
            let mean_ax = cube_sum(&mut shared, sum_ax) / n;
            c = UNIT_POS as usize;
            while c < d {
                let e = base + c;
                let m = mask_at(key, e, mask, dropped);
                let xhat = (x[e] + r[e] * m - stats.mean) * stats.rstd;
                let g = grad[e];
                let dz_e = stats.rstd * (g * gamma[c] - mean_a - xhat * mean_ax);
                dz[e] = dz_e;
                if comptime!(dropped) {
                    dr[e] = dz_e * m;
                }
                partial_gx[sums + c] += g * xhat;
                partial_g[sums + c] += g;
                c += step;
            }
        }
    }
}

/// One thread per channel: `∂γ[c]` and `∂β[c]`, the chunks' sums added in chunk order.
#[cube(launch)]
fn layer_norm_columns_total_kernel(
    partial_gx: &[f32],
    partial_g: &[f32],
    dgamma: &mut [f32],
    dbeta: &mut [f32],
    chunks: usize,
    d: usize,
) {
    let c = ABSOLUTE_POS;
    if c < d {
        let mut sum_gx = 0.0f32;
        let mut sum_g = 0.0f32;
        for chunk in 0..chunks {
            sum_gx += partial_gx[chunk * d + c];
            sum_g += partial_g[chunk * d + c];
        }
        dgamma[c] = sum_gx;
        dbeta[c] = sum_g;
    }
}

/// The inputs both directions share, in the kernels' layout (f32, contiguous), with the
/// sizes: `rows` rows of `d` channels, `len = rows·d` elements.
struct Prepared {
    /// The dropout's draws and slot (`None`: no dropout).
    dropout: Option<(CubeTensor, DropoutSlot)>,
    client: ComputeClient,
    device: CubeDevice,
    shape: Shape,
    /// The dtype of `x` (and of `∂z`), `gamma`'s, `beta`'s and `residual`'s.
    dtypes: [DType; 4],
    x: CubeTensor,
    r: CubeTensor,
    gamma: CubeTensor,
    beta: CubeTensor,
    d: usize,
    rows: usize,
    len: usize,
    epsilon: f32,
}

impl Prepared {
    fn new(inputs: LayerNormInputs<CubeBackend>) -> Self {
        let shape = inputs.x.shape();
        let d = inputs.gamma.shape().num_elements();
        let len = shape.num_elements();
        Self {
            dropout: inputs.dropout.map(|d| (prepare(d.draws), d.mask)),
            client: inputs.x.client.clone(),
            device: inputs.x.device.clone(),
            dtypes: [
                inputs.x.dtype(),
                inputs.gamma.dtype(),
                inputs.beta.dtype(),
                inputs.residual.dtype(),
            ],
            shape,
            x: prepare(inputs.x),
            r: prepare(inputs.residual),
            gamma: prepare(inputs.gamma),
            beta: prepare(inputs.beta),
            d,
            rows: len / d.max(1),
            len,
            epsilon: inputs.epsilon as f32,
        }
    }
}

impl Prepared {
    /// The draws to bind (`gamma` stands in without dropout: the kernel never reads it then),
    /// the mask's launch parameters, and whether there is a mask.
    fn mask(&self) -> (BufferArg, MaskParamsLaunch, bool) {
        match &self.dropout {
            Some((draws, slot)) => (
                tensor_arg(draws),
                MaskParamsLaunch::new(
                    slot.slot,
                    crate::dropout::keep_threshold(slot.keep),
                    (1.0 / slot.keep) as f32,
                ),
                true,
            ),
            None => (
                tensor_arg(&self.gamma),
                MaskParamsLaunch::new(0, 0, 1.0),
                false,
            ),
        }
    }
}

fn cube_forward(inputs: LayerNormInputs<CubeBackend>) -> FloatTensor<CubeBackend> {
    let _span = tracing::trace_span!("cube_add_layer_norm").entered();
    let p = Prepared::new(inputs);
    let out = p.client.empty(4 * p.len.max(1));
    if p.rows > 0 && p.d > 0 {
        let (draws, mask, dropped) = p.mask();
        residual_layer_norm_kernel::launch(
            &p.client,
            count_cubes(p.rows),
            CubeDim::new_1d(ROW_THREADS),
            tensor_arg(&p.x),
            tensor_arg(&p.r),
            tensor_arg(&p.gamma),
            tensor_arg(&p.beta),
            draws,
            arg(&out, p.len),
            p.rows,
            p.d,
            p.epsilon,
            mask,
            dropped,
        );
    }
    cast_to(tensor_f32(&p.client, &p.device, out, &p.shape), p.dtypes[0])
}

fn cube_backward(
    inputs: LayerNormInputs<CubeBackend>,
    grad: FloatTensor<CubeBackend>,
) -> LayerNormGrads<CubeBackend> {
    let _span = tracing::trace_span!("cube_add_layer_norm_backward").entered();
    let p = Prepared::new(inputs);
    let (client, d, rows, len) = (&p.client, p.d, p.rows, p.len);
    let grad = prepare(grad);
    let dz = client.empty(4 * len.max(1));
    // Without dropout `∂r` is `∂z`; the kernel then writes nothing into this one-element stand-in.
    let dr = match p.dropout {
        Some(_) => client.empty(4 * len.max(1)),
        None => client.empty(4),
    };
    let dgamma = client.empty(4 * d.max(1));
    let dbeta = client.empty(4 * d.max(1));
    if d > 0 {
        // With no rows there is one empty chunk, and the sums are zero.
        let chunks = rows.div_ceil(ROWS_PER_CHUNK).max(1);
        let units = chunks * d;
        let partial_gx = client.empty(4 * units);
        let partial_g = client.empty(4 * units);
        let (draws, mask, dropped) = p.mask();
        layer_norm_backward_kernel::launch(
            client,
            count_cubes(chunks),
            CubeDim::new_1d(ROW_THREADS),
            tensor_arg(&p.x),
            tensor_arg(&p.r),
            tensor_arg(&p.gamma),
            tensor_arg(&grad),
            draws,
            arg(&dz, len),
            arg(&dr, if dropped { len } else { 1 }),
            arg(&partial_gx, units),
            arg(&partial_g, units),
            rows,
            chunks,
            d,
            p.epsilon,
            mask,
            dropped,
        );
        layer_norm_columns_total_kernel::launch(
            client,
            count_1d(d),
            CubeDim::new_1d(THREADS_1D),
            arg(&partial_gx, units),
            arg(&partial_g, units),
            arg(&dgamma, d),
            arg(&dbeta, d),
            chunks,
            d,
        );
    }
    let [z_dtype, gamma_dtype, beta_dtype, _] = p.dtypes;
    let dx = cast_to(tensor_f32(client, &p.device, dz, &p.shape), z_dtype);
    let dr = match p.dropout {
        Some(_) => cast_to(tensor_f32(client, &p.device, dr, &p.shape), p.dtypes[3]),
        None => dx.clone(),
    };
    [
        dx,
        dr,
        cast_to(tensor_f32(client, &p.device, dgamma, &[d]), gamma_dtype),
        cast_to(tensor_f32(client, &p.device, dbeta, &[d]), beta_dtype),
    ]
}

impl AddLayerNormOps for CubeBackend {
    fn add_layer_norm(
        x: FloatTensor<Self>,
        residual: FloatTensor<Self>,
        gamma: FloatTensor<Self>,
        beta: FloatTensor<Self>,
        epsilon: LayerNormEpsilon,
    ) -> FloatTensor<Self> {
        cube_forward(LayerNormInputs::new(
            [x, residual, gamma, beta],
            epsilon,
            None,
        ))
    }
}

impl AddDroppedLayerNormOps for CubeBackend {
    fn add_dropped_layer_norm(
        x: FloatTensor<Self>,
        residual: FloatTensor<Self>,
        gamma: FloatTensor<Self>,
        beta: FloatTensor<Self>,
        draws: FloatTensor<Self>,
        mask: DropoutSlot,
        epsilon: LayerNormEpsilon,
    ) -> FloatTensor<Self> {
        cube_forward(LayerNormInputs::new(
            [x, residual, gamma, beta],
            epsilon,
            Some((draws, mask)),
        ))
    }
}

impl LayerNormKernels for CubeBackend {
    fn layer_norm_forward(inputs: LayerNormInputs<Self>) -> FloatTensor<Self> {
        cube_forward(inputs)
    }

    fn layer_norm_backward(
        inputs: LayerNormInputs<Self>,
        grad: FloatTensor<Self>,
    ) -> LayerNormGrads<Self> {
        cube_backward(inputs, grad)
    }
}
