//! The training SSIM's mean as one custom Burn op on the CPU backends (design.md §9.2).
//!
//! [`SsimOps::ssim_mean`] is a backend extension like the model's ops: implemented for NdArray
//! and Flex (host slices, here) and for `Autodiff<B, C>` over them; CubeCL devices keep the
//! tensor-op composition of [`crate::losses::SsimConfig::ssim_map`], which is also the test
//! reference. As tensor ops the loss is a five-block concatenation, two grouped convolutions, a
//! five-way split and about twenty elementwise ops on the whole image batch (the T·(N+1)
//! renders of a step), each with an autodiff node; on Flex the convolutions' backward alone
//! (`conv_transpose`) was ≈ 24 ms of CPU per quickstart step (BENCHMARKS.md, 2026-11-25: "five
//! more cuts of the serial part").
//!
//! **Forward.** Per image and channel, the five local moments `μx = G∗x`, `μy = G∗y`,
//! `Exx = G∗x²`, `Eyy = G∗y²`, `Exy = G∗xy` (`G` the separable Gaussian window with zero
//! padding, horizontal pass then vertical), then
//! `map = A₁A₂ / (B₁B₂)` with `A₁ = 2μxμy + C₁`, `A₂ = 2(Exy − μxμy) + C₂`,
//! `B₁ = μx² + μy² + C₁`, `B₂ = (Exx − μx²) + (Eyy − μy²) + C₂`, and the mean of `map`.
//!
//! **Backward.** With `D = B₁B₂`, the map's partial derivatives with respect to the moments are
//! `∂map/∂μx = 2μy(A₂ − A₁)/D − map·2μx(B₂ − B₁)/D` (and `x ↔ y`),
//! `∂map/∂Exx = ∂map/∂Eyy = −map·B₁/D`, `∂map/∂Exy = 2A₁/D`. The window with zero padding is a
//! symmetric operator (its taps are symmetric), so its adjoint is itself, and
//! `∂mean/∂x = (G∗∂μx + 2x·G∗∂Exx + y·G∗∂Exy) / count`, the same with `x ↔ y` for the target.
//!
//! The kernels run in the inputs' float type (`f32` in training, `f64` in the precision tests);
//! the mean is summed in `f64`, per plane and then over planes in plane order, so the result does
//! not depend on the thread count.

// NdArray is deprecated in Burn 0.22 in favour of Flex; ndarray is the CI backend the project
// requires (design.md §1.4).
#![allow(deprecated)]

use burn::backend::TensorMetadata;
use burn::backend::autodiff::checkpoint::base::Checkpointer;
use burn::backend::autodiff::checkpoint::strategy::CheckpointStrategy;
use burn::backend::autodiff::grads::Gradients;
use burn::backend::autodiff::ops::{Backward, Ops};
use burn::backend::tensor::FloatTensor;
use burn::backend::{Autodiff, Backend, Flex, NdArray, backend_extension};
use burn::tensor::Element;
use bytemuck::Pod;
use num_traits::Float;
use rayon::prelude::*;

use lifegom_render::in_precision;
use lifegom_render::op_backward::{gradient_per_input, record};
use lifegom_render::readback::{HostLend, cpu_float_from};

/// The window and constants of one SSIM (see [`crate::losses::SsimConfig`]).
#[derive(Debug, Clone, PartialEq)]
pub struct SsimWindow {
    /// The normalised 1-D Gaussian taps; odd length, symmetric.
    pub taps: Vec<f64>,
    /// Luminance stabiliser.
    pub c1: f64,
    /// Contrast stabiliser.
    pub c2: f64,
}

/// The mean SSIM of two `[B, C, H, W]` image batches, as a `[1]` tensor. Gradients flow to
/// both images. The caller checks that the shapes match and that the taps are symmetric.
#[backend_extension(NdArray, Flex, Autodiff)]
pub trait SsimOps: Backend {
    /// `mean(map)` (module docs).
    fn ssim_mean(
        pred: FloatTensor<Self>,
        gt: FloatTensor<Self>,
        window: SsimWindow,
    ) -> FloatTensor<Self>;
}

/// The op's inputs on one backend: what the forward takes and the autodiff node keeps.
#[derive(Debug, Clone)]
pub struct SsimInputs<B: Backend> {
    pred: FloatTensor<B>,
    gt: FloatTensor<B>,
    window: SsimWindow,
}

/// What a backend implements so that `Autodiff<B>` can differentiate the op.
#[doc(hidden)]
pub trait SsimKernels: Backend {
    /// The forward, `[1]`.
    fn ssim_forward(inputs: SsimInputs<Self>) -> FloatTensor<Self>;
    /// `[∂pred, ∂gt]` given the gradient of the mean.
    fn ssim_backward(inputs: SsimInputs<Self>, grad: FloatTensor<Self>) -> [FloatTensor<Self>; 2];
}

/// One `H × W` plane blurred by the separable window with zero padding: horizontal pass, then
/// vertical. Each pass adds one tap at a time over a whole row (`out[c] += g·in[c + t − pad]`
/// over the columns where `c + t − pad` is inside): no per-value bounds test, contiguous rows
/// the compiler vectorises, and each output still sums its taps in tap order.
fn blur<T: Real>(plane: &[T], (h, w): (usize, usize), taps: &[T], out: &mut [T], tmp: &mut [T]) {
    let pad = taps.len() / 2;
    for (src, dst) in plane.chunks_exact(w).zip(tmp.chunks_exact_mut(w)) {
        dst.fill(T::zero());
        for (t, &g) in taps.iter().enumerate() {
            // Output columns c with c + t − pad in [0, w).
            let (from, to) = (pad.saturating_sub(t), (w + pad).saturating_sub(t).min(w));
            if from >= to {
                continue;
            }
            let shifted = &src[from + t - pad..to + t - pad];
            for (d, &v) in dst[from..to].iter_mut().zip(shifted) {
                *d = *d + g * v;
            }
        }
    }
    for (r, dst) in out.chunks_exact_mut(w).enumerate() {
        dst.fill(T::zero());
        for (t, &g) in taps.iter().enumerate() {
            let Some(src) = (r + t).checked_sub(pad).filter(|&src| src < h) else {
                continue;
            };
            for (d, &v) in dst.iter_mut().zip(&tmp[src * w..(src + 1) * w]) {
                *d = *d + g * v;
            }
        }
    }
}

/// The quantities of one plane that the forward and the backward share.
struct PlaneTerms<T> {
    mu_x: Vec<T>,
    mu_y: Vec<T>,
    e_xx: Vec<T>,
    e_yy: Vec<T>,
    e_xy: Vec<T>,
}

impl<T: Real> PlaneTerms<T> {
    fn new(x: &[T], y: &[T], size: (usize, usize), taps: &[T]) -> Self {
        let n = x.len();
        let mut tmp = vec![T::zero(); n];
        let mut blurred = |values: &[T]| {
            let mut out = vec![T::zero(); n];
            blur(values, size, taps, &mut out, &mut tmp);
            out
        };
        let squares = |a: &[T], b: &[T]| a.iter().zip(b).map(|(&a, &b)| a * b).collect::<Vec<_>>();
        Self {
            mu_x: blurred(x),
            mu_y: blurred(y),
            e_xx: blurred(&squares(x, x)),
            e_yy: blurred(&squares(y, y)),
            e_xy: blurred(&squares(x, y)),
        }
    }

    /// `(A₁, A₂, B₁, B₂)` at pixel `i`, for the constants `(C₁, C₂)`.
    fn parts(&self, i: usize, (c1, c2): (T, T)) -> (T, T, T, T) {
        let (mx, my) = (self.mu_x[i], self.mu_y[i]);
        let two = T::one() + T::one();
        (
            two * mx * my + c1,
            two * (self.e_xy[i] - mx * my) + c2,
            mx * mx + my * my + c1,
            (self.e_xx[i] - mx * mx) + (self.e_yy[i] - my * my) + c2,
        )
    }
}

/// The float types the kernels run in (`f32` in training, `f64` in the precision tests).
trait Real: Float + Send + Sync {}
impl<T: Float + Send + Sync> Real for T {}

/// The window's taps and constants in `T`.
fn window_as<T: Real>(window: &SsimWindow) -> (Vec<T>, (T, T)) {
    let cast = |v: f64| T::from(v).expect("a float converts to f32 and f64");
    (
        window.taps.iter().map(|&g| cast(g)).collect(),
        (cast(window.c1), cast(window.c2)),
    )
}

/// `Σ map` over every plane of `x`, `y` (`[planes, h, w]`): each plane's sum in `f64`, then the
/// planes' in plane order.
fn ssim_sum<T: Real>(x: &[T], y: &[T], size: (usize, usize), window: &SsimWindow) -> f64 {
    let n = size.0 * size.1;
    let (taps, constants) = window_as::<T>(window);
    let per_plane: Vec<f64> = x
        .par_chunks(n.max(1))
        .zip(y.par_chunks(n.max(1)))
        .map(|(x, y)| {
            let terms = PlaneTerms::new(x, y, size, &taps);
            (0..x.len())
                .map(|i| {
                    let (a1, a2, b1, b2) = terms.parts(i, constants);
                    (a1 * a2 / (b1 * b2)).to_f64().unwrap_or(f64::NAN)
                })
                .sum::<f64>()
        })
        .collect();
    per_plane.into_iter().sum()
}

/// `(∂Σmap/∂x, ∂Σmap/∂y)` scaled by `scale` (module docs).
fn ssim_sum_grads<T: Real>(
    x: &[T],
    y: &[T],
    size: (usize, usize),
    window: &SsimWindow,
    scale: T,
) -> (Vec<T>, Vec<T>) {
    let n = size.0 * size.1;
    let (taps, constants) = window_as::<T>(window);
    let two = T::one() + T::one();
    let mut gx = vec![T::zero(); x.len()];
    let mut gy = vec![T::zero(); y.len()];
    gx.par_chunks_mut(n.max(1))
        .zip(gy.par_chunks_mut(n.max(1)))
        .zip(x.par_chunks(n.max(1)).zip(y.par_chunks(n.max(1))))
        .for_each(|((gx, gy), (x, y))| {
            let terms = PlaneTerms::new(x, y, size, &taps);
            let mut d_mu_x = vec![T::zero(); n];
            let mut d_mu_y = vec![T::zero(); n];
            let mut d_e_sq = vec![T::zero(); n];
            let mut d_e_xy = vec![T::zero(); n];
            for i in 0..n {
                let (a1, a2, b1, b2) = terms.parts(i, constants);
                let d = b1 * b2;
                let map = a1 * a2 / d;
                let (mx, my) = (terms.mu_x[i], terms.mu_y[i]);
                d_mu_x[i] = scale * (two * my * (a2 - a1) - map * two * mx * (b2 - b1)) / d;
                d_mu_y[i] = scale * (two * mx * (a2 - a1) - map * two * my * (b2 - b1)) / d;
                d_e_sq[i] = scale * (-map * b1 / d);
                d_e_xy[i] = scale * (two * a1 / d);
            }
            // The window is its own adjoint (symmetric taps, zero padding).
            let mut tmp = vec![T::zero(); n];
            let mut blurred = |values: &[T]| {
                let mut out = vec![T::zero(); n];
                blur(values, size, &taps, &mut out, &mut tmp);
                out
            };
            let (b_mu_x, b_mu_y) = (blurred(&d_mu_x), blurred(&d_mu_y));
            let (b_sq, b_xy) = (blurred(&d_e_sq), blurred(&d_e_xy));
            for i in 0..n {
                gx[i] = b_mu_x[i] + two * x[i] * b_sq[i] + y[i] * b_xy[i];
                gy[i] = b_mu_y[i] + two * y[i] * b_sq[i] + x[i] * b_xy[i];
            }
        });
    (gx, gy)
}

/// `(planes, (h, w))` of a `[B, C, H, W]` shape.
fn planes_of(shape: &[usize]) -> (usize, (usize, usize)) {
    let [b, c, h, w] = shape else {
        panic!("ssim: images must be [B, C, H, W], got {shape:?}");
    };
    (b * c, (*h, *w))
}

fn cpu_forward<B: HostLend>(inputs: SsimInputs<B>) -> FloatTensor<B> {
    in_precision!(inputs.pred.dtype(), cpu_forward_in(inputs))
}

fn cpu_forward_in<B: HostLend, T: Real + Element + Pod>(inputs: SsimInputs<B>) -> FloatTensor<B> {
    let (device, dtype) = (inputs.pred.device(), inputs.pred.dtype());
    let (planes, size) = planes_of(&inputs.pred.shape());
    let x = B::lend_float::<T>("ssim prediction", &inputs.pred);
    let y = B::lend_float::<T>("ssim target", &inputs.gt);
    let count = (planes * size.0 * size.1).max(1) as f64;
    let mean = ssim_sum(&x, &y, size, &inputs.window) / count;
    cpu_float_from::<B, f64>(vec![mean], [1], dtype, &device)
}

fn cpu_backward<B: HostLend>(inputs: SsimInputs<B>, grad: FloatTensor<B>) -> [FloatTensor<B>; 2] {
    in_precision!(inputs.pred.dtype(), cpu_backward_in(inputs, grad))
}

fn cpu_backward_in<B: HostLend, T: Real + Element + Pod>(
    inputs: SsimInputs<B>,
    grad: FloatTensor<B>,
) -> [FloatTensor<B>; 2] {
    let device = inputs.pred.device();
    let shapes = [&inputs.pred, &inputs.gt].map(|t| (t.shape(), t.dtype()));
    let (planes, size) = planes_of(&inputs.pred.shape());
    let upstream = B::lend_float::<f64>("ssim gradient", &grad);
    let x = B::lend_float::<T>("ssim prediction", &inputs.pred);
    let y = B::lend_float::<T>("ssim target", &inputs.gt);
    let count = (planes * size.0 * size.1).max(1) as f64;
    let scale = T::from(upstream[0] / count).expect("a float converts to f32 and f64");
    let (gx, gy) = ssim_sum_grads(&x, &y, size, &inputs.window, scale);
    let [(sx, tx), (sy, ty)] = shapes;
    [
        cpu_float_from::<B, T>(gx, sx, tx, &device),
        cpu_float_from::<B, T>(gy, sy, ty, &device),
    ]
}

/// Implements the op for a CPU backend through the shared slice functions.
macro_rules! cpu_ssim_backend {
    ($backend:ty) => {
        impl SsimOps for $backend {
            fn ssim_mean(
                pred: FloatTensor<Self>,
                gt: FloatTensor<Self>,
                window: SsimWindow,
            ) -> FloatTensor<Self> {
                cpu_forward::<Self>(SsimInputs { pred, gt, window })
            }
        }

        impl SsimKernels for $backend {
            fn ssim_forward(inputs: SsimInputs<Self>) -> FloatTensor<Self> {
                cpu_forward::<Self>(inputs)
            }

            fn ssim_backward(
                inputs: SsimInputs<Self>,
                grad: FloatTensor<Self>,
            ) -> [FloatTensor<Self>; 2] {
                cpu_backward::<Self>(inputs, grad)
            }
        }
    };
}

cpu_ssim_backend!(NdArray);
cpu_ssim_backend!(Flex);

#[derive(Debug)]
struct SsimBackward;

impl<B: SsimKernels> Backward<B, 2> for SsimBackward {
    type State = SsimInputs<B>;

    fn backward(
        self,
        ops: Ops<Self::State, 2>,
        grads: &mut Gradients,
        _checkpointer: &mut Checkpointer,
    ) {
        gradient_per_input::<B, _, 2>(ops, grads, B::ssim_backward);
    }
}

impl<B: SsimOps + SsimKernels, C: CheckpointStrategy> SsimOps for Autodiff<B, C> {
    fn ssim_mean(
        pred: FloatTensor<Self>,
        gt: FloatTensor<Self>,
        window: SsimWindow,
    ) -> FloatTensor<Self> {
        let (pred, pred_node) = pred.into_parts();
        let (gt, gt_node) = gt.into_parts();
        let inputs = SsimInputs { pred, gt, window };
        record::<B, C, _, _, 2>(SsimBackward, [pred_node, gt_node], inputs, B::ssim_forward)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The blur of a unit impulse is the 2-D window (outer product of the taps), cut at the
    /// border; blurring is its own adjoint: `⟨G a, b⟩ = ⟨a, G b⟩`.
    #[test]
    fn blur_is_the_window_and_self_adjoint() {
        let taps = [0.25, 0.5, 0.25];
        let (h, w) = (4usize, 5usize);
        let mut impulse = vec![0.0; h * w];
        impulse[w + 1] = 1.0;
        let (mut out, mut tmp) = (vec![0.0; h * w], vec![0.0; h * w]);
        blur(&impulse, (h, w), &taps, &mut out, &mut tmp);
        for r in 0..h {
            for c in 0..w {
                let tap = |d: isize| {
                    usize::try_from(d + 1)
                        .ok()
                        .and_then(|i| taps.get(i))
                        .copied()
                        .unwrap_or(0.0)
                };
                let expect = tap(r as isize - 1) * tap(c as isize - 1);
                assert!((out[r * w + c] - expect).abs() < 1e-15, "({r},{c})");
            }
        }
        let mut rng = lifegom_render::rng::Rng::new(4);
        let a: Vec<f64> = (0..h * w).map(|_| rng.range(-1.0, 1.0)).collect();
        let b: Vec<f64> = (0..h * w).map(|_| rng.range(-1.0, 1.0)).collect();
        let (mut ga, mut gb) = (vec![0.0; h * w], vec![0.0; h * w]);
        blur(&a, (h, w), &taps, &mut ga, &mut tmp);
        blur(&b, (h, w), &taps, &mut gb, &mut tmp);
        let dot = |p: &[f64], q: &[f64]| p.iter().zip(q).map(|(p, q)| p * q).sum::<f64>();
        assert!((dot(&ga, &b) - dot(&a, &gb)).abs() < 1e-12);
    }
}
