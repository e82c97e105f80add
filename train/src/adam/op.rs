//! The fused Adam step as a Burn backend extension for CubeCL devices.
//!
//! Listed for `Cube` only: [`super::FusedAdam`] never routes the CPU backends here, and the
//! optimizer runs outside autodiff (Burn hands it the parameters' inner tensors).

use burn::backend::fusion::{Fusion, FusionBackend};
use burn::backend::tensor::FloatTensor;
use burn::backend::{
    Backend, BackendTensor, Dispatch, DispatchAutodiffContext, DispatchTensor, DispatchTensorKind,
    ExtensionType, TensorMetadata, backend_extension,
};
use burn::optim::LearningRate;
use lifegom_render::cube::deferred::{Input, Value, deferred, float_like};
use lifegom_render::cube::host::THREADS_1D;

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

/// Threads per cube of the batched step; each parameter of a batch starts a fresh cube, so its
/// segment of a batch's flat outputs starts at a multiple of this many elements.
pub const SEGMENT_ALIGN: usize = THREADS_1D as usize;

/// Where each of `lens` parameters (element counts) starts in a batch's flat outputs, and the
/// outputs' length: one segment per parameter, each a whole number of [`SEGMENT_ALIGN`]-element
/// cubes (at least one), so every segment starts 1 KiB-aligned and its slice is a view, not a
/// copy.
pub fn segment_starts(lens: &[usize]) -> (Vec<usize>, usize) {
    let mut starts = Vec::with_capacity(lens.len());
    let mut end = 0;
    for &len in lens {
        starts.push(end);
        end += len.div_ceil(SEGMENT_ALIGN).max(1) * SEGMENT_ALIGN;
    }
    (starts, end)
}

/// The parameters of a batched step and what their update reads, one entry per parameter in
/// every list (the moments' lists empty on a first step, [`MomentInputs::Zero`]).
#[derive(Debug, Clone)]
pub struct AdamBatch<B: Backend> {
    /// The parameters, flat `[nᵢ]`; at least one.
    pub params: Vec<FloatTensor<B>>,
    /// Their gradients `[nᵢ]`.
    pub grads: Vec<FloatTensor<B>>,
    /// Their first moments `[nᵢ]`.
    pub moments_1: Vec<FloatTensor<B>>,
    /// Their second moments `[nᵢ]`.
    pub moments_2: Vec<FloatTensor<B>>,
}

impl<B: Backend> AdamBatch<B> {
    /// Every tensor, lists in field order.
    fn into_tensors(self) -> impl Iterator<Item = FloatTensor<B>> {
        self.params
            .into_iter()
            .chain(self.grads)
            .chain(self.moments_1)
            .chain(self.moments_2)
    }

    /// The inverse of [`Self::into_tensors`] for `count` parameters.
    fn from_tensors(mut all: Vec<FloatTensor<B>>, count: usize, inputs: MomentInputs) -> Self {
        let (moments_1, moments_2) = match inputs {
            MomentInputs::Given => {
                let moments_2 = all.split_off(3 * count);
                (all.split_off(2 * count), moments_2)
            }
            MomentInputs::Zero => (Vec::new(), Vec::new()),
        };
        let grads = all.split_off(count);
        Self {
            params: all,
            grads,
            moments_1,
            moments_2,
        }
    }
}

/// A batch's new values: per parameter, in the batch's order, the parameter and its moments
/// `[nᵢ]`.
#[derive(Debug, Clone)]
pub struct AdamStepped<B: Backend> {
    /// The updated parameters.
    pub params: Vec<FloatTensor<B>>,
    /// Their first moments.
    pub moments_1: Vec<FloatTensor<B>>,
    /// Their second moments.
    pub moments_2: Vec<FloatTensor<B>>,
}

/// [`ExtensionType`] for a record of tensor lists: each list crosses the dispatch boundary
/// element by element (the derive takes single tensors, not lists); the first list routes.
macro_rules! list_record {
    ($name:ident { $route:ident $(, $field:ident)* }) => {
        impl<B: Backend> ExtensionType<B> for $name<B> {
            type Target = $name<Dispatch>;

            fn map_to_dispatch<F>(
                self,
                map_kind: F,
                autodiff: DispatchAutodiffContext,
            ) -> Self::Target
            where
                F: Fn(BackendTensor<B>) -> DispatchTensorKind,
            {
                let to = |list: Vec<FloatTensor<B>>| -> Vec<DispatchTensor> {
                    list.into_iter()
                        .map(|t| DispatchTensor {
                            kind: map_kind(BackendTensor::Float(t)),
                            autodiff,
                        })
                        .collect()
                };
                $name {
                    $route: to(self.$route),
                    $($field: to(self.$field),)*
                }
            }

            fn map_from_dispatch<F>(target: Self::Target, unwrap_kind: F) -> Self
            where
                F: Fn(DispatchTensor) -> BackendTensor<B>,
            {
                let from = |list: Vec<DispatchTensor>| -> Vec<FloatTensor<B>> {
                    list.into_iter().map(|t| unwrap_kind(t).float()).collect()
                };
                $name {
                    $route: from(target.$route),
                    $($field: from(target.$field),)*
                }
            }

            fn routing_tensor(target: &Self::Target) -> Option<&DispatchTensor> {
                target.$route.first()
            }

            fn routing_float_tensor(target: &Self::Target) -> Option<&DispatchTensor> {
                target.$route.first()
            }

            fn autodiff_context(target: &Self::Target) -> DispatchAutodiffContext {
                target
                    .$route
                    .iter()
                    $(.chain(&target.$field))*
                    .fold(DispatchAutodiffContext::Disabled, |c, t| c.merge(t.autodiff))
            }
        }
    };
}

list_record!(AdamBatch {
    params,
    grads,
    moments_1,
    moments_2
});
list_record!(AdamStepped {
    params,
    moments_1,
    moments_2
});

/// Adam steps of several flat parameters at once (the batched step, [`super::batch`]).
///
/// Listed for `Cube` only: the fusion wrapper the macro writes does not take lists, so
/// `Fusion<B>` has a handwritten implementation that records the call as one deferred op. The
/// CPU backends never come here.
#[backend_extension(Cube)]
pub trait AdamBatchOps: Backend {
    /// One Adam step of every parameter of `batch`, all at the same step `scalars`. Returns the
    /// new parameters and moments, and `watch` as [`AdamStepOps::adam_step`] does. Each of the
    /// three kinds of output lies in one buffer, laid out by [`segment_starts`]: every output is
    /// a view of its segment. As few launches as the device's binding limit allows (up to 32
    /// parameters a launch).
    fn adam_step_batch(
        #[extension_type] batch: AdamBatch<Self>,
        watch: FloatTensor<Self>,
        inputs: MomentInputs,
        scalars: AdamScalars,
    ) -> (AdamStepped<Self>, FloatTensor<Self>);
}

impl<B: FusionBackend + AdamBatchOps> AdamBatchOps for Fusion<B> {
    fn adam_step_batch(
        batch: AdamBatch<Self>,
        watch: FloatTensor<Self>,
        inputs: MomentInputs,
        scalars: AdamScalars,
    ) -> (AdamStepped<Self>, FloatTensor<Self>) {
        let count = batch.params.len();
        let like = batch.params[0].clone();
        let specs = batch
            .params
            .iter()
            .map(|p| float_like::<B>(&like, p.shape()))
            .cycle()
            .take(3 * count)
            .chain([float_like::<B>(&watch, watch.shape())])
            .collect();
        let recorded = batch
            .into_tensors()
            .chain([watch])
            .map(Input::Float)
            .collect();
        let mut outputs = deferred::<B, _>("adam_step_batch", recorded, specs, move |mut v| {
            let watch = v
                .pop()
                .map(Value::float)
                .expect("the watch flag was recorded");
            let all = v.into_iter().map(Value::float).collect();
            let batch = AdamBatch::from_tensors(all, count, inputs);
            let (stepped, watch) = B::adam_step_batch(batch, watch, inputs, scalars);
            stepped
                .params
                .into_iter()
                .chain(stepped.moments_1)
                .chain(stepped.moments_2)
                .chain([watch])
                .map(Value::Float)
                .collect()
        });
        let watch = outputs.pop().expect("the watch flag is an output");
        let moments_2 = outputs.split_off(2 * count);
        let moments_1 = outputs.split_off(count);
        let stepped = AdamStepped {
            params: outputs,
            moments_1,
            moments_2,
        };
        (stepped, watch)
    }
}
