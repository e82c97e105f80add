//! Dropout with host-drawn masks on the CPU backends (design.md §7.4).
//!
//! The fusion layers apply dropout (p = 0.1) four times per call, six calls per training step:
//! about 8.5 million mask elements per quickstart step. Burn's `Dropout` draws each element from
//! a Bernoulli distribution through ChaCha12, building the sampler anew per element, and then
//! multiplies twice (mask, then `1/keep`). On Flex that cost ~10 % of a training step (the
//! profile in BENCHMARKS.md, "Training step profile").
//!
//! [`dropout`] keeps Burn's semantics (training flag, autodiff devices only, `x·m/keep` with
//! `m ~ Bernoulli(keep)`) and, on the CPU backends, draws the mask on the host with the
//! workspace's SplitMix64 ([`lifegom_render::rng`]): 32 random bits per element compared with
//! `keep·2³²`, the mask already scaled to `{0, 1/keep}`, one multiply. `x·(1/keep)` equals
//! Burn's `(x·1)·(1/keep)` bit for bit where an element is kept. The stream's seed is four
//! 16-bit draws from the device's own RNG, so `Device::seed` (which the trainer sets per step)
//! still fixes every mask. On CubeCL devices the mask is drawn on the device as Burn does (a host
//! draw would cost an upload per call, and the GPU's generator is not the bottleneck there).
//!
//! **Masks drawn inside a kernel.** Where dropout feeds a residual LayerNorm on a CubeCL device
//! (the fusion layers, `crate::fusion`), Burn's dropout is two launches per mask (its generator,
//! then the compare and multiply) and one more backward. There the LayerNorm's kernels draw the
//! mask themselves from a counter-based hash ([`kernel_mask_bits`]): element `e` of the dropped
//! tensor is kept when `mix(mix(e) ⊕ key) < keep·2³²`, `key` being [`kernel_mask_key`] of one
//! uniform draw from the device's RNG (a small `Tensor::random` per layer, so `Device::seed`
//! still fixes every mask). The backward recomputes the same bits: nothing is stored. `mix` is
//! a 32-bit integer finaliser (xor-shift, multiply, three rounds), a bijection whose output bits
//! each depend on every input bit; the kept fraction and independence from the index are tested
//! below. The host functions here are the kernels' reference (`crate::fusion::op`'s CPU
//! implementation uses them).

use burn::nn::Dropout;
use burn::tensor::{Distribution, Tensor, TensorData};
use lifegom_render::device::runs_on_host;
use lifegom_render::readback;
use lifegom_render::rng::Rng;
use rayon::prelude::*;

/// Where a host-drawn dropout mask's randomness comes from.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum MaskSeed {
    /// Drawn from the device's RNG when the mask is needed (Burn's rule decides whether one
    /// is: training flag, autodiff device, `prob > 0`).
    Device,
    /// A seed drawn earlier with [`draw_seed`]: the caller has decided this is a training pass
    /// (the layer may be an inference copy on a non-autodiff device), and the mask is the one
    /// [`MaskSeed::Device`] would have drawn at that point of the RNG stream.
    Given(u64),
    /// No mask: the identity (a pass in which [`MaskSeed::Device`] would draw none).
    Off,
}

/// `layer` applied to `input` (module docs): the identity unless the layer is in training mode
/// on an autodiff device with `prob > 0`.
pub fn dropout<const D: usize>(layer: &Dropout, input: Tensor<D>) -> Tensor<D> {
    dropout_with(layer, input, MaskSeed::Device)
}

/// Whether [`dropout`] on `device` draws a host mask (and so one seed from the device's RNG).
pub fn draws_host_mask(layer: &Dropout, device: &burn::tensor::Device) -> bool {
    layer.training.is_enabled() && device.is_autodiff() && layer.prob > 0.0 && runs_on_host(device)
}

/// The seed of the next host mask on `device`: four 16-bit draws from its RNG, exactly what
/// [`dropout`] draws when it needs one.
pub fn draw_seed(device: &burn::tensor::Device) -> u64 {
    let draws = Tensor::<1>::random([4], Distribution::Uniform(0.0, 1.0), device);
    readback::read::<f32, 1, _>("dropout seed", draws)
        .expect("a host tensor reads back")
        .iter()
        .fold(0u64, |acc, &u| {
            (acc << 16) | ((u * 65_536.0) as u64 & 0xffff)
        })
}

/// The seeds of the masks `layers` draw in one training call on `device`, drawn now from the
/// device's RNG in the same order ([`MaskSeed::Off`] where a layer draws none). `None` on a
/// CubeCL device, whose masks are drawn on the device as the call goes.
pub fn host_mask_seeds<const N: usize>(
    layers: [&Dropout; N],
    device: &burn::tensor::Device,
) -> Option<[MaskSeed; N]> {
    if !runs_on_host(device) {
        return None;
    }
    Some(layers.map(|layer| {
        if draws_host_mask(layer, device) {
            MaskSeed::Given(draw_seed(device))
        } else {
            MaskSeed::Off
        }
    }))
}

/// Whether [`dropout_with`]`(layer, _, seed)` is the identity whatever the device: no mask
/// (`Off`), or a given seed with no positive `prob`. What a `Device` seed does depends on the
/// device and the training flag, so it does not count.
pub fn drops_nothing(layer: &Dropout, seed: MaskSeed) -> bool {
    match seed {
        MaskSeed::Off => true,
        MaskSeed::Given(_) => layer.prob <= 0.0 || layer.prob.is_nan(),
        MaskSeed::Device => false,
    }
}

/// [`dropout`] with the mask's seed chosen by the caller.
pub fn dropout_with<const D: usize>(
    layer: &Dropout,
    input: Tensor<D>,
    seed: MaskSeed,
) -> Tensor<D> {
    let device = input.device();
    let seed = match seed {
        _ if drops_nothing(layer, seed) => return input,
        MaskSeed::Given(seed) => seed,
        MaskSeed::Device if draws_host_mask(layer, &device) => draw_seed(&device),
        // Burn's own layer applies the same rule: the identity off training, autodiff or
        // `prob > 0`, and on CubeCL devices its mask drawn on the device. (`Off` drops
        // nothing and returned above.)
        MaskSeed::Device | MaskSeed::Off => return layer.forward(input),
    };
    let keep = 1.0 - layer.prob;
    let mask = host_mask(input.shape().num_elements(), keep, seed);
    let mask = Tensor::<1>::from_data(
        TensorData::new(mask, [input.shape().num_elements()]),
        (&device, input.dtype()),
    )
    .reshape(input.shape());
    input * mask
}

/// Whether `layer` on `device` would draw a mask on a CubeCL device (Burn's rule: training flag,
/// autodiff device, `prob > 0`); there a residual LayerNorm can draw it inside its kernel.
pub fn draws_device_mask(layer: &Dropout, device: &burn::tensor::Device) -> bool {
    layer.training.is_enabled() && device.is_autodiff() && layer.prob > 0.0 && !runs_on_host(device)
}

/// The threshold below which 32 random bits keep an element: `keep·2³²`, rounded, at most
/// `u32::MAX`.
pub fn keep_threshold(keep: f64) -> u32 {
    (keep * 4_294_967_296.0).round().min(u32::MAX as f64) as u32
}

/// Draws scale to 24-bit keys: the uniform draws of Burn's generator are multiples of `2⁻²⁴`
/// or finer, so `draw·2²⁴` keeps their leading 24 bits exactly.
const DRAW_SCALE: f32 = 16_777_216.0;

/// The key of a kernel-drawn mask seeded by the uniform draw `draw` in `[0, 1)` (module docs).
pub fn kernel_mask_key(draw: f32) -> u32 {
    mix32((draw * DRAW_SCALE) as u32)
}

/// The 32 random bits of element `index` of the mask with key `key` (module docs).
pub fn kernel_mask_bits(key: u32, index: u32) -> u32 {
    mix32(mix32(index) ^ key)
}

/// The 32-bit finaliser the kernel masks hash with (the "lowbias32" constants, public domain).
/// The kernels in `crate::fusion::cube` repeat it in CubeCL.
pub fn mix32(mut x: u32) -> u32 {
    x ^= x >> 16;
    x = x.wrapping_mul(0x7feb_352d);
    x ^= x >> 15;
    x = x.wrapping_mul(0x846c_a68b);
    x ^ (x >> 16)
}

/// The `n` values of a kernel-drawn mask, `{0, 1/keep}`, on the host: the reference of the
/// CubeCL kernels and the CPU implementation of their op.
pub fn kernel_mask(n: usize, keep: f64, draw: f32) -> Vec<f32> {
    let (key, threshold, scale) = (
        kernel_mask_key(draw),
        keep_threshold(keep),
        (1.0 / keep) as f32,
    );
    (0..n)
        .map(|e| {
            if kernel_mask_bits(key, e as u32) < threshold {
                scale
            } else {
                0.0
            }
        })
        .collect()
}

/// Mask values per rayon task of [`host_mask`]: large enough to amortise a task, small enough
/// that the fusion's ~0.5 M-element masks split over two cores.
const MASK_VALUES_PER_TASK: usize = 1 << 15;

/// `n` mask values in `{0, 1/keep}`, each `1/keep` with probability `keep` (to 2⁻³²).
///
/// Value `2i` is the low and value `2i + 1` the high half of the stream's draw `i`. Tasks start
/// their own copy of the stream at their first draw ([`Rng::skipped`]), so the mask is the same
/// whatever the thread count: the one a single thread drawing in order makes.
fn host_mask(n: usize, keep: f64, seed: u64) -> Vec<f32> {
    let threshold = keep_threshold(keep);
    let scale = (1.0 / keep) as f32;
    let stream = Rng::new(seed);
    let draw = |bits: u32| if bits < threshold { scale } else { 0.0 };
    let mut mask = vec![0.0f32; n];
    mask.par_chunks_mut(MASK_VALUES_PER_TASK)
        .enumerate()
        .for_each(|(task, chunk)| {
            let mut rng = stream.skipped((task * MASK_VALUES_PER_TASK / 2) as u64);
            for pair in chunk.chunks_mut(2) {
                let bits = rng.next_u64();
                pair[0] = draw(bits as u32);
                if let Some(high) = pair.get_mut(1) {
                    *high = draw((bits >> 32) as u32);
                }
            }
        });
    mask
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::nn::DropoutConfig;
    use burn::tensor::Device;

    use lifegom_render::testing::read;

    /// The kept fraction is `keep` (within 5σ), kept values are `x/keep`, and the same device
    /// seed gives the same mask.
    fn statistics_and_seeding(device: &Device) {
        let ad = device.clone().autodiff();
        let layer = DropoutConfig::new(0.1).init();
        let n = 200_000;
        let x = Tensor::<2>::ones([n / 100, 100], &ad);
        ad.seed(7);
        let a = read(dropout(&layer, x.clone()));
        ad.seed(7);
        let b = read(dropout(&layer, x.clone()));
        assert_eq!(a, b, "the device seed fixes the mask");
        let kept = a.iter().filter(|&&v| v != 0.0).count() as f64 / n as f64;
        let sigma = (0.9 * 0.1 / n as f64).sqrt();
        assert!((kept - 0.9).abs() < 5.0 * sigma, "kept fraction {kept}");
        let scale = (1.0f64 / 0.9) as f32;
        assert!(a.iter().all(|&v| v == 0.0 || v == scale));
        let c = read(dropout(&layer, x));
        assert_ne!(a, c, "a new draw without re-seeding");
    }

    /// Off the autodiff device, or with the layer frozen, dropout is the identity; the gradient
    /// of a kept element is `1/keep` and of a dropped one 0.
    fn identity_and_gradient(device: &Device) {
        let layer = DropoutConfig::new(0.25).init();
        let x = Tensor::<1>::from_floats([1.0, 2.0, 3.0], device);
        assert_eq!(read(dropout(&layer, x.clone())), read(x));
        let ad = device.clone().autodiff();
        let x = Tensor::<1>::ones([1000], &ad).require_grad();
        let y = dropout(&layer, x.clone());
        let grads = y.clone().sum().backward();
        let g = read(x.grad(&grads).expect("x takes part"));
        assert_eq!(g, read(y), "d(x·m)/dx = m and x = 1");
    }

    /// A kernel mask keeps `keep` of its elements (within 5σ), in runs no longer than chance
    /// makes them (neighbouring indices are not correlated), and two keys give different masks
    /// that agree where independent masks would (within 5σ).
    #[test]
    fn kernel_masks_keep_their_fraction_independently() {
        let (n, keep) = (1_000_000usize, 0.9);
        let a = kernel_mask(n, keep, 0.25);
        let b = kernel_mask(n, keep, 0.5);
        let kept = |m: &[f32]| m.iter().filter(|&&v| v != 0.0).count() as f64 / n as f64;
        let sigma = (keep * (1.0 - keep) / n as f64).sqrt();
        for m in [&a, &b] {
            assert!((kept(m) - keep).abs() < 5.0 * sigma, "kept {}", kept(m));
        }
        // Pairs of neighbours both dropped: (1 − keep)² of them if independent.
        let both = a.windows(2).filter(|w| w[0] == 0.0 && w[1] == 0.0).count() as f64;
        let expected = (1.0 - keep).powi(2) * (n - 1) as f64;
        assert!(
            (both - expected).abs() < 5.0 * expected.sqrt(),
            "{both} vs {expected}"
        );
        let agree = a.iter().zip(&b).filter(|(x, y)| x == y).count() as f64 / n as f64;
        let p = keep * keep + (1.0 - keep) * (1.0 - keep);
        let sigma = (p * (1.0 - p) / n as f64).sqrt();
        assert!((agree - p).abs() < 5.0 * sigma, "agreement {agree} vs {p}");
        let scale = (1.0 / keep) as f32;
        assert!(a.iter().all(|&v| v == 0.0 || v == scale));
    }

    /// The parallel draw is the single stream drawn in order, low half then high half of each
    /// draw, at lengths around the task boundaries (odd lengths end on a low half).
    #[test]
    fn host_mask_is_the_sequential_stream() {
        let keep = 0.9;
        let threshold = (keep * 4_294_967_296.0f64).round() as u32;
        let scale = (1.0 / keep) as f32;
        for n in [
            0,
            1,
            2,
            MASK_VALUES_PER_TASK - 1,
            MASK_VALUES_PER_TASK,
            MASK_VALUES_PER_TASK + 1,
            3 * MASK_VALUES_PER_TASK + 5,
        ] {
            let mut rng = Rng::new(5);
            let sequential: Vec<f32> = (0..n.div_ceil(2))
                .flat_map(|_| {
                    let bits = rng.next_u64();
                    [bits as u32, (bits >> 32) as u32]
                })
                .take(n)
                .map(|b| if b < threshold { scale } else { 0.0 })
                .collect();
            assert_eq!(host_mask(n, keep, 5), sequential, "n = {n}");
        }
    }

    #[test]
    fn host_mask_matches_keep_probability_exactly_at_the_ends() {
        assert!(host_mask(1001, 1.0, 3).iter().all(|&v| v == 1.0));
        assert_eq!(host_mask(1001, 0.5, 3).len(), 1001);
    }

    lifegom_render::cpu_backend_tests!(dropout_statistics_and_seeding => statistics_and_seeding);
    lifegom_render::cpu_backend_tests!(dropout_identity_and_gradient => identity_and_gradient);
}
