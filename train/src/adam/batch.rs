//! A whole model's Adam step in a few launches on CubeCL devices (design.md §9.4).
//!
//! Burn's [`ModuleOptimizer`] walks the model and steps one parameter at a time, so even with
//! [`FusedAdam`](super::FusedAdam)'s one-kernel update a step launches one kernel per parameter:
//! 303 of a quickstart training step's 3,874. [`AdamOptimizer`] keeps the `ModuleOptimizer` — its
//! per-parameter state, parameter groups and learning rates, and the optimiser record that
//! checkpoints hold — and walks the model with it twice:
//!
//! 1. **Gather.** The optimiser inside files each parameter with its gradient, moments, step
//!    count and learning rate, and hands the parameter and its state back unchanged.
//! 2. The filed parameters, grouped by step count and learning rate, take their step through
//!    [`AdamBatchOps::adam_step_batch`](super::op::AdamBatchOps): up to 32 parameters a launch,
//!    into three flat outputs whose per-parameter segments are views, not copies.
//! 3. **Apply.** The second walk visits the same parameters in the same order (the same model and
//!    gradients), and the optimiser hands each its new values and state from the queue.
//!
//! Both walks are Burn's own mapping of the model; neither launches a kernel. The record format is
//! the `ModuleOptimizer`'s, so checkpoints written before the batched step load, and the other
//! way round. On the CPU backends the step is the `ModuleOptimizer`'s (Burn's `Adam` per
//! parameter), unchanged to the bit.

use std::collections::{BTreeMap, VecDeque};
use std::sync::{Arc, Mutex, MutexGuard, PoisonError};

use burn::module::{Module, ModuleVisitor, Param};
use burn::optim::lr_scheduler::module_lr_scheduler::ModuleLearningRate;
use burn::optim::{
    AdamState, AdaptiveMomentumState, GradientsParams, LearningRate, ModuleOptimizer,
};
use burn::store::RecordError;
use burn::tensor::{Bytes, Shape, Tensor};
use lifegom_render::device::runs_on_host;

use super::op::{AdamBatch, AdamBatchOps, AdamScalars, MomentInputs};
use super::{FusedAdamConfig, GradientWatch};

/// A parameter filed by the gather walk, flattened.
pub(super) struct Filed {
    pub(super) param: Tensor<1>,
    pub(super) grad: Tensor<1>,
    /// The moments of the previous step; `None` before the first.
    pub(super) moments: Option<(Tensor<1>, Tensor<1>)>,
    /// The step count this update makes (1 for the first).
    pub(super) time: usize,
    pub(super) lr: LearningRate,
    pub(super) shape: Shape,
}

/// A parameter's new values for the apply walk, flattened.
pub(super) struct Stepped {
    param: Tensor<1>,
    moment_1: Tensor<1>,
    moment_2: Tensor<1>,
    time: usize,
    shape: Shape,
}

impl Stepped {
    /// The new parameter and its state, in the parameter's shape; `shape` is the shape of the
    /// parameter the apply walk is at, which must be the one filed at this place.
    pub(super) fn into_step<const D: usize>(self, shape: &Shape) -> (Tensor<D>, AdamState<D>) {
        assert_eq!(
            &self.shape, shape,
            "the apply walk met a parameter other than the one the gather walk filed here"
        );
        let dims: [usize; D] = self.shape.dims::<D>();
        let momentum = AdaptiveMomentumState::new(
            self.time,
            self.moment_1.reshape(dims),
            self.moment_2.reshape(dims),
        );
        (self.param.reshape(dims), AdamState::new(momentum))
    }
}

/// What [`FusedAdam::step`](super::FusedAdam) does with a device parameter (module docs).
#[derive(Default)]
pub(super) enum Phase {
    /// Step it alone, in one launch (outside [`AdamOptimizer::step`]).
    #[default]
    Single,
    /// File it and hand it back unchanged.
    Gather(Vec<Filed>),
    /// Hand back the next stepped parameter.
    Apply(VecDeque<Stepped>),
}

/// The phase of the optimiser's walk, shared between the [`AdamOptimizer`] and the
/// `FusedAdam` its `ModuleOptimizer` owns. Clones share one phase.
#[derive(Clone, Default)]
pub(super) struct StepBatch(Arc<Mutex<Phase>>);

impl StepBatch {
    pub(super) fn phase(&self) -> MutexGuard<'_, Phase> {
        self.0.lock().unwrap_or_else(PoisonError::into_inner)
    }

    fn replace(&self, phase: Phase) -> Phase {
        std::mem::replace(&mut *self.phase(), phase)
    }
}

/// Adam over a whole model: Burn's [`ModuleOptimizer`] around a [`FusedAdam`](super::FusedAdam),
/// stepping every parameter of a device model in a few launches (module docs).
#[derive(Clone)]
pub struct AdamOptimizer {
    optim: ModuleOptimizer,
    batch: StepBatch,
    config: FusedAdamConfig,
    watch: GradientWatch,
}

impl AdamOptimizer {
    /// A fresh optimiser whose device steps report non-finite gradients to `watch` when it is
    /// armed.
    pub fn new(config: FusedAdamConfig, watch: GradientWatch) -> Self {
        let adam = config.init_watched(watch.clone());
        let batch = adam.batch.clone();
        Self {
            optim: ModuleOptimizer::from(adam),
            batch,
            config,
            watch,
        }
    }

    /// Steps every parameter of `module` that has a gradient in `grads`, at the learning rates of
    /// `lr`, and returns the updated module.
    pub fn step<M: Module>(
        &mut self,
        lr: impl Into<ModuleLearningRate>,
        module: M,
        grads: GradientsParams,
    ) -> M {
        let lr = lr.into();
        let mut copy = GradientsCopy {
            source: &grads,
            copy: GradientsParams::new(),
            on_host: None,
        };
        module.visit(&mut copy);
        let again = copy.copy;
        if copy.on_host != Some(false) {
            return self.optim.step(lr, module, grads);
        }
        self.batch.replace(Phase::Gather(Vec::new()));
        let module = self.optim.step(lr.clone(), module, grads);
        let Phase::Gather(filed) = self.batch.replace(Phase::Single) else {
            unreachable!("only this walk sets the gather phase");
        };
        let stepped = step_filed(filed, &self.config, &self.watch);
        self.batch.replace(Phase::Apply(stepped));
        let module = self.optim.step(lr, module, again);
        match self.batch.replace(Phase::Single) {
            Phase::Apply(left) if left.is_empty() => module,
            _ => unreachable!("the apply walk visits every parameter the gather walk filed"),
        }
    }

    /// The optimiser state as Burn's optimiser record (burnpack bytes).
    pub fn into_bytes(&self) -> Result<Bytes, RecordError> {
        self.optim.into_bytes()
    }

    /// This optimiser with the state of a record written by [`Self::into_bytes`] (or by Burn's
    /// `ModuleOptimizer` around Burn's `Adam` or a [`FusedAdam`](super::FusedAdam)).
    pub fn from_bytes(self, bytes: Bytes) -> Result<Self, RecordError> {
        Ok(Self {
            optim: self.optim.from_bytes(bytes)?,
            ..self
        })
    }
}

/// Copies `source`'s gradient of every parameter of the visited module into `copy` (handles,
/// not data), for the second walk, on a CubeCL device.
struct GradientsCopy<'a> {
    source: &'a GradientsParams,
    copy: GradientsParams,
    /// Whether the gradients are on a CPU backend (known from the first); there the walk is
    /// Burn's alone and copies nothing.
    on_host: Option<bool>,
}

impl ModuleVisitor for GradientsCopy<'_> {
    fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
        if self.on_host == Some(true) {
            return;
        }
        if let Some(grad) = self.source.get::<D>(param.id)
            && !*self
                .on_host
                .get_or_insert_with(|| runs_on_host(&grad.device()))
        {
            self.copy.register(param.id, grad);
        }
    }
}

/// One step of every filed parameter: a batched op per group of equal step count and learning
/// rate, the results in filing order.
fn step_filed(
    filed: Vec<Filed>,
    config: &FusedAdamConfig,
    watch: &GradientWatch,
) -> VecDeque<Stepped> {
    let mut groups: BTreeMap<(usize, u64), Vec<usize>> = BTreeMap::new();
    for (i, f) in filed.iter().enumerate() {
        groups.entry((f.time, f.lr.to_bits())).or_default().push(i);
    }
    let mut slots: Vec<Option<Stepped>> = filed.iter().map(|_| None).collect();
    let mut filed: Vec<Option<Filed>> = filed.into_iter().map(Some).collect();
    for ((time, _), members) in groups {
        let group: Vec<Filed> = members
            .iter()
            .map(|&i| filed[i].take().expect("each parameter is in one group"))
            .collect();
        let scalars = AdamScalars::new(config, time, group[0].lr);
        let inputs = if group[0].moments.is_some() {
            MomentInputs::Given
        } else {
            MomentInputs::Zero
        };
        let device = group[0].param.device();
        let mut batch = AdamBatch {
            params: Vec::new(),
            grads: Vec::new(),
            moments_1: Vec::new(),
            moments_2: Vec::new(),
        };
        let mut shapes = Vec::new();
        for f in group {
            batch.params.push(f.param.into_dispatch());
            batch.grads.push(f.grad.into_dispatch());
            if let Some((m, v)) = f.moments {
                batch.moments_1.push(m.into_dispatch());
                batch.moments_2.push(v.into_dispatch());
            }
            shapes.push(f.shape);
        }
        let stepped = watch.with_flag(&device, |flag| {
            <burn::backend::Dispatch as AdamBatchOps>::adam_step_batch(batch, flag, inputs, scalars)
        });
        let outputs = stepped
            .params
            .into_iter()
            .zip(stepped.moments_1)
            .zip(stepped.moments_2);
        for ((&i, shape), ((param, moment_1), moment_2)) in members.iter().zip(shapes).zip(outputs)
        {
            slots[i] = Some(Stepped {
                param: Tensor::from_dispatch(param),
                moment_1: Tensor::from_dispatch(moment_1),
                moment_2: Tensor::from_dispatch(moment_2),
                time,
                shape,
            });
        }
    }
    slots
        .into_iter()
        .map(|s| s.expect("every filed parameter was stepped"))
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::module::ParamGroup;
    use burn::optim::AdamConfig;
    use burn::optim::lr_scheduler::LrSchedulerConfig;
    use burn::optim::lr_scheduler::module_lr_scheduler::ModuleLrSchedulerConfig;
    use burn::tensor::{Device, TensorData};
    use lifegom_render::testing::{Rng, read, wgpu_test_device};

    /// Parameters of ranks 1 to 3, sizes from none or one element to several cubes, and more of
    /// them than one launch binds (`cube::BATCH_SLOTS`).
    #[derive(Module, Debug)]
    struct Parts {
        small: Vec<Param<Tensor<1>>>,
        plane: Param<Tensor<2>>,
        /// No elements: stepped without a launch.
        empty: Param<Tensor<2>>,
        block: Param<Tensor<3>>,
        other: Vec<Param<Tensor<2>>>,
    }

    fn draw(rng: &mut Rng, n: usize, scale: f32) -> Vec<f32> {
        (0..n).map(|_| scale * rng.range_f32(-1.0, 1.0)).collect()
    }

    fn parts(device: &Device) -> Parts {
        let mut rng = Rng::new(11);
        let mut tensor = |shape: Vec<usize>| {
            let n = shape.iter().product();
            TensorData::new(draw(&mut rng, n, 1.0), shape)
        };
        Parts {
            small: (0..37)
                .map(|i| Param::from_data(tensor(vec![1 + i % 5]), device))
                .collect(),
            plane: Param::from_data(tensor(vec![17, 33]), device),
            empty: Param::from_data(tensor(vec![0, 4]), device),
            block: Param::from_data(tensor(vec![3, 2, 100]), device),
            other: (0..2)
                .map(|_| Param::from_data(tensor(vec![4, 70]), device))
                .collect(),
        }
    }

    /// Every parameter's values, in module order.
    fn values(parts: &Parts) -> Vec<Vec<f32>> {
        let mut out: Vec<Vec<f32>> = parts.small.iter().map(|p| read(p.val())).collect();
        out.push(read(parts.plane.val()));
        out.push(read(parts.block.val()));
        out.extend(parts.other.iter().map(|p| read(p.val())));
        out
    }

    /// Gradients equal to `scale`·(a fixed draw) for every parameter but the last `other`,
    /// which has none (so it keeps its step count behind the rest).
    fn gradients(parts: &Parts, seed: u64, scale: f32, device: &Device) -> GradientsParams {
        struct Draw<'a> {
            rng: Rng,
            device: &'a Device,
            scale: f32,
            skip: burn::module::ParamId,
            grads: &'a mut GradientsParams,
        }
        impl ModuleVisitor for Draw<'_> {
            fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
                if param.id == self.skip {
                    return;
                }
                let shape = param.val().shape();
                let data = draw(&mut self.rng, shape.num_elements(), self.scale);
                let grad = Tensor::<D>::from_data(TensorData::new(data, shape), self.device);
                self.grads.register(param.id, grad);
            }
        }
        let mut grads = GradientsParams::new();
        parts.visit(&mut Draw {
            rng: Rng::new(seed),
            device,
            scale,
            skip: parts.other[1].id,
            grads: &mut grads,
        });
        grads
    }

    /// Two learning rates: the `small` parameters at one, the rest at another.
    fn learning_rates(parts: &Parts) -> ModuleLearningRate {
        let group = ParamGroup::ids_from_module(parts.small.clone());
        ModuleLrSchedulerConfig::new(LrSchedulerConfig::Constant(2e-3))
            .with_group(group, LrSchedulerConfig::Constant(5e-4))
            .init()
            .expect("constant learning rates")
            .step()
    }

    fn assert_close(step: usize, ours: &[Vec<f32>], burn: &[Vec<f32>], tolerance: f32) {
        assert_eq!(ours.len(), burn.len());
        for (k, (x, y)) in ours.iter().zip(burn).enumerate() {
            let scale = y.iter().fold(0f32, |m, v| m.max(v.abs())).max(1e-30);
            for (i, (u, v)) in x.iter().zip(y).enumerate() {
                assert!(
                    (u - v).abs() <= tolerance * scale,
                    "step {step}: parameter {k}[{i}] = {u}, Burn's Adam {v}"
                );
            }
        }
    }

    /// Four steps of the batched optimiser and of Burn's `ModuleOptimizer` around Burn's `Adam`
    /// on the same module: two learning rates, a parameter left without gradient until the last
    /// step (so two step counts meet in one walk), and after step 2 each optimiser continuing
    /// from the other's record. Every parameter agrees after every step within `tolerance`.
    fn check_against_burn(device: &Device, tolerance: f32) {
        let start = parts(&device.clone().autodiff());
        let lr = learning_rates(&start);
        let mut ours = AdamOptimizer::new(FusedAdamConfig::default(), GradientWatch::default());
        let mut burn = ModuleOptimizer::from(AdamConfig::new().build());
        let (mut a, mut b) = (start.clone(), start);
        for step in 1..=4 {
            let scale = [1.0, 1e-3, 10.0, 0.5][step - 1];
            let seed = step as u64;
            let (ga, mut gb) = (
                gradients(&a, seed, scale, device),
                gradients(&b, seed, scale, device),
            );
            let (mut ga, last) = (ga, step == 4);
            if last {
                // The parameter skipped so far takes its first step now.
                let g = Tensor::<2>::ones([4, 70], device);
                ga.register(a.other[1].id, g.clone());
                gb.register(b.other[1].id, g);
            }
            a = ours.step(lr.clone(), a, ga);
            b = burn.step(lr.clone(), b, gb);
            assert_close(step, &values(&a), &values(&b), tolerance);
            if step == 2 {
                // Each optimiser goes on from the other's record: the formats are one.
                let (ours_bytes, burn_bytes) = (
                    ours.into_bytes().expect("our record writes"),
                    burn.into_bytes().expect("Burn's record writes"),
                );
                ours = AdamOptimizer::new(FusedAdamConfig::default(), GradientWatch::default())
                    .from_bytes(burn_bytes)
                    .expect("Burn's record reads");
                burn = ModuleOptimizer::from(AdamConfig::new().build())
                    .from_bytes(ours_bytes)
                    .expect("our record reads");
            }
        }
    }

    /// On wgpu (lavapipe in CI) the batched step agrees with Burn's op-by-op Adam to rounding.
    #[test]
    fn batched_step_matches_burn_adam_wgpu() {
        let Some(device) = wgpu_test_device() else {
            return;
        };
        check_against_burn(&device, 1e-6);
    }

    /// On the CPU backends the optimiser is Burn's `ModuleOptimizer` around Burn's `Adam`: equal
    /// to the bit.
    #[test]
    fn equals_burn_adam_on_cpu() {
        for choice in lifegom_render::device::DeviceChoice::CPU {
            check_against_burn(&choice.device(), 0.0);
        }
    }
}
