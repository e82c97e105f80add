//! A frozen BatchNorm's per-channel affine, computed once per set of statistics on CubeCL
//! devices (design.md §7.5).
//!
//! The Point Transformer's BatchNorms are frozen (`γ`, `β` take no gradient, the running
//! statistics never update), and a training step or a reconstruction applies 31 of them that are
//! not folded into a layer: each needs `s = γ/√(σ²+ε)` and `t = β − μ·s`, one fused launch per
//! BN per step although the values never change. [`frozen_affine`] makes them one op: on a miss,
//! one launch writes `s` and `t`; its result is kept in a small cache keyed by the four input
//! buffers (their memory ids, unique for the process's life, and their ranges), which the entry
//! also holds so that nothing can write them in place while they are cached. Every later step
//! finds the same buffers and launches nothing. New weights are new buffers: a miss, never a
//! stale value.
//!
//! The CPU backends keep the tensor ops (their numerics are the network's); so do statistics
//! that take a gradient.

mod cube;
pub mod op;

use burn::nn::BatchNorm;
use burn::tensor::{Device, Tensor};
use lifegom_render::device::runs_on_host;

/// `(s, t)`, each `[C]`, of the eval-mode `bn` on `device`: `x·s + t` per channel.
pub fn frozen_affine(bn: &BatchNorm, device: &Device) -> (Tensor<1>, Tensor<1>) {
    let mean = bn.running_mean.value().to_device(device);
    let var = bn.running_var.value().to_device(device);
    let (gamma, beta) = (bn.gamma.val(), bn.beta.val());
    let tracked = gamma.is_require_grad() || beta.is_require_grad();
    if runs_on_host(device) || tracked {
        let scale = gamma / (var + bn.epsilon).sqrt();
        let shift = beta - mean * scale.clone();
        return (scale, shift);
    }
    // Untracked values: the op runs without autodiff, and on an autodiff device its results
    // join the graph as constants. (Not on a plain device: there they must stay plain, or every
    // op they meet would run as if training.)
    let autodiff = gamma.is_autodiff();
    let inner = |t: Tensor<1>| t.inner().into_dispatch();
    let (scale, shift) = <burn::backend::Dispatch as op::FrozenAffineOps>::frozen_affine(
        inner(gamma),
        inner(beta),
        inner(mean),
        inner(var),
        bn.epsilon as f32,
    );
    let back = |t| {
        let t = Tensor::<1>::from_dispatch(t);
        if autodiff { Tensor::from_inner(t) } else { t }
    };
    (back(scale), back(shift))
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::module::Module;
    use burn::module::Param;
    use burn::nn::BatchNormConfig;
    use burn::tensor::TensorData;
    use lifegom_render::testing::{Rng, read, wgpu_test_device};

    /// A frozen BN of `c` channels with drawn statistics, on `device`.
    fn drawn_bn(c: usize, seed: u64, device: &Device) -> BatchNorm {
        let mut rng = Rng::new(seed);
        let mut draw = |lo: f32, hi: f32| -> Tensor<1> {
            let v: Vec<f32> = (0..c).map(|_| rng.range_f32(lo, hi)).collect();
            Tensor::from_data(TensorData::new(v, [c]), device)
        };
        let mut bn = BatchNormConfig::new(c)
            .with_epsilon(1e-5)
            .init(device)
            .freeze();
        bn.gamma = Param::from_tensor(draw(-2.0, 2.0)).set_require_grad(false);
        bn.beta = Param::from_tensor(draw(-1.0, 1.0)).set_require_grad(false);
        bn.running_mean = burn::module::RunningState::new(draw(-1.0, 1.0));
        bn.running_var = burn::module::RunningState::new(draw(0.0, 3.0));
        bn
    }

    /// The tensor-op composition on Flex, read back.
    fn reference(bn: &BatchNorm) -> (Vec<f32>, Vec<f32>) {
        let flex = Device::flex();
        let to = |t: Tensor<1>| Tensor::<1>::from_data(t.into_data(), &flex);
        let (gamma, beta) = (to(bn.gamma.val()), to(bn.beta.val()));
        let (mean, var) = (to(bn.running_mean.value()), to(bn.running_var.value()));
        let scale = gamma / (var + bn.epsilon).sqrt();
        let shift = beta - mean * scale.clone();
        (read(scale), read(shift))
    }

    fn assert_close(got: &[f32], want: &[f32], what: &str) {
        assert_eq!(got.len(), want.len());
        for (i, (g, w)) in got.iter().zip(want).enumerate() {
            assert!(
                (g - w).abs() <= 1e-6 * w.abs().max(1.0),
                "{what}[{i}] = {g}, the tensor ops give {w}"
            );
        }
    }

    /// On wgpu (lavapipe in CI) the op equals the tensor ops on Flex; asked again for the same
    /// statistics it gives the same values (that it launches nothing then is shown by the launch
    /// counts, BENCHMARKS.md 2026-11-27: "Adam in a few launches, frozen affines cached", not
    /// here), and new statistics of the same shape — made after the first ones were dropped, where
    /// an allocator could reuse their memory — get their own values, never the cached ones. Also
    /// under an autodiff device, as the trainer calls it.
    #[test]
    fn frozen_affine_matches_tensor_ops_and_caches_wgpu() {
        let Some(device) = wgpu_test_device() else {
            return;
        };
        for device in [device.clone(), device.autodiff()] {
            for c in [3, 64, 300] {
                let first = drawn_bn(c, c as u64, &device);
                let (want_s, want_t) = reference(&first);
                let (s, t) = frozen_affine(&first, &device);
                assert_close(&read(s.clone()), &want_s, "scale");
                assert_close(&read(t), &want_t, "shift");
                let (again, _) = frozen_affine(&first, &device);
                assert_eq!(read(again), read(s), "the scale asked again");
                drop(first);
                let second = drawn_bn(c, 1000 + c as u64, &device);
                let (want_s, want_t) = reference(&second);
                let (s, t) = frozen_affine(&second, &device);
                assert_close(&read(s), &want_s, "scale of new statistics");
                assert_close(&read(t), &want_t, "shift of new statistics");
            }
        }
    }

    /// On a plain (inference) device the results are plain tensors: an autodiff result there
    /// would turn every op it meets into a training op (dropout included).
    #[test]
    fn plain_device_results_stay_plain_wgpu() {
        let Some(device) = wgpu_test_device() else {
            return;
        };
        let bn = drawn_bn(4, 3, &device);
        let (s, t) = frozen_affine(&bn, &device);
        assert!(!s.is_autodiff() && !t.is_autodiff());
        let ad = device.autodiff();
        let (s, _) = frozen_affine(&drawn_bn(4, 3, &ad), &ad);
        assert!(
            s.is_autodiff(),
            "on an autodiff device the results join its graph"
        );
    }

    /// Statistics that take a gradient go through the tensor ops, so the gradient reaches `γ`.
    #[test]
    fn tracked_statistics_keep_their_gradient_wgpu() {
        let Some(device) = wgpu_test_device() else {
            return;
        };
        let ad = device.autodiff();
        let mut bn = drawn_bn(5, 9, &ad);
        bn.gamma = Param::from_tensor(bn.gamma.val().require_grad());
        let (s, _) = frozen_affine(&bn, &ad);
        let grads = s.sum().backward();
        assert!(bn.gamma.val().grad(&grads).is_some(), "γ's gradient");
    }
}
