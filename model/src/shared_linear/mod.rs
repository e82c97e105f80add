//! Linear layers that every feedback pass of a reconstruction shares, with one parameter
//! gradient for all passes on CubeCL devices (design.md §7.5).
//!
//! A reconstruction runs the Point Transformer `T` times with the same weights, kept in one
//! [`crate::norm_folds::NormFolds`]. Burn's autodiff differentiates each pass's product alone:
//! a weight-gradient product `xₜᵀ·gₜ` and a bias reduction per pass, then an addition per pass
//! into each parameter's gradient. On a GPU that is `2T + 2(T − 1)` launches per layer (10 at
//! the paper's `T = 3`) for what is one product and one reduction over every pass's rows:
//!
//! ```text
//! ∂W = Σₜ xₜᵀ·gₜ = Xᵀ·G        ∂b = Σₜ Σ_rows gₜ = Σ_rows G        X = [x₁; …; x_T], G = [g₁; …; g_T]
//! ```
//!
//! [`SharedLinear`] computes it so: each pass's backward computes its `∂x` at once and files
//! `(xₜ, gₜ)` with the layer; the weight's and the bias's own nodes, which Burn's autodiff runs
//! after every pass's, stack the rows and take one product and one reduction (the `op` module).
//! The result is the same gradient up to float summation order. Cost: each pass's `gₜ` is held
//! until the layer's parameters are differentiated, instead of being freed after its products.
//!
//! On the CPU backends a shared layer is the layer it wraps ([`crate::linear_op::affine`]): their
//! gradients stay the same to the bit.

mod cube;
pub mod op;

use burn::backend::Dispatch;
use burn::tensor::Tensor;
use lifegom_render::device::runs_on_host;

use crate::linear_op;
use op::{Ledger, Role, SharedLinearOps};

/// `x·W + b` over the last axis, with `W` `[in, out]` and `b` `[out]` read by several passes
/// (module docs). Make one per layer and reconstruction, and use it for every pass.
#[derive(Debug, Clone)]
pub struct SharedLinear {
    weight: Tensor<2>,
    bias: Tensor<1>,
    /// `None` on the CPU backends.
    ledger: Option<Ledger>,
}

impl SharedLinear {
    /// The layer `x·weight + bias`.
    ///
    /// # Panics
    ///
    /// If `bias` is not `[out]` for `weight` `[in, out]`.
    pub fn new(weight: Tensor<2>, bias: Tensor<1>) -> Self {
        assert_eq!(
            weight.dims()[1],
            bias.dims()[0],
            "a shared layer's bias has one entry per output"
        );
        if runs_on_host(&weight.device()) {
            return Self {
                weight,
                bias,
                ledger: None,
            };
        }
        let ledger = Ledger::default();
        let shared = |t: burn::backend::tensor::FloatTensor<Dispatch>, role| {
            <Dispatch as SharedLinearOps>::shared_parameter(t, ledger.clone(), role)
        };
        Self {
            weight: Tensor::from_dispatch(shared(weight.into_dispatch(), Role::Weight)),
            bias: Tensor::from_dispatch(shared(bias.into_dispatch(), Role::Bias)),
            ledger: Some(ledger),
        }
    }

    /// `x` `[.., in]` → `[.., out]`.
    ///
    /// # Panics
    ///
    /// If `x`'s last axis is not the layer's input width.
    pub fn forward<const D: usize>(&self, x: Tensor<D>) -> Tensor<D> {
        let Some(ledger) = &self.ledger else {
            return linear_op::affine(x, self.weight.clone(), Some(self.bias.clone()));
        };
        assert_eq!(
            x.dims()[D - 1],
            self.weight.dims()[0],
            "input width of a shared layer"
        );
        Tensor::from_dispatch(<Dispatch as SharedLinearOps>::shared_linear(
            x.into_dispatch(),
            self.weight.clone().into_dispatch(),
            self.bias.clone().into_dispatch(),
            ledger.clone(),
        ))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::tensor::{Device, TensorData};
    use lifegom_render::device::DeviceChoice;
    use lifegom_render::testing::{Rng, read, wgpu_test_device};

    /// `passes` passes through one layer, each pass's input the previous pass's output (as the
    /// feedback loop chains them), on `device` with autodiff: the output and the gradients of
    /// the first input, the weight and the bias. `shared` picks [`SharedLinear`] or Burn's
    /// `linear` (the CPU op on the CPU backends) on the same values.
    fn run_passes(device: &Device, passes: usize, shared: bool) -> [Vec<f32>; 4] {
        let mut rng = Rng::new(7);
        let mut draw = |shape: [usize; 2]| {
            let values: Vec<f32> = (0..shape[0] * shape[1])
                .map(|_| rng.range_f32(-1.0, 1.0))
                .collect();
            Tensor::<2>::from_data(TensorData::new(values, shape), device)
        };
        let x0 = draw([37, 6]).require_grad();
        let weight = draw([6, 6]).require_grad();
        let bias = draw([1, 6]).reshape([6]).require_grad();
        let layer = SharedLinear::new(weight.clone(), bias.clone());
        let mut x = x0.clone();
        let mut total = None;
        for pass in 0..passes {
            let y = if shared {
                layer.forward(x.clone())
            } else {
                linear_op::affine(x.clone(), weight.clone(), Some(bias.clone()))
            };
            // A different use per pass, so that no two passes' gradients are equal.
            let out = (y.clone() * (0.5 + pass as f32 / 4.0)).tanh();
            total = Some(match total {
                None => out.clone().sum(),
                Some(t) => t + out.clone().sum(),
            });
            x = out;
        }
        let total = total.expect("at least one pass");
        let grads = total.backward();
        let grad = |t: &Tensor<2>| read(t.grad(&grads).expect("a gradient"));
        [
            read(x),
            grad(&x0),
            grad(&weight),
            read(bias.grad(&grads).expect("a gradient")),
        ]
    }

    fn close(a: &[f32], b: &[f32], what: &str) {
        let scale = b.iter().fold(0f32, |m, v| m.max(v.abs())).max(1e-6);
        for (i, (u, v)) in a.iter().zip(b).enumerate() {
            assert!(
                (u - v).abs() <= 1e-5 * scale,
                "{what}[{i}]: {u} against {v}"
            );
        }
    }

    /// On lavapipe the shared layer's output and every gradient equal Burn's `linear` used as
    /// many times, within float summation order, and Flex's results: for one pass (nothing
    /// stacked), three (one launch) and six (stacked four at a time, then the rest).
    #[test]
    fn one_gradient_for_all_passes_wgpu() {
        let Some(device) = wgpu_test_device() else {
            return;
        };
        let ad = device.autodiff();
        for passes in [1, 3, 6] {
            let flex = run_passes(&DeviceChoice::Flex.device().autodiff(), passes, false);
            let shared = run_passes(&ad, passes, true);
            let composed = run_passes(&ad, passes, false);
            for (i, what) in ["output", "∂x", "∂W", "∂b"].iter().enumerate() {
                close(
                    &shared[i],
                    &composed[i],
                    &format!("{passes} passes: {what}"),
                );
                close(&shared[i], &flex[i], &format!("{passes} passes: {what}"));
            }
        }
    }

    /// On the CPU backends the shared layer is the wrapped layer: equal to the bit.
    #[test]
    fn host_layers_are_the_layer() {
        for choice in DeviceChoice::CPU {
            let device = choice.device().autodiff();
            let a = run_passes(&device, 3, true);
            let b = run_passes(&device, 3, false);
            assert_eq!(a, b);
        }
    }
}
