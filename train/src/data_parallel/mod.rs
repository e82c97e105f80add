//! Batches larger than one subject: gradient accumulation in one process, and data-parallel
//! replicas that average their gradients over MPI (design.md §9.7).
//!
//! A training step takes an optimizer step on the **mean** gradient of a batch of `B` samples.
//! The batch is split over the `N` ranks of a job (`N = 1` without MPI), `k = B / N` samples
//! each (`[train] accumulate = k`); a rank sums the gradients of its `k` samples (Burn's
//! [`GradientsAccumulator`](burn::optim::GradientsAccumulator)), the ranks sum their sums
//! ([`Replicas::sum_f32`], one `MPI_Allreduce` of a flat host buffer), and every rank divides
//! by `B` and takes the same Adam step, so the weights stay identical everywhere without
//! ever being sent. Because the gradient is a mean, the learning rates mean the same at every
//! batch size.
//!
//! ```text
//! batch of step s: samples  S·… (S = samples consumed before s)
//!   rank r, j-th of its k:  S + r·k + j
//! g_r   = Σ_j ∇loss(sample)                 (on the device)
//! g     = (Σ_r g_r) / (k·N)                 (host buffer, all-reduce sum over ranks)
//! θ     ← Adam(θ, g)                        (the same on every rank)
//! ```
//!
//! So `N` ranks with `accumulate = 1` see exactly the samples one process sees with
//! `accumulate = N`, in the same order, with the same dropout masks (each sample's seed is its
//! index), and take the same steps up to the order of the float sums. Parameters that got no
//! gradient on any rank stay without one (a presence flag per parameter travels in the same
//! buffer), as they would in one process.
//!
//! [`weights_checksum`] hashes every parameter's bits; the trainer compares it across ranks
//! before each checkpoint ([`Replicas::agree`]), so a checkpoint written by rank 0 is every
//! rank's model.

#[cfg(feature = "mpi")]
pub mod mpi;

use burn::module::{Module, ModuleVisitor, Param};
use burn::optim::GradientsParams;
use burn::tensor::{Device, Tensor, TensorData};
use lifegom_render::readback::{self, ReadbackError};

/// Environment variables by which MPI launchers (Open MPI's `mpirun`, MPICH's Hydra, PMIx,
/// Slurm's `srun` with PMI) tell a process its rank.
const LAUNCHER_RANK_VARIABLES: [&str; 4] =
    ["OMPI_COMM_WORLD_RANK", "PMI_RANK", "PMIX_RANK", "PMI_ID"];

/// The environment variable that says an MPI launcher started this process, if one did.
pub fn launcher_rank_variable() -> Option<&'static str> {
    LAUNCHER_RANK_VARIABLES
        .into_iter()
        .find(|v| std::env::var_os(v).is_some())
}

/// Errors of the ranks' collective operations.
#[derive(Debug, thiserror::Error)]
pub enum ReplicaError {
    /// A gradient or weight could not be read to the host.
    #[error(transparent)]
    Readback(#[from] ReadbackError),
    /// The ranks' weights differ: they no longer train one model.
    #[error(
        "the ranks' weights differ at step {step} (checksums {min:#018x} … {max:#018x}): the replicas diverged; the last checkpoint that all ranks agreed on is the one on disk"
    )]
    Diverged {
        /// The step at which the check failed.
        step: u64,
        /// Smallest checksum over the ranks.
        min: u64,
        /// Largest checksum over the ranks.
        max: u64,
    },
    /// The ranks would take different batches (each must hold the same number of samples).
    #[error("the ranks' shares of the batch differ: between {min} and {max} samples")]
    UnevenBatch {
        /// The smallest share.
        min: u64,
        /// The largest share.
        max: u64,
    },
}

/// The processes that train one model together, as the trainer sees them.
///
/// Every rank calls each method in the same order (they are collective operations); a rank
/// that stops calling them stops the others at their next call, which is why a rank that
/// fails must end the whole job (the MPI implementation aborts it).
pub trait Replicas {
    /// This process's rank, `0..size()`.
    fn rank(&self) -> usize;
    /// The number of ranks.
    fn size(&self) -> usize;
    /// Replaces `values` with their element-wise sum over all ranks (on every rank).
    fn sum_f32(&self, values: &mut [f32]);
    /// [`Replicas::sum_f32`] for `f64` (the step's statistics).
    fn sum_f64(&self, values: &mut [f64]);
    /// The smallest and largest `value` over all ranks.
    fn min_max(&self, value: u64) -> (u64, u64);
    /// Whether any rank passed `true` (a stop request seen by one rank stops them all at the
    /// same step).
    fn any(&self, flag: bool) -> bool {
        self.min_max(u64::from(flag)).1 == 1
    }
    /// Checks that every rank holds `checksum` ([`weights_checksum`]) at `step`.
    fn agree(&self, step: u64, checksum: u64) -> Result<(), ReplicaError> {
        let (min, max) = self.min_max(checksum);
        if min == max {
            Ok(())
        } else {
            Err(ReplicaError::Diverged { step, min, max })
        }
    }
}

/// One process training alone: every collective is the identity.
#[derive(Debug, Clone, Copy, Default)]
pub struct SingleProcess;

impl Replicas for SingleProcess {
    fn rank(&self) -> usize {
        0
    }
    fn size(&self) -> usize {
        1
    }
    fn sum_f32(&self, _values: &mut [f32]) {}
    fn sum_f64(&self, _values: &mut [f64]) {}
    fn min_max(&self, value: u64) -> (u64, u64) {
        (value, value)
    }
}

/// Which samples of the run's stream each rank takes (module docs): `accumulate` per rank and
/// step, after `first_sample` samples already consumed.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct BatchLayout {
    /// Samples consumed before the first step of this layout.
    pub first_sample: u64,
    /// Samples per rank and step (`[train] accumulate`).
    pub accumulate: usize,
    /// This rank.
    pub rank: usize,
    /// Ranks.
    pub ranks: usize,
}

impl BatchLayout {
    /// One process, one sample a step, starting after `first_sample`.
    pub fn alone(first_sample: u64) -> Self {
        Self {
            first_sample,
            accumulate: 1,
            rank: 0,
            ranks: 1,
        }
    }

    /// Samples per step over all ranks.
    pub fn batch(&self) -> u64 {
        (self.accumulate * self.ranks) as u64
    }

    /// The stream index of this rank's `i`-th sample (counting from the layout's first step).
    pub fn sample_index(&self, i: u64) -> u64 {
        let k = self.accumulate.max(1) as u64;
        self.first_sample + (i / k) * self.batch() + (self.rank as u64) * k + i % k
    }
}

/// Turns `grads`, the sum of this rank's gradients over `local` samples, into the mean
/// gradient of the whole batch (`local` samples on each of the ranks), on every rank (module
/// docs). `module` names the parameters and their order. `None` when the ranks' summed
/// gradient is not finite (checked where it passes through the host: with several ranks), the
/// same on every rank.
pub fn average_gradients<M: Module>(
    module: &M,
    grads: GradientsParams,
    local: usize,
    replicas: &dyn Replicas,
) -> Result<Option<GradientsParams>, ReplicaError> {
    let samples = local * replicas.size();
    if replicas.size() == 1 {
        // Where the gradients live on the host, a pass over them costs little: a finite loss
        // with a non-finite gradient (a 0/0 in some backward) is caught here as under MPI.
        // On a GPU it would cost a read-back of every gradient a step, so there only the loss
        // is checked (design.md §1.6).
        let mut check = HostGradientsFinite {
            grads: &grads,
            finite: true,
        };
        module.visit(&mut check);
        if !check.finite {
            return Ok(None);
        }
        if samples == 1 {
            return Ok(Some(grads));
        }
        let mut scale = Scale {
            grads,
            factor: 1.0 / samples as f32,
        };
        module.visit(&mut scale);
        return Ok(Some(scale.grads));
    }
    // Every rank must divide by the same batch.
    let (min, max) = replicas.min_max(local as u64);
    if min != max {
        return Err(ReplicaError::UnevenBatch { min, max });
    }
    let mut gather = Gather {
        grads,
        values: Vec::new(),
        present: Vec::new(),
        error: None,
    };
    module.visit(&mut gather);
    if let Some(e) = gather.error {
        return Err(e.into());
    }
    let n = gather.values.len();
    let mut buffer = gather.values;
    buffer.extend_from_slice(&gather.present);
    {
        let _span = tracing::debug_span!("all_reduce", floats = buffer.len()).entered();
        replicas.sum_f32(&mut buffer);
    }
    if !buffer.iter().all(|v| v.is_finite()) {
        return Ok(None);
    }
    let (values, present) = buffer.split_at(n);
    let mut scatter = Scatter {
        values,
        present,
        offset: 0,
        index: 0,
        factor: 1.0 / samples as f32,
        grads: GradientsParams::new(),
    };
    module.visit(&mut scatter);
    Ok(Some(scatter.grads))
}

/// FNV-1a over the bits of every float parameter, in the module's visiting order: equal on two
/// ranks exactly when their weights are bitwise equal (up to hash collisions).
pub fn weights_checksum<M: Module>(module: &M) -> Result<u64, ReplicaError> {
    let mut hash = Checksum {
        state: 0xcbf2_9ce4_8422_2325,
        error: None,
    };
    module.visit(&mut hash);
    match hash.error {
        Some(e) => Err(e.into()),
        None => Ok(hash.state),
    }
}

/// The non-autodiff device a parameter's gradient lives on.
fn gradient_device<const D: usize>(param: &Param<Tensor<D>>) -> Device {
    param.val().inner().device()
}

struct Scale {
    grads: GradientsParams,
    factor: f32,
}

impl ModuleVisitor for Scale {
    fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
        if let Some(g) = self.grads.remove::<D>(param.id) {
            self.grads.register(param.id, g.mul_scalar(self.factor));
        }
    }
}

/// Flattens the gradients into one host buffer (zeros where a parameter has none) and a
/// presence flag per parameter.
/// Whether every gradient that lives on the host (ndarray, Flex) is finite; gradients on a
/// CubeCL device are not read.
struct HostGradientsFinite<'a> {
    grads: &'a GradientsParams,
    finite: bool,
}

impl ModuleVisitor for HostGradientsFinite<'_> {
    fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
        if !self.finite {
            return;
        }
        if let Some(g) = self.grads.get::<D>(param.id)
            && lifegom_render::device::runs_on_host(&g.device())
        {
            // A read failure is not a non-finite value; the step itself reports it.
            if let Ok(values) = readback::read::<f32, D, _>("gradient", g) {
                self.finite = values.iter().all(|v| v.is_finite());
            }
        }
    }
}

struct Gather {
    grads: GradientsParams,
    values: Vec<f32>,
    present: Vec<f32>,
    error: Option<ReadbackError>,
}

impl ModuleVisitor for Gather {
    fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
        let n = param.val().shape().num_elements();
        match self.grads.remove::<D>(param.id) {
            Some(g) => match readback::read::<f32, D, _>("gradient", g) {
                Ok(v) => {
                    self.values.extend_from_slice(&v);
                    self.present.push(1.0);
                }
                Err(e) => {
                    self.error.get_or_insert(e);
                    self.values.resize(self.values.len() + n, 0.0);
                    self.present.push(0.0);
                }
            },
            None => {
                self.values.resize(self.values.len() + n, 0.0);
                self.present.push(0.0);
            }
        }
    }
}

/// The inverse of [`Gather`], dividing by the batch.
struct Scatter<'a> {
    values: &'a [f32],
    present: &'a [f32],
    offset: usize,
    index: usize,
    factor: f32,
    grads: GradientsParams,
}

impl ModuleVisitor for Scatter<'_> {
    fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
        let shape = param.val().shape();
        let n = shape.num_elements();
        let values = &self.values[self.offset..self.offset + n];
        self.offset += n;
        let present = self.present[self.index] > 0.0;
        self.index += 1;
        if present {
            let mean: Vec<f32> = values.iter().map(|v| v * self.factor).collect();
            let g = Tensor::<D>::from_data(TensorData::new(mean, shape), &gradient_device(param));
            self.grads.register(param.id, g);
        }
    }
}

struct Checksum {
    state: u64,
    error: Option<ReadbackError>,
}

impl ModuleVisitor for Checksum {
    fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
        match readback::read::<f32, D, _>("weight", param.val().inner()) {
            Ok(v) => {
                for x in v {
                    for byte in x.to_bits().to_le_bytes() {
                        self.state ^= u64::from(byte);
                        self.state = self.state.wrapping_mul(0x0000_0100_0000_01b3);
                    }
                }
            }
            Err(e) => {
                self.error.get_or_insert(e);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    // `Device::ndarray`: the design card's CI backend, deprecated by Burn in favour of Flex.
    #![allow(deprecated)]
    use super::*;
    use burn::module::Module;
    use burn::nn::{Linear, LinearConfig};

    /// Rank 0 of two, in one process: its sums add the other rank's buffer `other`, and its
    /// `min_max` sees the other rank's value `other_value` (its own when `None`), as
    /// `MPI_Allreduce` would.
    struct TwoRanks {
        other: Vec<f32>,
        other_value: Option<u64>,
    }

    impl Replicas for TwoRanks {
        fn rank(&self) -> usize {
            0
        }
        fn size(&self) -> usize {
            2
        }
        fn sum_f32(&self, values: &mut [f32]) {
            for (v, o) in values.iter_mut().zip(&self.other) {
                *v += o;
            }
        }
        fn sum_f64(&self, _values: &mut [f64]) {}
        fn min_max(&self, value: u64) -> (u64, u64) {
            let other = self.other_value.unwrap_or(value);
            (value.min(other), value.max(other))
        }
    }

    fn grads_of(layer: &Linear, x: Tensor<2>) -> GradientsParams {
        let loss = layer.forward(x).powf_scalar(2.0).sum();
        GradientsParams::from_grads(loss.backward(), layer)
    }

    fn host<const D: usize>(t: Tensor<D>) -> Vec<f32> {
        readback::read::<f32, D, _>("test tensor", t).expect("readback")
    }

    #[test]
    fn the_mean_gradient_is_the_same_accumulated_or_all_reduced() {
        let device = Device::ndarray().autodiff();
        device.seed(3);
        let layer: Linear = LinearConfig::new(4, 3).init(&device);
        let x0 = Tensor::<2>::from_data([[1.0, -2.0, 0.5, 3.0]], &device);
        let x1 = Tensor::<2>::from_data([[0.25, 1.0, -1.5, 2.0]], &device);

        // One process, two samples: Burn's accumulator, then the mean.
        let mut acc = burn::optim::GradientsAccumulator::<Linear>::new();
        acc.accumulate(&layer, grads_of(&layer, x0.clone()));
        acc.accumulate(&layer, grads_of(&layer, x1.clone()));
        let single = average_gradients(&layer, acc.grads(), 2, &SingleProcess)
            .expect("single")
            .expect("finite");

        // Two ranks, one sample each: rank 0 receives rank 1's flat buffer in its sum.
        let mut rank1 = Gather {
            grads: grads_of(&layer, x1),
            values: vec![],
            present: vec![],
            error: None,
        };
        layer.visit(&mut rank1);
        let replicas = TwoRanks {
            other: [rank1.values, rank1.present].concat(),
            other_value: None,
        };
        let parallel = average_gradients(&layer, grads_of(&layer, x0), 1, &replicas)
            .expect("two ranks")
            .expect("finite");

        let id = layer.weight.id;
        let (a, b) = (
            host(single.get::<2>(id).expect("weight gradient")),
            host(parallel.get::<2>(id).expect("weight gradient")),
        );
        assert_eq!(a.len(), 12);
        for (a, b) in a.iter().zip(&b) {
            assert!((a - b).abs() <= 1e-6 * a.abs().max(1.0), "{a} vs {b}");
        }
        let bias = layer.bias.as_ref().expect("bias").id;
        assert_eq!(
            host(single.get::<1>(bias).expect("bias gradient")),
            host(parallel.get::<1>(bias).expect("bias gradient"))
        );
    }

    /// One process on a host backend: a finite loss whose gradient is not finite (the `sqrt`
    /// of zero has an infinite derivative) gives no step, as a non-finite loss does.
    #[test]
    fn a_non_finite_gradient_behind_a_finite_loss_gives_no_step() {
        for device in [Device::ndarray(), Device::flex()] {
            let device = device.autodiff();
            device.seed(4);
            let layer: Linear = LinearConfig::new(2, 1).with_bias(false).init(&device);
            let x = Tensor::<2>::from_data([[0.0, 0.0]], &device);
            let loss = layer.forward(x.clone()).abs().sqrt().sum();
            assert!(host(loss.clone()).iter().all(|v| v.is_finite()));
            let grads = GradientsParams::from_grads(loss.backward(), &layer);
            assert!(
                average_gradients(&layer, grads, 1, &SingleProcess)
                    .unwrap()
                    .is_none()
            );
            let fine = grads_of(&layer, Tensor::from_data([[1.0, 2.0]], &device));
            assert!(
                average_gradients(&layer, fine, 1, &SingleProcess)
                    .unwrap()
                    .is_some()
            );
        }
    }

    #[test]
    fn ranks_take_disjoint_consecutive_samples() {
        let layout = |rank| BatchLayout {
            first_sample: 10,
            accumulate: 2,
            rank,
            ranks: 3,
        };
        let taken: Vec<Vec<u64>> = (0..3)
            .map(|r| (0..4).map(|i| layout(r).sample_index(i)).collect())
            .collect();
        assert_eq!(taken[0], [10, 11, 16, 17]);
        assert_eq!(taken[1], [12, 13, 18, 19]);
        assert_eq!(taken[2], [14, 15, 20, 21]);
        // One process with the whole batch as its accumulation sees the same stream.
        let alone = BatchLayout {
            first_sample: 10,
            accumulate: 6,
            rank: 0,
            ranks: 1,
        };
        let all: Vec<u64> = (0..12).map(|i| alone.sample_index(i)).collect();
        assert_eq!(all, (10..22).collect::<Vec<_>>());
    }

    #[test]
    fn the_checksum_sees_one_changed_weight() {
        let device = Device::ndarray();
        device.seed(5);
        let layer: Linear = LinearConfig::new(4, 3).init(&device);
        let a = weights_checksum(&layer).expect("checksum");
        assert_eq!(a, weights_checksum(&layer.clone()).expect("checksum"));
        let mut nudged = layer.clone();
        let w = nudged.weight.val();
        let bump = Tensor::<2>::zeros(w.shape(), &device)
            .slice_assign([0..1, 0..1], Tensor::<2>::from_data([[1e-6]], &device));
        nudged.weight = Param::from_tensor(w + bump);
        assert_ne!(a, weights_checksum(&nudged).expect("checksum"));
        let diverged = TwoRanks {
            other: vec![],
            other_value: Some(a ^ 1),
        }
        .agree(7, a);
        assert!(
            matches!(diverged, Err(ReplicaError::Diverged { step: 7, .. })),
            "{diverged:?}"
        );
    }
}
