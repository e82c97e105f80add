//! [`Replicas`] over MPI (the `mpi` feature): the ranks of an `mpirun` / `srun` job, each one
//! replica, their gradients summed by `MPI_Allreduce` (rsmpi over the system's MPI library).
//!
//! MPI is initialised only when the process was started by a launcher (its environment names
//! a rank), so the same binary still runs alone. Only the thread that initialised MPI calls it
//! (`MPI_THREAD_FUNNELED`): the trainer does its collectives outside rayon's pool.
//!
//! A rank that fails must not leave the others waiting in a collective: [`MpiReplicas::abort`]
//! ends the whole job (`MPI_Abort`), and the train command calls it on any error when it runs
//! with more than one rank.
//!
//! **Fault injection for the tests** (`LIFEGOM_MPI_FAULT`, read at initialisation; never set
//! in normal use): `diverge:R` makes rank `R` add 1e-3 to the first element of its summed
//! gradient buffer, so its weights drift from the others' and the next checksum comparison must
//! catch it; `fail:R` makes rank `R` exit (status 3, without finalising MPI) at its second
//! collective sum, as a rank that dies mid-run would.

use std::cell::Cell;

use mpi::collective::SystemOperation;
use mpi::environment::{Threading, Universe};
use mpi::topology::SimpleCommunicator;
use mpi::traits::{Communicator, CommunicatorCollectives};

use super::{Replicas, launcher_rank_variable};

/// A test fault (module docs).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Fault {
    Diverge(usize),
    Fail(usize),
}

impl Fault {
    fn from_env() -> Option<Self> {
        let spec = std::env::var("LIFEGOM_MPI_FAULT").ok()?;
        let (kind, rank) = spec.split_once(':')?;
        let rank = rank.parse().ok()?;
        match kind {
            "diverge" => Some(Self::Diverge(rank)),
            "fail" => Some(Self::Fail(rank)),
            _ => None,
        }
    }
}

/// The ranks of this MPI job.
pub struct MpiReplicas {
    // Finalises MPI when dropped: must outlive `world`.
    _universe: Universe,
    world: SimpleCommunicator,
    fault: Option<Fault>,
    sums: Cell<u64>,
}

impl std::fmt::Debug for MpiReplicas {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("MpiReplicas")
            .field("rank", &self.rank())
            .field("size", &self.size())
            .finish()
    }
}

/// Why MPI could not be started.
#[derive(Debug, thiserror::Error)]
pub enum MpiError {
    /// `MPI_Init_thread` failed or was already called.
    #[error("MPI could not be initialised (or was initialised twice)")]
    Init,
    /// The library cannot promise that the main thread alone may call it.
    #[error("the MPI library offers thread level {0:?}, the trainer needs at least Funneled")]
    Threading(Threading),
}

impl MpiReplicas {
    /// Initialises MPI when a launcher started this process (module docs); `Ok(None)` when it
    /// runs alone.
    pub fn from_launcher() -> Result<Option<Self>, MpiError> {
        if launcher_rank_variable().is_none() {
            return Ok(None);
        }
        let (universe, threading) =
            mpi::initialize_with_threading(Threading::Funneled).ok_or(MpiError::Init)?;
        if threading == Threading::Single {
            return Err(MpiError::Threading(threading));
        }
        let world = universe.world();
        Ok(Some(Self {
            _universe: universe,
            world,
            fault: Fault::from_env(),
            sums: Cell::new(0),
        }))
    }

    /// Ends every rank of the job with `code` (no rank is left waiting in a collective).
    pub fn abort(&self, code: i32) -> ! {
        self.world.abort(code)
    }

    fn is_faulty(&self, fault: Fault) -> bool {
        self.fault == Some(fault)
    }
}

impl Replicas for MpiReplicas {
    fn rank(&self) -> usize {
        self.world.rank() as usize
    }

    fn size(&self) -> usize {
        self.world.size() as usize
    }

    fn sum_f32(&self, values: &mut [f32]) {
        let sent = values.to_vec();
        self.world
            .all_reduce_into(&sent[..], values, SystemOperation::sum());
        let n = self.sums.get() + 1;
        self.sums.set(n);
        if self.is_faulty(Fault::Diverge(self.rank()))
            && let Some(v) = values.first_mut()
        {
            *v += 1e-3;
        }
        if n >= 2 && self.is_faulty(Fault::Fail(self.rank())) {
            eprintln!(
                "rank {}: LIFEGOM_MPI_FAULT=fail:{} — this rank exits as if it had died",
                self.rank(),
                self.rank()
            );
            std::process::exit(3);
        }
    }

    fn sum_f64(&self, values: &mut [f64]) {
        let sent = values.to_vec();
        self.world
            .all_reduce_into(&sent[..], values, SystemOperation::sum());
    }

    fn min_max(&self, value: u64) -> (u64, u64) {
        let (mut min, mut max) = (0u64, 0u64);
        self.world
            .all_reduce_into(&value, &mut min, SystemOperation::min());
        self.world
            .all_reduce_into(&value, &mut max, SystemOperation::max());
        (min, max)
    }
}
