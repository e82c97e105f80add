//! Linear layers that every feedback pass of a reconstruction shares, with one parameter
//! gradient for all passes on CubeCL devices (design.md §7.5).
//!
//! A reconstruction runs the Point Transformer `T` times with the same weights, kept in one
//! `NormFolds` (`lifegom_model::norm_folds`). Burn's autodiff differentiates each pass's product alone:
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
//! after every pass's, form both from every pass's rows in one launch and a sum over chunks of
//! rows (the `op` and `gradient` modules).
//! The result is the same gradient up to float summation order. Cost: each pass's `gₜ` is held
//! until the layer's parameters are differentiated, instead of being freed after its products.
//!
//! A layer that a frozen BatchNorm follows applies it in its product's launch
//! (`SharedLinear::folded`, [`op::OutputMap`]): `(x·W + b)·s + t`, the BN's `s`, `t` made once
//! per process; backward, the scale enters `∂x` where the product stages the gradient and the
//! parameters' gradient where the rows are read, so the norm costs no launch of its own. (Until
//! c9ab074, 2026-11-28, the layer was folded with it each step: a launch per layer.)
//!
//! On the CPU backends a shared layer is the layer it wraps ([`crate::linear_op::affine`]): their
//! gradients stay the same to the bit.

mod gradient;
pub mod op;
pub use op::filing::detached_passes;
mod product;
mod trained_fold;

use burn::backend::Dispatch;
use burn::nn::{BatchNorm, Linear};
use burn::tensor::{Device, Tensor};
use lifegom_render::device::runs_on_host;
use lifegom_render::split::join_columns;

use crate::activation::Activation;
use crate::gemm_conv::op::Patches;
use crate::handoff::Handoff;
use crate::linear_op;
use op::{Ledger, OutputMap, Role, SharedLinearOps};

/// `x·W + b` over the last axis, with `W` `[in, out]` and `b` `[out]` read by several passes
/// (module docs), or `(x·W + b)·s + t` with a frozen BatchNorm's `s`, `t` after it
/// (`SharedLinear::folded`). Make one per layer and reconstruction, and use it for every pass.
#[derive(Debug, Clone)]
pub struct SharedLinear {
    weight: Tensor<2>,
    /// The bias, or any `[out]` tensor where `map` reads none.
    bias: Tensor<1>,
    /// A frozen BatchNorm's `s`, `t`, or any `[out]` tensors where `map` reads none.
    norm: [Tensor<1>; 2],
    map: OutputMap,
    /// `None` on the CPU backends.
    ledger: Option<Ledger>,
}

/// Layers with biases that read the same input, as one layer whose outputs are theirs side by
/// side: `(cat(W₁, W₂, …) [in, Σ out], cat(b₁, b₂, …))` on `device`. One product then replaces
/// several, forward and backward (the Point Transformer's query, key and value); where that
/// pays is [`SharedLinear::stacks_on`].
///
/// # Panics
///
/// If `layers` is empty or a layer has no bias.
pub fn stacked(layers: &[&Linear], device: &Device) -> (Tensor<2>, Tensor<1>) {
    // One launch each way per stack on a GPU, where `cat` takes one per layer forward and a
    // slice per layer backward.
    let weight = join_columns(layers.iter().map(|l| l.weight.val()).collect());
    let bias = join_columns(
        layers
            .iter()
            .map(|l| l.bias.as_ref().expect("stacked layers have biases").val())
            .collect(),
    );
    (weight.to_device(device), bias.to_device(device))
}

impl SharedLinear {
    /// Whether layers that read one input run as one [`stacked`] product on `device`: on CubeCL
    /// devices, where it saves a launch per layer each way and sums the input's gradient inside
    /// the product. The CPU backends keep a product per layer: their float order is the
    /// network's.
    pub fn stacks_on(device: &Device) -> bool {
        !runs_on_host(device)
    }

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
        let norm = [bias.clone(), bias.clone()];
        if runs_on_host(&weight.device()) {
            return Self {
                weight,
                bias,
                norm,
                map: OutputMap::Biased,
                ledger: None,
            };
        }
        let ledger = Ledger::default();
        Self {
            weight: shared(weight, &ledger, Role::Weight),
            bias: shared(bias, &ledger, Role::Bias),
            norm,
            map: OutputMap::Biased,
            ledger: Some(ledger),
        }
    }

    /// `BN(linear(·))` for a BatchNorm on its running statistics, as one shared layer, with
    /// `s = γ/√(σ²+ε)`, `t = β − μ·s` ([`crate::frozen_affine`]). On a CubeCL device, when the
    /// BN's `γ`, `β` take no gradient, `(x·W + b)·s + t` (`x·W·s + t` without a bias) with the
    /// norm applied in the product's epilogue, forward and backward (module docs): no launch of
    /// its own. Elsewhere the fold as tensor ops, `(W·diag(s), b·s + t)`, in [`Self::new`]: the
    /// CPU backends' float order is the network's, and a BN that trains needs its gradient.
    ///
    /// # Panics
    ///
    /// If the BN's width is not the layer's output width.
    pub fn folded(linear: &Linear, bn: &BatchNorm, device: &Device) -> Self {
        let d_out = linear.weight.dims()[1];
        assert_eq!(bn.gamma.dims()[0], d_out, "one BN channel per output");
        let (scale, shift) = crate::frozen_affine::frozen_affine(bn, device);
        let frozen = !bn.gamma.val().is_require_grad() && !bn.beta.val().is_require_grad();
        if runs_on_host(device) || !frozen {
            let weight = linear.weight.val() * scale.clone().unsqueeze_dim(0);
            let bias = match &linear.bias {
                Some(b) => b.val() * scale + shift,
                None => shift,
            };
            return Self::new(weight, bias);
        }
        let ledger = Ledger::default();
        let (bias, map) = match &linear.bias {
            Some(b) => (shared(b.val(), &ledger, Role::Bias), OutputMap::NormedBias),
            None => (shift.clone(), OutputMap::Normed),
        };
        Self {
            weight: shared(linear.weight.val(), &ledger, Role::Weight),
            bias,
            norm: [scale, shift],
            map,
            ledger: Some(ledger),
        }
    }

    /// `BN(x·Wᵀ)` for a bias-free layer whose weight `weight` is stored `[out, in]` (a
    /// convolution's, [`crate::conv_norm`]) and a BatchNorm on its running statistics whose
    /// `γ`, `β` train: `x·(Wᵀ·diag(s)) + (β − μ·s)`, `s = γ/√(σ²+ε)`. The fold is one launch per
    /// reconstruction; the backward forms the passes' gradient once and turns it into `∂W`,
    /// `∂γ`, `∂β` in one more ([`op::SharedLinearOps::trained_fold`]).
    ///
    /// # Panics
    ///
    /// On a CPU backend, or if the BN's width is not the layer's output width.
    pub(crate) fn trained_fold(weight: Tensor<2>, bn: &BatchNorm, device: &Device) -> Self {
        assert!(
            !runs_on_host(device),
            "the CPU backends compose the convolution and the BatchNorm"
        );
        assert_eq!(
            bn.gamma.dims()[0],
            weight.dims()[0],
            "one BN channel per output"
        );
        let ledger = Ledger::default();
        let (weight, bias) = <Dispatch as SharedLinearOps>::trained_fold(
            weight.into_dispatch(),
            bn.gamma.val().into_dispatch(),
            bn.beta.val().into_dispatch(),
            bn.running_mean.value().to_device(device).into_dispatch(),
            bn.running_var.value().to_device(device).into_dispatch(),
            bn.epsilon as f32,
            ledger.clone(),
        );
        let bias = Tensor::from_dispatch(bias);
        Self {
            weight: Tensor::from_dispatch(weight),
            norm: [bias.clone(), bias.clone()],
            bias,
            map: OutputMap::Biased,
            ledger: Some(ledger),
        }
    }

    /// `x` `[.., in]` → `[.., out]`.
    ///
    /// # Panics
    ///
    /// If `x`'s last axis is not the layer's input width.
    pub fn forward<const D: usize>(&self, x: Tensor<D>) -> Tensor<D> {
        self.forward_with(x, Activation::Identity)
    }

    /// `relu(x·W + b + residual)` for `x` `[.., in]` and `residual` `[.., out]`, a residual
    /// block's last layer: the sum and the ReLU in the product's launch on CubeCL devices, and
    /// the residual's gradient the masked gradient that the backward's product writes anyway,
    /// handed to the layer `handoff` joins (the block's first, which reads `residual` as its
    /// input: [`Self::forward_receiving`]) or else registered; on the CPU backends the layer,
    /// the sum and Burn's ReLU.
    ///
    /// # Panics
    ///
    /// If `x`'s last axis is not the layer's input width, or `residual` is not the output's shape.
    pub fn forward_residual_relu<const D: usize>(
        &self,
        x: Tensor<D>,
        residual: Tensor<D>,
        handoff: &Handoff,
    ) -> Tensor<D> {
        let Some(ledger) = &self.ledger else {
            let y = linear_op::affine(x, self.weight.clone(), Some(self.bias.clone()));
            return burn::tensor::activation::relu(y + residual);
        };
        let mut out = x.dims();
        out[D - 1] = self.weight.dims()[1];
        assert_eq!(
            x.dims()[D - 1],
            self.weight.dims()[0],
            "input width of a shared layer"
        );
        assert_eq!(
            residual.dims(),
            out,
            "a residual has the layer's output shape"
        );
        let [scale, shift] = self.norm.clone().map(Tensor::into_dispatch);
        Tensor::from_dispatch(<Dispatch as SharedLinearOps>::shared_linear_residual(
            x.into_dispatch(),
            None,
            self.weight.clone().into_dispatch(),
            self.bias.clone().into_dispatch(),
            scale,
            shift,
            self.map,
            residual.into_dispatch(),
            ledger.clone(),
            handoff.clone(),
        ))
    }

    /// `act(x·W + b)`: `x` `[.., in]` → `[.., out]`, the activation in the product's launch on
    /// CubeCL devices (the `product` module); on the CPU backends the layer, then Burn's ReLU.
    ///
    /// # Panics
    ///
    /// If `x`'s last axis is not the layer's input width.
    pub fn forward_with<const D: usize>(&self, x: Tensor<D>, activation: Activation) -> Tensor<D> {
        self.forward_receiving(x, activation, &Handoff::none())
    }

    /// [`Self::forward_with`], `x`'s gradient on CubeCL devices adding, in its launch, the one
    /// `handoff` brings from a later residual layer that adds `x`
    /// ([`Self::forward_residual_relu`]).
    ///
    /// # Panics
    ///
    /// If `x`'s last axis is not the layer's input width.
    pub fn forward_receiving<const D: usize>(
        &self,
        x: Tensor<D>,
        activation: Activation,
        handoff: &Handoff,
    ) -> Tensor<D> {
        let Some(ledger) = &self.ledger else {
            let y = linear_op::affine(x, self.weight.clone(), Some(self.bias.clone()));
            return match activation {
                Activation::Identity => y,
                Activation::Relu => burn::tensor::activation::relu(y),
            };
        };
        assert_eq!(
            x.dims()[D - 1],
            self.weight.dims()[0],
            "input width of a shared layer"
        );
        let [scale, shift] = self.norm.clone().map(Tensor::into_dispatch);
        Tensor::from_dispatch(<Dispatch as SharedLinearOps>::shared_linear(
            x.into_dispatch(),
            None,
            self.weight.clone().into_dispatch(),
            self.bias.clone().into_dispatch(),
            scale,
            shift,
            self.map,
            ledger.clone(),
            activation,
            handoff.clone(),
        ))
    }
}

impl SharedLinear {
    /// `act(columns·W + b)` for the patch columns of the image `x` `[N, C, H, W]` under the
    /// window `patches` (a convolution, [`crate::conv_norm`]): `[N·H_out·W_out, out]`. The
    /// product, and the weight gradient's kernel, read the columns from the image where they
    /// stage them, so they are never written. CubeCL devices only.
    ///
    /// # Panics
    ///
    /// On a CPU backend, or if the window's width `C·kh·kw` is not the layer's input width.
    pub(crate) fn forward_patches(
        &self,
        x: Tensor<4>,
        patches: Patches,
        residual: Option<Tensor<2>>,
        activation: Activation,
    ) -> Tensor<2> {
        let ledger = self
            .ledger
            .as_ref()
            .expect("the CPU backends run Burn's convolution");
        let width = patches.columns_shape(&x.shape())[1];
        assert_eq!(
            width,
            self.weight.dims()[0],
            "input width of a shared layer"
        );
        let [scale, shift] = self.norm.clone().map(Tensor::into_dispatch);
        let (x, weight, bias) = (
            x.into_dispatch(),
            self.weight.clone().into_dispatch(),
            self.bias.clone().into_dispatch(),
        );
        let handoff = Handoff::none();
        Tensor::from_dispatch(match residual {
            Some(residual) => {
                assert_eq!(activation, Activation::Relu, "a residual ends in a ReLU");
                <Dispatch as SharedLinearOps>::shared_linear_residual(
                    x,
                    Some(patches),
                    weight,
                    bias,
                    scale,
                    shift,
                    self.map,
                    residual.into_dispatch(),
                    ledger.clone(),
                    handoff,
                )
            }
            None => <Dispatch as SharedLinearOps>::shared_linear(
                x,
                Some(patches),
                weight,
                bias,
                scale,
                shift,
                self.map,
                ledger.clone(),
                activation,
                handoff,
            ),
        })
    }
}

/// `value` as the parameter `role` of the layer whose passes `ledger` records (the `op` module).
fn shared<const D: usize>(value: Tensor<D>, ledger: &Ledger, role: Role) -> Tensor<D> {
    Tensor::from_dispatch(<Dispatch as SharedLinearOps>::shared_parameter(
        value.into_dispatch(),
        ledger.clone(),
        role,
    ))
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::module::{Param, RunningState};
    use burn::nn::BatchNormConfig;
    use burn::tensor::TensorData;
    use lifegom_render::device::DeviceChoice;
    use lifegom_render::testing::{Rng, assert_close_to_scale, read, wgpu_test_device};

    use crate::split_k::force_split_k_rows;

    /// How the passes run the layer.
    #[derive(Debug, Clone, Copy, PartialEq)]
    enum Layer {
        /// [`SharedLinear`] (through [`SharedLinear::folded`] for a folded layer on a device).
        Shared,
        /// Burn's `linear` (the CPU op on the CPU backends), folded with tensor ops.
        Composed,
    }

    /// Whether a folded layer has a bias of its own.
    #[derive(Debug, Clone, Copy, PartialEq)]
    enum OwnBias {
        Given,
        Absent,
    }

    /// Whether a frozen BatchNorm follows the layer, and if so whether the layer has a bias.
    #[derive(Debug, Clone, Copy, PartialEq)]
    enum Norm {
        None,
        Folded(OwnBias),
    }

    /// `passes` passes through one 6 → 6 layer, each pass's input the previous pass's output (as
    /// the feedback loop chains them), on `device` with autodiff: the output and the gradients of
    /// the first input, the weight and the bias (when it has one and takes a gradient). The same
    /// values whatever the device and the way the layer runs.
    fn run_passes(device: &Device, passes: usize, layer: Layer, norm: Norm) -> Vec<Vec<f32>> {
        run_ending(
            device,
            Passes {
                passes,
                rows: 37,
                width: 6,
            },
            layer,
            norm,
            Ending::Activated(Activation::Identity),
        )
    }

    /// How many passes of how many rows through a layer of how many channels.
    #[derive(Debug, Clone, Copy)]
    struct Passes {
        passes: usize,
        rows: usize,
        width: usize,
    }

    /// What follows the layer's product.
    #[derive(Debug, Clone, Copy, PartialEq)]
    enum Ending {
        /// The activation.
        Activated(Activation),
        /// The pass's input added as a residual, then a ReLU.
        ResidualRelu,
    }

    /// [`run_passes`] for any size and [`Ending`].
    fn run_ending(
        device: &Device,
        Passes {
            passes,
            rows,
            width,
        }: Passes,
        layer: Layer,
        norm: Norm,
        ending: Ending,
    ) -> Vec<Vec<f32>> {
        let mut rng = Rng::new(7);
        let mut draw = |shape: [usize; 2], lo: f32, hi: f32| {
            let values: Vec<f32> = (0..shape[0] * shape[1])
                .map(|_| rng.range_f32(lo, hi))
                .collect();
            Tensor::<2>::from_data(TensorData::new(values, shape), device)
        };
        let x0 = draw([rows, width], -1.0, 1.0).require_grad();
        let weight = draw([width, width], -1.0, 1.0).require_grad();
        let bias = draw([1, width], -1.0, 1.0).reshape([width]).require_grad();
        let mut stat = |lo: f32, hi: f32| draw([1, width], lo, hi).reshape([width]);
        let (gamma, beta, mean, var) = (
            stat(-1.5, 1.5),
            stat(-0.5, 0.5),
            stat(-0.5, 0.5),
            stat(0.2, 2.0),
        );
        let linear = Linear {
            weight: Param::from_tensor(weight.clone()),
            bias: match norm {
                Norm::Folded(OwnBias::Absent) => None,
                _ => Some(Param::from_tensor(bias.clone())),
            },
        };
        let mut bn = BatchNormConfig::new(width).init(device);
        bn.gamma = Param::from_tensor(gamma).set_require_grad(false);
        bn.beta = Param::from_tensor(beta).set_require_grad(false);
        bn.running_mean = RunningState::new(mean);
        bn.running_var = RunningState::new(var);
        let shared = match norm {
            Norm::None => SharedLinear::new(weight.clone(), bias.clone()),
            Norm::Folded(_) => SharedLinear::folded(&linear, &bn, device),
        };
        // The composed reference folds with tensor ops.
        let (w, b) = match norm {
            Norm::None => (weight.clone(), bias.clone()),
            Norm::Folded(_) => {
                let (scale, shift) = crate::frozen_affine::frozen_affine(&bn, device);
                let w = linear.weight.val() * scale.clone().unsqueeze_dim(0);
                let b = match &linear.bias {
                    Some(b) => b.val() * scale + shift,
                    None => shift,
                };
                (w, b)
            }
        };
        let mut x = x0.clone();
        let mut total = None;
        for pass in 0..passes {
            let composed = || linear_op::affine(x.clone(), w.clone(), Some(b.clone()));
            let y = match (layer, ending) {
                (Layer::Shared, Ending::Activated(activation)) => {
                    shared.forward_with(x.clone(), activation)
                }
                (Layer::Shared, Ending::ResidualRelu) => {
                    shared.forward_residual_relu(x.clone(), x.clone(), &Handoff::none())
                }
                (Layer::Composed, Ending::Activated(Activation::Identity)) => composed(),
                (Layer::Composed, Ending::Activated(Activation::Relu)) => {
                    burn::tensor::activation::relu(composed())
                }
                (Layer::Composed, Ending::ResidualRelu) => {
                    burn::tensor::activation::relu(composed() + x.clone())
                }
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
        let mut parts = vec![
            read(x),
            read(x0.grad(&grads).expect("an input gradient")),
            read(weight.grad(&grads).expect("a weight gradient")),
        ];
        if norm != Norm::Folded(OwnBias::Absent) {
            parts.push(read(bias.grad(&grads).expect("a bias gradient")));
        }
        parts
    }

    /// On lavapipe the shared layer's output and every gradient equal Burn's `linear` used as
    /// many times, within float summation order, and Flex's results: for one pass, three (one
    /// gradient launch) and six (a launch for four passes' rows, one for the rest); plain, and
    /// folded with a frozen BN with and without a bias of its own; with the gradient as one
    /// chunk (37 rows per pass are under two chunks) and split-k in chunks of 8 rows (each
    /// launch's last chunk short: 37, 111, 148 and 74 rows).
    #[test]
    fn one_gradient_for_all_passes_wgpu() {
        let Some(device) = wgpu_test_device() else {
            return;
        };
        let ad = device.autodiff();
        let flex = DeviceChoice::Flex.device().autodiff();
        for split in [None, Some(8)] {
            for norm in [
                Norm::None,
                Norm::Folded(OwnBias::Given),
                Norm::Folded(OwnBias::Absent),
            ] {
                for passes in [1, 3, 6] {
                    let reference = run_passes(&flex, passes, Layer::Composed, norm);
                    force_split_k_rows(split);
                    let shared = run_passes(&ad, passes, Layer::Shared, norm);
                    force_split_k_rows(None);
                    let composed = run_passes(&ad, passes, Layer::Composed, norm);
                    for (i, what) in ["output", "∂x", "∂W", "∂b"]
                        .iter()
                        .enumerate()
                        .take(shared.len())
                    {
                        let what = format!("split {split:?}, {norm:?}, {passes} passes: {what}");
                        assert_close_to_scale(&shared[i], &composed[i], 1e-5, &what);
                        assert_close_to_scale(&shared[i], &reference[i], 1e-5, &what);
                    }
                }
            }
        }
    }

    /// Two layers' gradients formed together (`op::filing`): passes through a 6 → 6 layer and a
    /// 6 → 5 layer in turn, three of each, plus a pass of each inside [`detached_passes`] whose
    /// output is detached (were they counted, neither layer would be complete before its own
    /// parameter node, and each would form alone). With split-k in chunks of 8 rows both layers have several
    /// chunks, and the first parameter node to run forms both, one sum over the chunks for the
    /// two; each gradient is then a view of one buffer at an aligned offset. Outputs and every
    /// gradient equal Flex's composition, where the detached pass is Burn's `linear` detached;
    /// also when the batch's bound on partial gradients leaves the second layer out.
    #[test]
    fn layers_form_their_gradients_together_wgpu() {
        let Some(device) = wgpu_test_device() else {
            return;
        };
        let run = |device: &Device, layer: Layer| -> Vec<Vec<f32>> {
            let mut rng = Rng::new(11);
            let mut draw = |shape: [usize; 2]| {
                let values: Vec<f32> = (0..shape[0] * shape[1])
                    .map(|_| rng.range_f32(-1.0, 1.0))
                    .collect();
                Tensor::<2>::from_data(TensorData::new(values, shape), device)
            };
            let x0 = draw([37, 6]).require_grad();
            let params = [(6, 6), (6, 5)].map(|(i, o)| {
                let w = draw([i, o]).require_grad();
                let b = draw([1, o]).reshape([o]).require_grad();
                (w, b)
            });
            let shared = params
                .clone()
                .map(|(w, b)| SharedLinear::new(w.clone(), b.clone()));
            let apply = |l: usize, x: Tensor<2>| match layer {
                Layer::Shared => shared[l].forward(x),
                Layer::Composed => {
                    let (w, b) = &params[l];
                    linear_op::affine(x, w.clone(), Some(b.clone()))
                }
            };
            let mut x = x0.clone();
            let mut total = x0.clone().sum() * 0.0;
            for pass in 0..3 {
                let hidden = apply(0, x.clone()).tanh();
                let out = apply(1, hidden.clone());
                total = total + out.clone().sum() * (0.5 + pass as f32 / 4.0);
                // A pass of each layer whose output is detached: it reaches no gradient.
                let detached = |l: usize| {
                    match layer {
                        Layer::Shared => detached_passes(|| apply(l, hidden.clone())),
                        Layer::Composed => apply(l, hidden.clone()),
                    }
                    .detach()
                };
                total = total
                    + (detached(0) * hidden.clone()).sum()
                    + (detached(1) * out.clone()).sum();
                x = hidden;
            }
            let grads = total.backward();
            let mut parts = vec![read(x), read(x0.grad(&grads).expect("an input gradient"))];
            for (w, b) in &params {
                parts.push(read(w.grad(&grads).expect("a weight gradient")));
                parts.push(read(b.grad(&grads).expect("a bias gradient")));
            }
            parts
        };
        let reference = run(&DeviceChoice::Flex.device().autodiff(), Layer::Composed);
        // Then with a batch bound under the two layers' partial gradients: the second layer
        // is left out of the first's batch, keeps its rows and forms them when it asks.
        for (bound, want) in [(None, &[2][..]), (Some(1), &[1, 1])] {
            force_split_k_rows(Some(8));
            op::filing::BATCH_BYTES.set(bound);
            op::filing::BATCHES.with_borrow_mut(Vec::clear);
            let shared = run(&device.clone().autodiff(), Layer::Shared);
            let batches = op::filing::BATCHES.with_borrow_mut(std::mem::take);
            op::filing::BATCH_BYTES.set(None);
            force_split_k_rows(None);
            assert_eq!(batches, want, "layers formed per batch, bound {bound:?}");
            for (part, what) in shared
                .iter()
                .zip(&reference)
                .zip(["output", "∂x", "∂W₀", "∂b₀", "∂W₁", "∂b₁"])
            {
                assert_close_to_scale(part.0, part.1, 1e-5, &format!("{what}, bound {bound:?}"));
            }
        }
    }

    /// On lavapipe the product kernel (`product`) with the ReLU in its launch (alone, and after
    /// the pass's input added as a residual), and the masked backward product that writes the
    /// masked gradient (also the residual's), equal Burn's `linear`, `+` and `relu` on Flex:
    /// output, `∂x`, `∂W`, `∂b`, plain and folded, for one and three passes, at sizes that leave
    /// partial blocks on every axis (150 rows, 70 channels: two full blocks of 64 rows and one
    /// of 22, one full column block and one of 6, four full inner steps of 16 and one of 6), and
    /// at the 6-channel size of [`one_gradient_for_all_passes_wgpu`]. The weights are drawn so
    /// that about half of the outputs are negative: the mask matters.
    #[test]
    fn relu_products_match_burn_wgpu() {
        let Some(device) = wgpu_test_device() else {
            return;
        };
        let ad = device.autodiff();
        let flex = DeviceChoice::Flex.device().autodiff();
        for (rows, width) in [(150, 70), (37, 6)] {
            for norm in [Norm::None, Norm::Folded(OwnBias::Given)] {
                for passes in [1, 3] {
                    let size = Passes {
                        passes,
                        rows,
                        width,
                    };
                    for ending in [Ending::Activated(Activation::Relu), Ending::ResidualRelu] {
                        let reference = run_ending(&flex, size, Layer::Composed, norm, ending);
                        let shared = run_ending(&ad, size, Layer::Shared, norm, ending);
                        for (i, what) in ["output", "∂x", "∂W", "∂b"].iter().enumerate() {
                            let what = format!("{size:?}, {norm:?}, {ending:?}: {what}");
                            assert_close_to_scale(&shared[i], &reference[i], 1e-5, &what);
                        }
                        let zeros = shared[0].iter().filter(|v| **v == 0.0).count();
                        assert!(
                            zeros > 0 && zeros < shared[0].len(),
                            "{size:?}, {ending:?}: the ReLU clips some outputs and passes \
                             others ({zeros})"
                        );
                    }
                }
            }
        }
    }

    /// On the CPU backends the shared layer is the wrapped layer, folded with the same tensor
    /// ops: equal to the bit.
    #[test]
    fn host_layers_are_the_layer() {
        for choice in DeviceChoice::CPU {
            let device = choice.device().autodiff();
            for norm in [Norm::None, Norm::Folded(OwnBias::Given)] {
                let a = run_passes(&device, 3, Layer::Shared, norm);
                let b = run_passes(&device, 3, Layer::Composed, norm);
                assert_eq!(a, b, "{norm:?}");
            }
        }
    }
}
