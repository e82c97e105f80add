//! The aggregation step of the Point Transformer's vector attention (design.md §7.5): each
//! point's output is the sum over its `k` neighbours of their values, weighted per channel by a
//! softmax over the neighbours,
//!
//! `out[i, s, j] = Σ_κ softmax_κ(w[i, ·, j])[κ] · v[i, κ, s, j]`,
//!
//! with `v` `[n, k, S, C/S]` (the S value channels that share one weight channel, `share_planes`)
//! and the attention logits `w` `[n, k, C/S]`; the result is `[n, C]` (`s`-major).
//!
//! [`aggregate`] computes it:
//! - on the CPU backends as the plain tensor-op composition ([`aggregate_reference`]: softmax,
//!   broadcast product, sum over the neighbours), whose autodiff nodes are cheap there and whose
//!   numerics are the network's since it was written;
//! - on CubeCL devices through the [`op::VectorAttentionOps`] extension: one forward kernel and
//!   one backward kernel (`cube`) in place of the composition's eight forward and about a dozen
//!   backward launches per layer and pass.

mod cube;
pub mod op;

use burn::tensor::Tensor;
use burn::tensor::activation::softmax;
use lifegom_render::device::runs_on_host;

/// `Σ_κ softmax_κ(logits)·values` (module docs): `values` `[n, k, S, C/S]`, `logits`
/// `[n, k, C/S]` → `[n, C]`.
///
/// # Panics
///
/// If the shapes do not match as above.
pub fn aggregate(values: Tensor<4>, logits: Tensor<3>) -> Tensor<2> {
    let [n, k, s, cs] = values.dims();
    assert_eq!(
        logits.dims(),
        [n, k, cs],
        "vector attention: logits must be [n, k, C/S] for values {:?}",
        values.dims()
    );
    if runs_on_host(&values.device()) {
        return aggregate_reference(values, logits);
    }
    let out: Tensor<3> = Tensor::from_dispatch(
        <burn::backend::Dispatch as op::VectorAttentionOps>::attention_aggregate(
            values.into_dispatch(),
            logits.into_dispatch(),
        ),
    );
    out.reshape([n, s * cs])
}

/// [`aggregate`] as Burn tensor ops: the specification, and the implementation on the CPU
/// backends.
pub fn aggregate_reference(values: Tensor<4>, logits: Tensor<3>) -> Tensor<2> {
    let [n, _, s, cs] = values.dims();
    let weights = softmax(logits, 1);
    (values * weights.unsqueeze_dim::<4>(2))
        .sum_dim(1)
        .reshape([n, s * cs])
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::tensor::{Device, TensorData};
    use lifegom_render::rng::Rng;
    use lifegom_render::testing::read;

    /// [`aggregate`] against [`aggregate_reference`] computed on Flex: values and the gradients
    /// of both inputs, with logits large enough that the softmax's max shift matters and one
    /// neighbour set where every logit is equal.
    fn check_matches_reference(device: &Device) {
        let (n, k, s, cs) = (37usize, 5usize, 3usize, 4usize);
        let mut rng = Rng::new(11);
        let values: Vec<f32> = (0..n * k * s * cs)
            .map(|_| rng.range_f32(-1.0, 1.0))
            .collect();
        let mut logits: Vec<f32> = (0..n * k * cs)
            .map(|_| rng.range_f32(-30.0, 30.0))
            .collect();
        for kk in 0..k {
            for j in 0..cs {
                logits[kk * cs + j] = 2.5;
            }
        }
        let weight: Vec<f32> = (0..n * s * cs).map(|_| rng.range_f32(-1.0, 1.0)).collect();
        let run = |device: &Device, fused: bool| {
            let ad = device.clone().autodiff();
            let v = Tensor::<4>::from_data(TensorData::new(values.clone(), [n, k, s, cs]), &ad)
                .require_grad();
            let w = Tensor::<3>::from_data(TensorData::new(logits.clone(), [n, k, cs]), &ad)
                .require_grad();
            let out = if fused {
                aggregate(v.clone(), w.clone())
            } else {
                aggregate_reference(v.clone(), w.clone())
            };
            assert_eq!(out.dims(), [n, s * cs]);
            let g = Tensor::<2>::from_data(TensorData::new(weight.clone(), [n, s * cs]), &ad);
            let grads = (out.clone() * g).sum().backward();
            [
                read(out),
                read(v.grad(&grads).expect("values gradient")),
                read(w.grad(&grads).expect("logits gradient")),
            ]
        };
        let want = run(&Device::flex(), false);
        let got = run(device, true);
        for (name, (a, b)) in ["values", "values gradient", "logits gradient"]
            .iter()
            .zip(got.iter().zip(&want))
        {
            assert_eq!(a.len(), b.len(), "{name}");
            let diff = a
                .iter()
                .zip(b)
                .fold(0.0f32, |m, (x, y)| m.max((x - y).abs()));
            assert!(diff <= 1e-5, "{name} on {device:?}: max diff {diff:.2e}");
        }
        assert!(
            got[2].iter().any(|g| g.abs() > 1e-3),
            "logit gradients vanished"
        );
    }

    lifegom_render::cpu_backend_tests!(aggregate_matches_reference => check_matches_reference);

    #[test]
    fn aggregate_matches_reference_wgpu() {
        if let Some(device) = lifegom_render::testing::wgpu_test_device() {
            check_matches_reference(&device);
        }
    }
}
