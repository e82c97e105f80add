//! The fused Adam step on Burn's CubeCL backend: one thread per parameter element reads the
//! parameter, its gradient and both moments and writes all three back, in the order of Burn's
//! op-by-op update (`m·β₁ + g·(1 − β₁)`, `v·β₂ + g²·(1 − β₂)`, `p − (m·c / (√v + ε'))·lr`).
//! A thread whose gradient is NaN or infinite also stores 1 into the one-element `watch`
//! buffer, which the op hands back as its fourth output: every writer stores the same value, so
//! the race between them is harmless, and a finite gradient writes nothing.
//!
//! The batched step ([`AdamBatchOps`]) runs the same update for up to [`BATCH_SLOTS`]
//! parameters a launch, each bound as a buffer of its own (a `Sequence` of buffers, unrolled in
//! the kernel): parameter `s` owns the launch's cubes `first_cube[s]..first_cube[s + 1]`, and each
//! thread writes its element at its own position in the flat outputs, where the parameters'
//! segments lie in the order of [`segment_starts`].

use burn::backend::TensorMetadata;
use burn::backend::tensor::FloatTensor;
use burn_cubecl::CubeBackend;
use burn_cubecl::cubecl;
use burn_cubecl::cubecl::prelude::*;
use burn_cubecl::cubecl::server::Handle;
use burn_cubecl::tensor::CubeTensor;
use lifegom_render::cube::host::{
    THREADS_1D, arg, cast_to, count_1d, prepare, tensor_arg, tensor_f32, u32_bytes,
};

use super::op::{
    AdamBatch, AdamBatchOps, AdamScalars, AdamStepOps, AdamStepped, MomentInputs, SEGMENT_ALIGN,
    segment_starts,
};

/// Adam's per-step factors as one kernel argument ([`AdamScalars`] on the host).
#[derive(CubeType, CubeLaunch)]
struct StepScalars {
    beta_1: f32,
    one_minus_beta_1: f32,
    beta_2: f32,
    one_minus_beta_2: f32,
    moment_factor: f32,
    epsilon: f32,
    lr: f32,
}

/// The kernel argument for `s`.
fn step_scalars(s: &AdamScalars) -> StepScalarsLaunch {
    StepScalarsLaunch::new(
        s.beta_1,
        s.one_minus_beta_1,
        s.beta_2,
        s.one_minus_beta_2,
        s.moment_factor,
        s.epsilon,
        s.lr,
    )
}

/// Sets `watch[0]` when `g` is NaN or infinite (module docs).
#[cube]
fn watch_gradient(g: f32, watch: &mut [f32]) {
    if f32::is_nan(g) || f32::is_inf(g) {
        watch[0] = 1.0;
    }
}

/// Stores one element's step at `o`: its new moments `m`, `v` and the parameter `p` moved by
/// `(m·c / (√v + ε'))·lr`, in the order of Burn's op-by-op update.
#[cube]
#[allow(clippy::too_many_arguments)]
fn store_step(
    p: f32,
    m: f32,
    v: f32,
    o: usize,
    param_out: &mut [f32],
    moment_1_out: &mut [f32],
    moment_2_out: &mut [f32],
    s: &StepScalars,
) {
    moment_1_out[o] = m;
    moment_2_out[o] = v;
    let update = (m * s.moment_factor) / (f32::sqrt(v) + s.epsilon);
    param_out[o] = p - update * s.lr;
}

/// One thread per element. With `first` (≠ 0) the moments' inputs are not read: they start at
/// zero ([`MomentInputs::Zero`]).
#[cube(launch)]
#[allow(clippy::too_many_arguments)]
fn adam_step_kernel(
    param: &[f32],
    grad: &[f32],
    moment_1: &[f32],
    moment_2: &[f32],
    param_out: &mut [f32],
    moment_1_out: &mut [f32],
    moment_2_out: &mut [f32],
    watch: &mut [f32],
    units: usize,
    first: u32,
    s: &StepScalars,
) {
    let i = ABSOLUTE_POS;
    if i < units {
        let g = grad[i];
        watch_gradient(g, watch);
        let mut m = g * s.one_minus_beta_1;
        let mut v = (g * g) * s.one_minus_beta_2;
        if first == 0 {
            // Float addition commutes: the same sums as Burn's `m·β₁ + g·(1 − β₁)`.
            m += moment_1[i] * s.beta_1;
            v += moment_2[i] * s.beta_2;
        }
        store_step(param[i], m, v, i, param_out, moment_1_out, moment_2_out, s);
    }
}

impl AdamStepOps for CubeBackend {
    fn adam_step(
        param: FloatTensor<Self>,
        grad: FloatTensor<Self>,
        moment_1: FloatTensor<Self>,
        moment_2: FloatTensor<Self>,
        watch: FloatTensor<Self>,
        inputs: MomentInputs,
        s: AdamScalars,
    ) -> (
        FloatTensor<Self>,
        FloatTensor<Self>,
        FloatTensor<Self>,
        FloatTensor<Self>,
    ) {
        let dtype = param.dtype();
        let shape = param.shape();
        let n = shape.num_elements();
        let (client, device) = (param.client.clone(), param.device.clone());
        let param = prepare(param);
        let grad = prepare(grad);
        let (first, moment_1, moment_2) = match inputs {
            MomentInputs::Zero => (1u32, grad.clone(), grad.clone()),
            MomentInputs::Given => (0u32, prepare(moment_1), prepare(moment_2)),
        };
        let watch = prepare(watch);
        let outputs = [(); 3].map(|()| client.empty(4 * n.max(1)));
        if n > 0 {
            adam_step_kernel::launch(
                &client,
                count_1d(n),
                CubeDim::new_1d(THREADS_1D),
                tensor_arg(&param),
                tensor_arg(&grad),
                tensor_arg(&moment_1),
                tensor_arg(&moment_2),
                arg(&outputs[0], n),
                arg(&outputs[1], n),
                arg(&outputs[2], n),
                tensor_arg(&watch),
                n,
                first,
                step_scalars(&s),
            );
        }
        let [p, m, v] = outputs.map(|h| cast_to(tensor_f32(&client, &device, h, &shape), dtype));
        (p, m, v, watch)
    }
}

/// Most parameters one launch of the batched step binds. Above 32 the unrolled kernel grows
/// while the launches saved are few.
pub const BATCH_SLOTS: usize = 32;

/// The batched step, one thread per output element of this launch's segments (module docs).
///
/// `params` holds a buffer per parameter, or with `flat_params` one buffer in the batch's own
/// layout (the previous batched step's output, read at the output's index); `moments_1` and
/// `moments_2` the same with `flat_moments`, and nothing with `first`, where the moments start
/// at zero.
#[cube(launch)]
#[allow(clippy::too_many_arguments)]
fn adam_batch_kernel(
    params: &Sequence<Box<[f32]>>,
    grads: &Sequence<Box<[f32]>>,
    moments_1: &Sequence<Box<[f32]>>,
    moments_2: &Sequence<Box<[f32]>>,
    first_cube: &[u32],
    param_out: &mut [f32],
    moment_1_out: &mut [f32],
    moment_2_out: &mut [f32],
    watch: &mut [f32],
    out_offset: usize,
    s: &StepScalars,
    #[comptime] first: bool,
    #[comptime] flat_params: bool,
    #[comptime] flat_moments: bool,
) {
    let cube = (ABSOLUTE_POS / SEGMENT_ALIGN) as u32;
    #[unroll]
    for slot in 0..grads.len() {
        if cube >= first_cube[slot] && cube < first_cube[slot + 1] {
            let i = ABSOLUTE_POS - first_cube[slot] as usize * SEGMENT_ALIGN;
            let grad = &grads[slot];
            if i < grad.len() {
                let o = out_offset + ABSOLUTE_POS;
                let g = grad[i];
                watch_gradient(g, watch);
                let mut m = g * s.one_minus_beta_1;
                let mut v = (g * g) * s.one_minus_beta_2;
                if !first {
                    if flat_moments {
                        m += moments_1[0][o] * s.beta_1;
                        v += moments_2[0][o] * s.beta_2;
                    } else {
                        m += moments_1[slot][i] * s.beta_1;
                        v += moments_2[slot][i] * s.beta_2;
                    }
                }
                let p = if flat_params {
                    params[0][o]
                } else {
                    params[slot][i]
                };
                store_step(p, m, v, o, param_out, moment_1_out, moment_2_out, s);
            }
        }
    }
}

/// How one kind of a batch's inputs is bound.
enum Layout {
    /// A buffer per parameter.
    PerSlot(Vec<CubeTensor>),
    /// Every parameter's values in one buffer (`whole`), laid out as this batch's outputs will
    /// be; `parts` are the parameters' views of it.
    Flat {
        whole: Box<CubeTensor>,
        parts: Vec<CubeTensor>,
    },
}

impl Layout {
    /// `list` (one tensor per parameter) as one buffer where every tensor is the view of its
    /// segment of one buffer in the layout of `starts` and `total` (the outputs of a batched step
    /// of the same parameters: every step after the first), or else per parameter.
    fn of(list: Vec<CubeTensor>, starts: &[usize], total: usize) -> Self {
        let Some(head) = list.first() else {
            return Self::PerSlot(list);
        };
        let memory = head.handle.memory.descriptor();
        let bytes = 4 * total as u64;
        let flat = list.iter().zip(starts).all(|(t, &start)| {
            t.dtype == burn::tensor::DType::F32
                && t.handle.memory.descriptor() == memory
                && t.handle.size() == bytes
                && t.handle.offset_start.unwrap_or(0) == 4 * start as u64
        });
        if !flat {
            return Self::PerSlot(list);
        }
        let mut whole = head.handle.clone();
        (whole.offset_start, whole.offset_end) = (None, None);
        Self::Flat {
            whole: Box::new(tensor_f32(&head.client, &head.device, whole, &[total])),
            parts: list,
        }
    }

    /// The same tensors bound one per parameter.
    fn per_slot(self) -> Self {
        match self {
            Self::Flat { parts, .. } => Self::PerSlot(parts),
            per_slot => per_slot,
        }
    }

    fn is_flat(&self) -> bool {
        matches!(self, Self::Flat { .. })
    }

    /// Buffers bound for `slots` parameters.
    fn bindings(&self, slots: usize) -> usize {
        match self {
            Self::PerSlot(_) => slots,
            Self::Flat { .. } => 1,
        }
    }

    /// The kernel's sequence for the parameters `range`.
    fn arg(&self, range: std::ops::Range<usize>) -> SequenceArg<Box<[f32]>> {
        match self {
            Self::PerSlot(list) => list[range].iter().map(tensor_arg).collect(),
            Self::Flat { whole, .. } => [tensor_arg(whole)].into_iter().collect(),
        }
    }
}

/// Parameters per launch of the batched step on `client`'s device: as many as its binding
/// limit allows with the inputs bound as `bound` gives, at most [`BATCH_SLOTS`], at least one.
fn slots_per_launch(
    client: &lifegom_render::cube::host::ComputeClient,
    bound: impl Fn(usize) -> usize,
) -> usize {
    let limit = client.properties().hardware.max_bindings as usize;
    (1..=BATCH_SLOTS)
        .take_while(|&k| bound(k) <= limit)
        .last()
        .unwrap_or(1)
}

impl AdamBatchOps for CubeBackend {
    fn adam_step_batch(
        batch: AdamBatch<Self>,
        watch: FloatTensor<Self>,
        inputs: MomentInputs,
        s: AdamScalars,
    ) -> (AdamStepped<Self>, FloatTensor<Self>) {
        let first = &batch.params[0];
        let (dtype, client, device) = (first.dtype(), first.client.clone(), first.device.clone());
        let lens: Vec<usize> = batch
            .params
            .iter()
            .map(|p| p.shape().num_elements())
            .collect();
        let (starts, total) = segment_starts(&lens);
        let ready = |list: Vec<FloatTensor<Self>>| -> Vec<CubeTensor> {
            list.into_iter().map(prepare).collect()
        };
        let params = Layout::of(ready(batch.params), &starts, total);
        let grads = Layout::PerSlot(ready(batch.grads));
        let (moments_1, moments_2) = match inputs {
            MomentInputs::Zero => (Layout::PerSlot(Vec::new()), Layout::PerSlot(Vec::new())),
            MomentInputs::Given => {
                let moments_1 = Layout::of(ready(batch.moments_1), &starts, total);
                let moments_2 = Layout::of(ready(batch.moments_2), &starts, total);
                // Both flat or neither: one comptime choice for the pair.
                if moments_1.is_flat() && moments_2.is_flat() {
                    (moments_1, moments_2)
                } else {
                    (moments_1.per_slot(), moments_2.per_slot())
                }
            }
        };
        let watch = prepare(watch);
        let outputs = [(); 3].map(|()| client.empty(4 * total));
        let first = inputs == MomentInputs::Zero;
        // Buffers a launch of `k` parameters binds: the inputs, the cube table, three outputs
        // and the watch flag.
        let bound = |k| {
            let moments = if first {
                0
            } else {
                moments_1.bindings(k) + moments_2.bindings(k)
            };
            params.bindings(k) + grads.bindings(k) + moments + 5
        };
        let slots = slots_per_launch(&client, bound);
        for begin in (0..lens.len()).step_by(slots) {
            let range = begin..(begin + slots).min(lens.len());
            let base = starts[begin];
            let end = starts.get(range.end).copied().unwrap_or(total);
            // Each parameter's cubes, counted from this launch's first cube.
            let cubes: Vec<u32> = range
                .clone()
                .map(|i| ((starts[i] - base) / SEGMENT_ALIGN) as u32)
                .chain([((end - base) / SEGMENT_ALIGN) as u32])
                .collect();
            let table = client.create_from_slice(&u32_bytes(&cubes));
            let moments = |m: &Layout| {
                if first {
                    SequenceArg::new()
                } else {
                    m.arg(range.clone())
                }
            };
            adam_batch_kernel::launch(
                &client,
                count_1d(end - base),
                CubeDim::new_1d(SEGMENT_ALIGN as u32),
                params.arg(range.clone()),
                grads.arg(range.clone()),
                moments(&moments_1),
                moments(&moments_2),
                arg(&table, cubes.len()),
                arg(&outputs[0], total),
                arg(&outputs[1], total),
                arg(&outputs[2], total),
                tensor_arg(&watch),
                base,
                step_scalars(&s),
                first,
                params.is_flat(),
                moments_1.is_flat(),
            );
        }
        // Each output a view of its segment: offsets at both ends, no copy. The segment starts
        // 1 KiB-aligned, as a binding's offset must be; its end needs no alignment.
        let views = |handle: &Handle| -> Vec<CubeTensor> {
            starts
                .iter()
                .zip(&lens)
                .map(|(&start, &len)| {
                    let view = handle
                        .clone()
                        .offset_start(4 * start as u64)
                        .offset_end(4 * (total - start - len) as u64);
                    cast_to(tensor_f32(&client, &device, view, &[len]), dtype)
                })
                .collect()
        };
        let [params, moments_1, moments_2] = outputs.each_ref().map(views);
        let stepped = AdamStepped {
            params,
            moments_1,
            moments_2,
        };
        (stepped, watch)
    }
}
