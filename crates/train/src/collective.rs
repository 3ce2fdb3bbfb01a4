//! How the ranks of a data-parallel run combine their work: every rank holds the whole model,
//! takes its share of each step's batch, and the ranks sum their gradients (and loss terms)
//! before each takes the same Adam step, so N ranks at batch b follow one process at batch
//! N b. [`Single`] is the one-process case; [`Mpi`] (feature `mpi`) sums through MPI's
//! `MPI_Allreduce`, launched with `mpirun -n N gagavatar train ...`.

use crate::run_error::{RunError, RunResult};

/// Element-wise sums across the ranks of a run.
pub trait Collective: Send + Sync {
    /// This process's rank, 0-based (rank 0 writes the run folder).
    fn rank(&self) -> usize;
    /// The number of ranks.
    fn size(&self) -> usize;
    /// Replaces `buf`, on every rank, by its element-wise sum over the ranks.
    fn sum_f32(&self, buf: &mut [f32]) -> RunResult<()>;
    /// [`Collective::sum_f32`] for f64.
    fn sum_f64(&self, buf: &mut [f64]) -> RunResult<()>;

    /// Whether every rank says `ok` (each learns the verdict, so all stop together).
    fn all_ok(&self, ok: bool) -> RunResult<bool> {
        let mut v = [if ok { 1.0 } else { 0.0 }];
        self.sum_f64(&mut v)?;
        Ok(v[0] == self.size() as f64)
    }

    /// An error naming this rank.
    fn error(&self, reason: impl Into<String>) -> RunError
    where
        Self: Sized,
    {
        RunError::Ranks {
            rank: self.rank(),
            size: self.size(),
            reason: reason.into(),
        }
    }
}

/// One process: sums are the values themselves.
#[derive(Debug, Clone, Copy, Default)]
pub struct Single;

impl Collective for Single {
    fn rank(&self) -> usize {
        0
    }
    fn size(&self) -> usize {
        1
    }
    fn sum_f32(&self, _buf: &mut [f32]) -> RunResult<()> {
        Ok(())
    }
    fn sum_f64(&self, _buf: &mut [f64]) -> RunResult<()> {
        Ok(())
    }
}

/// Whether this process was started by an MPI launcher (`mpirun`, `mpiexec`, `srun`): the
/// variables OpenMPI, MPICH/Hydra and PMIx set for their ranks.
pub fn launched_by_mpi() -> bool {
    ["OMPI_COMM_WORLD_SIZE", "PMI_SIZE", "PMIX_RANK"]
        .iter()
        .any(|v| std::env::var_os(v).is_some())
}

/// This process's rank among the job's ranks on its machine, as MPI launchers (OpenMPI,
/// MPICH/Hydra, Slurm) tell it; 0 outside such a job. Each rank takes its own GPU with it.
pub fn local_rank() -> usize {
    [
        "OMPI_COMM_WORLD_LOCAL_RANK",
        "MPI_LOCALRANKID",
        "PMI_LOCAL_RANK",
        "SLURM_LOCALID",
    ]
    .iter()
    .find_map(|v| std::env::var(v).ok()?.trim().parse().ok())
    .unwrap_or(0)
}

#[cfg(feature = "mpi")]
pub use with_mpi::Mpi;

#[cfg(feature = "mpi")]
mod with_mpi {
    use super::Collective;
    use crate::run_error::{RunError, RunResult};
    use mpi::collective::SystemOperation;
    use mpi::topology::SimpleCommunicator;
    use mpi::traits::{Communicator, CommunicatorCollectives};

    /// The ranks of `MPI_COMM_WORLD`. MPI is initialised once per process and finalised when
    /// this is dropped.
    pub struct Mpi {
        world: SimpleCommunicator,
        _universe: mpi::environment::Universe,
    }

    // MPI is initialised with thread level "funneled" or better by `mpi::initialize`; the
    // run calls it from one thread at a time (the training loop), which every level allows.
    unsafe impl Send for Mpi {}
    unsafe impl Sync for Mpi {}

    impl Mpi {
        /// Initialises MPI (an error if it already was, or cannot be).
        pub fn init() -> RunResult<Self> {
            let universe = mpi::initialize().ok_or_else(|| RunError::Ranks {
                rank: 0,
                size: 0,
                reason: "MPI could not be initialised (or already was)".into(),
            })?;
            let world = universe.world();
            Ok(Self {
                world,
                _universe: universe,
            })
        }
    }

    impl Collective for Mpi {
        fn rank(&self) -> usize {
            self.world.rank() as usize
        }
        fn size(&self) -> usize {
            self.world.size() as usize
        }
        fn sum_f32(&self, buf: &mut [f32]) -> RunResult<()> {
            let send = buf.to_vec();
            self.world
                .all_reduce_into(&send[..], buf, SystemOperation::sum());
            Ok(())
        }
        fn sum_f64(&self, buf: &mut [f64]) -> RunResult<()> {
            let send = buf.to_vec();
            self.world
                .all_reduce_into(&send[..], buf, SystemOperation::sum());
            Ok(())
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn single_sums_are_the_values() {
        let c = Single;
        let mut v = [1.5f32, -2.0];
        c.sum_f32(&mut v).unwrap();
        assert_eq!(v, [1.5, -2.0]);
        assert!(c.all_ok(true).unwrap());
        assert!(!c.all_ok(false).unwrap());
        assert_eq!((c.rank(), c.size()), (0, 1));
    }
}
