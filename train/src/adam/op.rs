//! The fused Adam step as a Burn backend extension for CubeCL devices.
//!
//! Listed for `Cube` only: [`super::FusedAdam`] never routes the CPU backends here, and the
//! optimizer runs outside autodiff (Burn hands it the parameters' inner tensors).

use burn::backend::tensor::FloatTensor;
use burn::backend::{Backend, backend_extension};
use burn::optim::LearningRate;

use super::FusedAdamConfig;

/// The per-step scalars of the update, in `f32`, computed the way Burn's `Adam` computes them
/// (so the kernel multiplies by the same rounded factors).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AdamScalars {
    /// β₁.
    pub beta_1: f32,
    /// 1 − β₁.
    pub one_minus_beta_1: f32,
    /// β₂.
    pub beta_2: f32,
    /// 1 − β₂.
    pub one_minus_beta_2: f32,
    /// `√(1 − β₂ᵗ) / (1 − β₁ᵗ)`: both bias corrections in one factor on the first moment.
    pub moment_factor: f32,
    /// `ε·√(1 − β₂ᵗ)`, added to `√v` (ε scaled by the same correction Burn scales it by).
    pub epsilon: f32,
    /// The learning rate.
    pub lr: f32,
}

impl AdamScalars {
    /// The scalars of step `time` (1 for the first step) at learning rate `lr`.
    pub fn new(config: &FusedAdamConfig, time: usize, lr: LearningRate) -> Self {
        let t = time.min(i32::MAX as usize) as i32;
        let bias_correction_2_sqrt = (1.0 - config.beta_2.powi(t)).sqrt();
        Self {
            beta_1: config.beta_1,
            one_minus_beta_1: 1.0 - config.beta_1,
            beta_2: config.beta_2,
            one_minus_beta_2: 1.0 - config.beta_2,
            moment_factor: bias_correction_2_sqrt / (1.0 - config.beta_1.powi(t)),
            epsilon: config.epsilon * bias_correction_2_sqrt,
            lr: lr as f32,
        }
    }
}

/// Where a step's moments start from.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum MomentInputs {
    /// The first step: both moments start at zero and the moment arguments are not read (pass
    /// any `[n]` tensor, e.g. the gradient).
    Zero,
    /// The moment arguments hold the previous step's moments.
    Given,
}

/// One Adam step of a flat parameter `[n]`, in one kernel.
#[backend_extension(Cube, Fusion)]
pub trait AdamStepOps: Backend {
    /// `param`, `grad` and the moments are `[n]`; `watch` is `[1]`. Returns the updated
    /// parameter and moments, and `watch` itself, set to 1 where any element of `grad` is not
    /// finite and otherwise left as it was: the same buffer, so that one flag threaded through
    /// every parameter's step of an optimiser step reports the whole gradient
    /// ([`super::GradientWatch`]).
    #[fusion(meta = |param, _grad, _moment_1, _moment_2, watch, _inputs, _scalars| {
        (param.clone(), param.clone(), param.clone(), watch.clone())
    })]
    fn adam_step(
        param: FloatTensor<Self>,
        grad: FloatTensor<Self>,
        moment_1: FloatTensor<Self>,
        moment_2: FloatTensor<Self>,
        watch: FloatTensor<Self>,
        inputs: MomentInputs,
        scalars: AdamScalars,
    ) -> (
        FloatTensor<Self>,
        FloatTensor<Self>,
        FloatTensor<Self>,
        FloatTensor<Self>,
    );
}
