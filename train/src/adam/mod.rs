//! Adam in a few kernels per model step on CubeCL devices (design.md §9.4).
//!
//! Burn's `Adam` updates a parameter with about a dozen tensor ops (two moment updates, the
//! square, the bias corrections, the square root, the division, the step), each one kernel on a
//! GPU: about 3,900 of the 20,900 kernels a quickstart training step launched on wgpu
//! (BENCHMARKS.md, "Kernel launches per training step"). [`FusedAdam`] computes the same update
//! in one kernel per parameter there ([`op::AdamStepOps`], `cube` module): read the parameter,
//! its gradient and both moments, write all three back. The trainer's [`AdamOptimizer`]
//! ([`batch`]) goes further: one launch steps up to 32 parameters ([`op::AdamBatchOps`]), 14
//! launches for the quickstart model's 303 parameters.
//!
//! - Its state is Burn's [`AdamState`]: checkpoints written with Burn's `Adam` load, and the
//!   other way round.
//! - On the CPU backends it *is* Burn's `Adam` (it calls it), so training there is unchanged to
//!   the bit.
//! - It does what `AdamConfig::new()` does: no weight decay, no AMSGrad, no gradient clipping
//!   (the trainer uses none of them).
//!
//! **A non-finite gradient on a GPU.** On the CPU backends the trainer reads every gradient
//! before the step (they are on the host already). On a GPU that would cost a read-back or a
//! reduction per parameter, so the step kernels watch instead: with a [`GradientWatch`] armed,
//! each kernel sets a one-element flag wherever its gradient is NaN or infinite, the same flag
//! passing from one launch to the next. The trainer reads it once after the step (one
//! read-back, no extra launch) and, if it is set, puts back the weights and the optimiser state
//! it kept from before the step: the step is not applied (design.md §1.6).

pub mod batch;
pub(crate) mod cube;
pub mod op;

pub use batch::AdamOptimizer;

use std::sync::{Arc, Mutex, PoisonError};

use burn::backend::Dispatch;
use burn::backend::tensor::FloatTensor;
use burn::optim::{Adam, AdamConfig, AdamState, AdaptiveMomentumState, LearningRate, Optimizer};
use burn::tensor::{Device, Tensor, TensorData};
use lifegom_render::device::runs_on_host;
use lifegom_render::readback::{self, ReadbackError};

use batch::{Filed, Phase, StepBatch};
use op::{AdamScalars, MomentInputs};

/// Adam's hyper-parameters (Burn's defaults).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FusedAdamConfig {
    /// Decay of the first moment.
    pub beta_1: f32,
    /// Decay of the second moment.
    pub beta_2: f32,
    /// Added to the second moment's square root.
    pub epsilon: f32,
}

impl Default for FusedAdamConfig {
    /// Burn's `AdamConfig::new()`: β₁ = 0.9, β₂ = 0.999, ε = 1e-5.
    fn default() -> Self {
        Self {
            beta_1: 0.9,
            beta_2: 0.999,
            epsilon: 1e-5,
        }
    }
}

impl FusedAdamConfig {
    /// The optimizer, reporting non-finite gradients to `watch` when it is armed.
    pub fn init_watched(self, watch: GradientWatch) -> FusedAdam {
        FusedAdam {
            watch,
            ..self.init()
        }
    }

    /// The optimizer.
    pub fn init(self) -> FusedAdam {
        FusedAdam {
            watch: GradientWatch::default(),
            batch: StepBatch::default(),
            config: self,
            host: AdamConfig::new()
                .with_beta_1(self.beta_1)
                .with_beta_2(self.beta_2)
                .with_epsilon(self.epsilon)
                .build(),
        }
    }
}

/// Adam with a one-kernel step on CubeCL devices and Burn's `Adam` on the CPU backends (module
/// docs).
#[derive(Clone)]
pub struct FusedAdam {
    config: FusedAdamConfig,
    watch: GradientWatch,
    /// Burn's Adam with the same hyper-parameters: the CPU path.
    host: Adam,
    /// Whether a device step files, applies or runs alone ([`batch`]).
    batch: StepBatch,
}

impl std::fmt::Debug for FusedAdam {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("FusedAdam")
            .field("config", &self.config)
            .finish_non_exhaustive()
    }
}

impl Optimizer for FusedAdam {
    type State<const D: usize> = AdamState<D>;

    fn step<const D: usize>(
        &self,
        lr: LearningRate,
        tensor: Tensor<D>,
        grad: Tensor<D>,
        state: Option<Self::State<D>>,
    ) -> (Tensor<D>, Option<Self::State<D>>) {
        if runs_on_host(&tensor.device()) {
            return self.host.step(lr, tensor, grad, state);
        }
        let (time, moments) = match &state {
            Some(AdamState { momentum }) => (
                momentum.time + 1,
                Some((momentum.moment_1.clone(), momentum.moment_2.clone())),
            ),
            None => (1, None),
        };
        let shape = tensor.shape();
        if shape.num_elements() == 0 {
            // Nothing to update and no buffer to bind: the step only counts, once (in the walk
            // that applies, not the one that gathers).
            if matches!(*self.batch.phase(), Phase::Gather(_)) {
                return (tensor, state);
            }
            let empty = tensor.clone();
            let momentum = AdaptiveMomentumState::new(time, empty.clone(), empty);
            return (tensor, Some(AdamState::new(momentum)));
        }
        let flat = |t: Tensor<D>| t.reshape([shape.num_elements()]);
        match &mut *self.batch.phase() {
            Phase::Single => {}
            Phase::Gather(filed) => {
                filed.push(Filed {
                    param: flat(tensor.clone()),
                    grad: flat(grad),
                    moments: moments.map(|(m, v)| (flat(m), flat(v))),
                    time,
                    lr,
                    shape,
                });
                return (tensor, state);
            }
            Phase::Apply(stepped) => {
                let next = stepped
                    .pop_front()
                    .expect("the apply walk visits no more parameters than the gather walk filed");
                let (param, state) = next.into_step::<D>(&shape);
                return (param, Some(state));
            }
        }
        let scalars = AdamScalars::new(&self.config, time, lr);
        let grad = flat(grad).into_dispatch();
        let (inputs, moment_1, moment_2) = match moments {
            Some((m, v)) => (
                MomentInputs::Given,
                flat(m).into_dispatch(),
                flat(v).into_dispatch(),
            ),
            None => (MomentInputs::Zero, grad.clone(), grad.clone()),
        };
        let (param, moment_1, moment_2) = self.watch.with_flag(&tensor.device(), |watch| {
            let (param, moment_1, moment_2, watch) =
                <burn::backend::Dispatch as op::AdamStepOps>::adam_step(
                    flat(tensor).into_dispatch(),
                    grad,
                    moment_1,
                    moment_2,
                    watch,
                    inputs,
                    scalars,
                );
            ((param, moment_1, moment_2), watch)
        });
        let back = |t| Tensor::<1>::from_dispatch(t).reshape(shape.clone());
        let momentum = AdaptiveMomentumState::new(time, back(moment_1), back(moment_2));
        (back(param), Some(AdamState::new(momentum)))
    }

    fn to_device<const D: usize>(state: Self::State<D>, device: &Device) -> Self::State<D> {
        <Adam as Optimizer>::to_device(state, device)
    }
}

/// A flag that the GPU step kernels set when a gradient is not finite (module docs), shared
/// between the trainer, which arms and reads it, and the optimizer inside its
/// `ModuleOptimizer`. Clones share one flag.
#[derive(Debug, Clone, Default)]
pub struct GradientWatch {
    /// The flag while the watch is armed, `None` otherwise.
    flag: Arc<Mutex<Option<Tensor<1>>>>,
}

impl GradientWatch {
    /// Starts watching the next optimizer step on `device` with a cleared flag (an upload, no
    /// kernel launch). On the CPU backends nothing is watched: their steps do not run the
    /// kernels, and the trainer checks their gradients on the host.
    pub fn arm(&self, device: &Device) {
        if runs_on_host(device) {
            return;
        }
        let device = device.clone().inner();
        *self.flag.lock().unwrap_or_else(PoisonError::into_inner) =
            Some(Tensor::from_data(TensorData::from([0.0f32]), &device));
    }

    /// Runs `launch` with the flag its kernels set for a non-finite gradient and takes the flag
    /// it hands back: the armed flag, or a fresh one nobody reads when the watch is not armed.
    fn with_flag<R>(
        &self,
        device: &Device,
        launch: impl FnOnce(FloatTensor<Dispatch>) -> (R, FloatTensor<Dispatch>),
    ) -> R {
        let mut slot = self.flag.lock().unwrap_or_else(PoisonError::into_inner);
        let armed = slot.is_some();
        let flag = match slot.take() {
            Some(flag) => flag,
            None => Tensor::<1>::from_data(TensorData::from([0.0f32]), device),
        };
        let (result, flag) = launch(flag.into_dispatch());
        if armed {
            *slot = Some(Tensor::from_dispatch(flag));
        }
        result
    }

    /// Whether a gradient of the watched step was not finite: one read-back of the flag, which
    /// waits for the step's kernels. Disarms the watch. `false` when nothing was watched.
    pub fn tripped(&self) -> Result<bool, ReadbackError> {
        let flag = self
            .flag
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .take();
        match flag {
            Some(flag) => Ok(readback::read::<f32, 1, _>("gradient watch", flag)?[0] != 0.0),
            None => Ok(false),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::tensor::TensorData;
    use lifegom_render::device::DeviceChoice;
    use lifegom_render::testing::{Rng, read, wgpu_test_device};

    fn tensor(values: &[f32], shape: [usize; 2], device: &Device) -> Tensor<2> {
        Tensor::from_data(TensorData::new(values.to_vec(), shape), device)
    }

    /// Four steps of [`FusedAdam`] and of Burn's `Adam` from the same parameter, with a fresh
    /// gradient each step (one of them zero where the moments must decay alone): parameters and
    /// both moments agree after every step, within `tolerance` relative to each value's scale.
    fn check_against_burn_adam(device: &Device, tolerance: f32) {
        let shape = [7, 5];
        let n = 35;
        let mut rng = Rng::new(3);
        let mut draw =
            |scale: f32| -> Vec<f32> { (0..n).map(|_| scale * rng.range_f32(-1.0, 1.0)).collect() };
        let start = draw(1.0);
        let grads: Vec<Vec<f32>> = vec![draw(1.0), draw(1e-3), vec![0.0; n], draw(10.0)];
        let fused = FusedAdamConfig::default().init();
        let burn_adam = AdamConfig::new().build();
        let (mut p_fused, mut p_burn) =
            (tensor(&start, shape, device), tensor(&start, shape, device));
        let (mut s_fused, mut s_burn) = (None, None);
        for (step, g) in grads.iter().enumerate() {
            let lr = [1e-3, 5e-4, 1e-3, 2e-2][step];
            (p_fused, s_fused) = fused.step(lr, p_fused, tensor(g, shape, device), s_fused);
            (p_burn, s_burn) = burn_adam.step(lr, p_burn, tensor(g, shape, device), s_burn);
            let (a, b): (&AdamState<2>, &AdamState<2>) = (
                s_fused.as_ref().expect("a state"),
                s_burn.as_ref().expect("a state"),
            );
            assert_eq!(a.momentum.time, b.momentum.time);
            for (what, x, y) in [
                ("parameter", p_fused.clone(), p_burn.clone()),
                (
                    "first moment",
                    a.momentum.moment_1.clone(),
                    b.momentum.moment_1.clone(),
                ),
                (
                    "second moment",
                    a.momentum.moment_2.clone(),
                    b.momentum.moment_2.clone(),
                ),
            ] {
                let (x, y) = (read(x), read(y));
                let scale = y.iter().fold(0f32, |m, v| m.max(v.abs())).max(1e-30);
                for (i, (u, v)) in x.iter().zip(&y).enumerate() {
                    assert!(
                        (u - v).abs() <= tolerance * scale,
                        "step {}: {what}[{i}] = {u}, Burn's Adam {v}",
                        step + 1
                    );
                }
            }
        }
    }

    /// How a watch test steps its layer: parameter by parameter through Burn's
    /// `ModuleOptimizer`, or batched through the trainer's [`AdamOptimizer`].
    #[derive(Clone, Copy, Debug)]
    enum Walk {
        PerParameter,
        Batched,
    }

    /// On wgpu an armed [`GradientWatch`] reports a gradient with one infinite or NaN element,
    /// in any parameter of the step, both per parameter and batched; it stays clear for finite
    /// gradients, and a watch that was not armed reports nothing.
    #[test]
    fn watch_reports_a_non_finite_gradient_wgpu() {
        let Some(device) = wgpu_test_device() else {
            return;
        };
        for walk in [Walk::PerParameter, Walk::Batched] {
            check_watch(&device, walk);
        }
    }

    fn check_watch(device: &Device, walk: Walk) {
        use burn::nn::{Linear, LinearConfig};
        use burn::optim::{GradientsParams, ModuleOptimizer};
        let ad = device.clone().autodiff();
        let watch = GradientWatch::default();
        let config = FusedAdamConfig::default();
        let mut single = ModuleOptimizer::from(config.init_watched(watch.clone()));
        let mut batched = AdamOptimizer::new(config, watch.clone());
        let mut layer: Linear = LinearConfig::new(2, 3).init(&ad);
        let mut step = |weight: [f32; 6], bias: [f32; 3], armed: bool| {
            let mut grads = GradientsParams::new();
            grads.register(layer.weight.id, tensor(&weight, [2, 3], device));
            let bias_id = layer.bias.as_ref().expect("a bias").id;
            grads.register(
                bias_id,
                Tensor::<1>::from_data(TensorData::from(bias), device),
            );
            if armed {
                watch.arm(&ad);
            }
            let before = read(layer.weight.val());
            layer = match walk {
                Walk::PerParameter => single.step(1e-3, layer.clone(), grads),
                Walk::Batched => batched.step(1e-3, layer.clone(), grads),
            };
            let moved = read(layer.weight.val()) != before;
            (watch.tripped().expect("the flag reads back"), moved)
        };
        let finite = [0.5, -1.0, 2.0, 0.25, 1e-3, -3.0];
        assert_eq!(
            step(finite, [1.0, 2.0, 3.0], true),
            (false, true),
            "{walk:?}"
        );
        let mut infinite = finite;
        infinite[4] = f32::INFINITY;
        assert!(
            step(infinite, [1.0, 2.0, 3.0], true).0,
            "{walk:?}: an infinite weight gradient"
        );
        assert!(
            step(finite, [1.0, f32::NAN, 3.0], true).0,
            "{walk:?}: a NaN bias gradient"
        );
        assert!(
            !step(finite, [1.0, 2.0, 3.0], true).0,
            "{walk:?}: the flag starts clear each step"
        );
        assert!(
            !step(infinite, [1.0, 2.0, 3.0], false).0,
            "{walk:?}: an unarmed watch reported"
        );
    }

    /// On the CPU backends the fused optimizer is Burn's: equal to the bit.
    #[test]
    fn equals_burn_adam_on_cpu() {
        for choice in DeviceChoice::CPU {
            check_against_burn_adam(&choice.device(), 0.0);
        }
    }

    /// On wgpu (lavapipe in CI) the one-kernel step agrees with Burn's op-by-op Adam to float
    /// rounding (the kernel may contract a multiply and an add).
    #[test]
    fn matches_burn_adam_wgpu() {
        let Some(device) = wgpu_test_device() else {
            return;
        };
        check_against_burn_adam(&device, 1e-6);
    }
}
