//! The channel norm's kernels on Burn's CubeCL backend (see [`super`]), for `[N, C, H, W]`
//! images and the per-channel `γ`, `β`. The images are read in the layout they come in when it
//! is a permutation of a contiguous one (Burn's convolutions hand channels-last images back),
//! and the outputs are written in that layout: copying them to the row-major order and back
//! would cost two launches per pass each way. Each thread computes its channel's
//! `s = γ/√(σ²+ε)` and `t = β − μ·s` itself, in the order of the composed ops (`γ` divided by
//! the root, then `β − μ·s`, then `x·s + t`), so both give the same values.
//!
//! - `channel_norm_forward_kernel`, one thread per element.
//! - `channel_norm_partials_kernel`, one thread per image, channel and chunk of
//!   [`PIXELS_PER_CHUNK`] pixels: it writes `∂x = g'·s` for its pixels (`g'` is `g` where the
//!   activation passes it) and its sums of `g'·x` and `g'`.
//! - `channel_norm_totals_kernel`, one thread per channel: the partial sums of up to four passes
//!   added in pass and row order (deterministic), then `∂β = Σg'` and
//!   `∂γ = (Σg'·x − μ·Σg')/√(σ²+ε)` (`t` depends on `s` too).

use burn::backend::TensorMetadata;
use burn::backend::tensor::FloatTensor;
use burn::tensor::{DType, Shape};
use burn_cubecl::CubeBackend;
use burn_cubecl::cubecl;
use burn_cubecl::cubecl::prelude::*;
use burn_cubecl::tensor::CubeTensor;
use lifegom_render::cube::host::{
    THREADS_1D, arg, cast_to, count_1d, prepare, tensor_arg, tensor_f32,
};
use lifegom_render::cube::image::{ImageLayout, dense, image_layout};

use super::op::{ChannelNormKernels, ChannelNormOps, NormLedger, TOTAL_PARTS};
use crate::activation::Activation;
use crate::activation::cube::{activate, activation_gradient};

/// Pixels of one image and channel each partial sum covers.
const PIXELS_PER_CHUNK: usize = 256;

/// Length of one pass's partial sums for images of `shape` `[N, C, H, W]`.
pub(super) fn partial_len(shape: &Shape) -> usize {
    let (n, c, hw) = (shape[0], shape[1], shape[2] * shape[3]);
    n * hw.div_ceil(PIXELS_PER_CHUNK).max(1) * c * 2
}

/// Channel `c`'s `s = γ/√(σ²+ε)`.
#[cube]
fn scale_of(gamma: &[f32], var: &[f32], c: usize, eps: f32) -> f32 {
    gamma[c] / f32::sqrt(var[c] + eps)
}

/// Channel `c`'s `t = β − μ·s`.
#[cube]
fn shift_of(beta: &[f32], mean: &[f32], c: usize, s: f32) -> f32 {
    beta[c] - mean[c] * s
}

#[cube(launch)]
#[allow(clippy::too_many_arguments)]
fn channel_norm_forward_kernel(
    x: &[f32],
    gamma: &[f32],
    beta: &[f32],
    mean: &[f32],
    var: &[f32],
    out: &mut [f32],
    units: usize,
    channels: usize,
    channel_stride: usize,
    eps: f32,
    #[comptime] activation: Activation,
) {
    // `e` walks the buffer: in a permuted contiguous layout the channel of offset `e` is
    // `(e / stride_c) mod C`, and the output keeps the input's layout.
    let e = ABSOLUTE_POS;
    if e < units {
        let c = (e / channel_stride) % channels;
        let s = scale_of(gamma, var, c, eps);
        let t = shift_of(beta, mean, c, s);
        out[e] = activate(x[e] * s + t, activation);
    }
}

#[cube(launch)]
#[allow(clippy::too_many_arguments)]
fn channel_norm_partials_kernel(
    x: &[f32],
    gamma: &[f32],
    beta: &[f32],
    mean: &[f32],
    var: &[f32],
    grad: &[f32],
    dx: &mut [f32],
    partial: &mut [f32],
    units: usize,
    channels: usize,
    pixels: usize,
    width: usize,
    chunks: usize,
    chunk_len: usize,
    eps: f32,
    #[comptime] activation: Activation,
    x_layout: &ImageLayout,
    grad_layout: &ImageLayout,
) {
    let unit = ABSOLUTE_POS;
    if unit < units {
        let c = unit % channels;
        let row = unit / channels;
        let n = row / chunks;
        let chunk = row % chunks;
        let s = scale_of(gamma, var, c, eps);
        let t = shift_of(beta, mean, c, s);
        let start = chunk * chunk_len;
        let end = usize::min(start + chunk_len, pixels);
        let mut gx = 0.0f32;
        let mut g_sum = 0.0f32;
        for i in start..end {
            let at = x_layout.at_pixel(n, c, i, width);
            let xi = x[at];
            let g = activation_gradient(
                xi * s + t,
                grad[grad_layout.at_pixel(n, c, i, width)],
                activation,
            );
            dx[at] = g * s;
            gx += g * xi;
            g_sum += g;
        }
        partial[unit * 2] = gx;
        partial[unit * 2 + 1] = g_sum;
    }
}

/// Sum `j` (0: `g'·x`, 1: `g'`) of rows `0..rows` of one pass's partial sums for channel `c`,
/// added onto `acc`.
#[cube]
fn add_rows(part: &[f32], rows: usize, channels: usize, c: usize, j: usize, acc: f32) -> f32 {
    let mut total = acc;
    for row in 0..rows {
        total += part[(row * channels + c) * 2 + j];
    }
    total
}

#[cube(launch)]
#[allow(clippy::too_many_arguments)]
fn channel_norm_totals_kernel(
    part0: &[f32],
    part1: &[f32],
    part2: &[f32],
    part3: &[f32],
    mean: &[f32],
    var: &[f32],
    sums: &mut [f32],
    dgamma: &mut [f32],
    dbeta: &mut [f32],
    rows0: usize,
    rows1: usize,
    rows2: usize,
    rows3: usize,
    channels: usize,
    eps: f32,
) {
    let c = ABSOLUTE_POS;
    if c < channels {
        let mut gx = add_rows(part0, rows0, channels, c, 0, 0.0f32);
        gx = add_rows(part1, rows1, channels, c, 0, gx);
        gx = add_rows(part2, rows2, channels, c, 0, gx);
        gx = add_rows(part3, rows3, channels, c, 0, gx);
        let mut g = add_rows(part0, rows0, channels, c, 1, 0.0f32);
        g = add_rows(part1, rows1, channels, c, 1, g);
        g = add_rows(part2, rows2, channels, c, 1, g);
        g = add_rows(part3, rows3, channels, c, 1, g);
        sums[c * 2] = gx;
        sums[c * 2 + 1] = g;
        dbeta[c] = g;
        dgamma[c] = (gx - mean[c] * g) / f32::sqrt(var[c] + eps);
    }
}

/// A tensor over `handle` laid out as `like`.
fn laid_out_as(like: &CubeTensor, handle: cubecl::server::Handle) -> CubeTensor {
    CubeTensor::new(
        like.client.clone(),
        handle,
        (*like.meta).clone(),
        like.device.clone(),
        DType::F32,
    )
}

/// `[N, C, H·W]` of an image tensor.
fn image_sizes(x: &FloatTensor<CubeBackend>) -> (usize, usize, usize) {
    let shape = x.shape();
    assert_eq!(shape.num_dims(), 4, "channel norm over [N, C, H, W] images");
    (shape[0], shape[1], shape[2] * shape[3])
}

impl ChannelNormOps for CubeBackend {
    fn channel_norm_parameters(
        gamma: FloatTensor<Self>,
        _beta: FloatTensor<Self>,
        _mean: FloatTensor<Self>,
        _var: FloatTensor<Self>,
        _epsilon: f32,
        _ledger: NormLedger,
    ) -> FloatTensor<Self> {
        gamma
    }

    fn channel_norm(
        x: FloatTensor<Self>,
        params: FloatTensor<Self>,
        beta: FloatTensor<Self>,
        mean: FloatTensor<Self>,
        var: FloatTensor<Self>,
        epsilon: f32,
        activation: Activation,
        _ledger: NormLedger,
    ) -> FloatTensor<Self> {
        let dtype = x.dtype();
        let (n, c, hw) = image_sizes(&x);
        let client = x.client.clone();
        let x = dense(x);
        let [gamma, beta, mean, var] = [params, beta, mean, var].map(prepare);
        let units = n * c * hw;
        let channel_stride = x.meta.strides()[1].max(1);
        let out = client.empty(4 * units.max(1));
        if units > 0 {
            channel_norm_forward_kernel::launch(
                &client,
                count_1d(units),
                CubeDim::new_1d(THREADS_1D),
                tensor_arg(&x),
                tensor_arg(&gamma),
                tensor_arg(&beta),
                tensor_arg(&mean),
                tensor_arg(&var),
                arg(&out, units),
                units,
                c,
                channel_stride,
                epsilon,
                activation,
            );
        }
        cast_to(laid_out_as(&x, out), dtype)
    }
}

impl ChannelNormKernels for CubeBackend {
    fn channel_norm_backward(
        x: FloatTensor<Self>,
        params: FloatTensor<Self>,
        beta: FloatTensor<Self>,
        mean: FloatTensor<Self>,
        var: FloatTensor<Self>,
        grad: FloatTensor<Self>,
        epsilon: f32,
        activation: Activation,
    ) -> (FloatTensor<Self>, FloatTensor<Self>) {
        let dtype = x.dtype();
        let shape = x.shape();
        let width = shape[3];
        let (n, c, hw) = image_sizes(&x);
        let (client, device) = (x.client.clone(), x.device.clone());
        let (x, grad) = (dense(x), dense(grad));
        let [gamma, beta, mean, var] = [params, beta, mean, var].map(prepare);
        let chunks = hw.div_ceil(PIXELS_PER_CHUNK).max(1);
        let units = n * chunks * c;
        let dx = client.empty(4 * (n * c * hw).max(1));
        let len = partial_len(&shape);
        let partial = client.empty(4 * len.max(1));
        if units > 0 {
            channel_norm_partials_kernel::launch(
                &client,
                count_1d(units),
                CubeDim::new_1d(THREADS_1D),
                tensor_arg(&x),
                tensor_arg(&gamma),
                tensor_arg(&beta),
                tensor_arg(&mean),
                tensor_arg(&var),
                tensor_arg(&grad),
                arg(&dx, (n * c * hw).max(1)),
                arg(&partial, len.max(1)),
                units,
                c,
                hw,
                width,
                chunks,
                PIXELS_PER_CHUNK,
                epsilon,
                activation,
                image_layout(&x),
                image_layout(&grad),
            );
        }
        (
            cast_to(laid_out_as(&x, dx), dtype),
            tensor_f32(&client, &device, partial, &[len]),
        )
    }

    fn channel_norm_totals(
        partials: Vec<FloatTensor<Self>>,
        mean: FloatTensor<Self>,
        var: FloatTensor<Self>,
        epsilon: f32,
    ) -> (FloatTensor<Self>, FloatTensor<Self>, FloatTensor<Self>) {
        assert!(
            !partials.is_empty() && partials.len() <= TOTAL_PARTS,
            "1 to {TOTAL_PARTS} passes' partial sums"
        );
        let dtype = mean.dtype();
        let c = mean.shape()[0];
        let (client, device) = (mean.client.clone(), mean.device.clone());
        let [mean, var] = [mean, var].map(prepare);
        let parts: Vec<_> = partials.into_iter().map(prepare).collect();
        let rows: Vec<usize> = (0..TOTAL_PARTS)
            .map(|i| parts.get(i).map_or(0, |p| p.shape()[0] / (2 * c).max(1)))
            .collect();
        // Unused parts are bound to the first one and read zero rows of it.
        let part = |i: usize| tensor_arg(parts.get(i).unwrap_or(&parts[0]));
        let sums = client.empty(4 * (2 * c).max(1));
        let [dgamma, dbeta] = [(); 2].map(|()| client.empty(4 * c.max(1)));
        if c > 0 {
            channel_norm_totals_kernel::launch(
                &client,
                count_1d(c),
                CubeDim::new_1d(THREADS_1D),
                part(0),
                part(1),
                part(2),
                part(3),
                tensor_arg(&mean),
                tensor_arg(&var),
                arg(&sums, 2 * c),
                arg(&dgamma, c),
                arg(&dbeta, c),
                rows[0],
                rows[1],
                rows[2],
                rows[3],
                c,
                epsilon,
            );
        }
        (
            tensor_f32(&client, &device, sums, &[2 * c]),
            cast_to(tensor_f32(&client, &device, dgamma, &[c]), dtype),
            cast_to(tensor_f32(&client, &device, dbeta, &[c]), dtype),
        )
    }
}
