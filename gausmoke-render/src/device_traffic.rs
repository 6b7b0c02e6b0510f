//! Device-to-host reads and kernel launches, counted process-wide.
//!
//! A read-back stalls a GPU training loop until the queue drains, so every read of a tensor's
//! values by the library goes through [`read_floats`] (or, inside the kernels, [`note_read`]
//! beside the raw read) and is counted here. Host copies made by the CPU backends' own op
//! implementations are not device reads and are not counted. Launches are counted by cubecl's
//! launch observer (every kernel, burn's own included) once [`count_launches`] has been called;
//! builds without a cube backend launch no kernels.

use std::sync::atomic::{AtomicU64, Ordering};

use burn::tensor::Tensor;

static READS: [AtomicU64; 3] = [const { AtomicU64::new(0) }; 3];
static LAUNCHES: AtomicU64 = AtomicU64::new(0);

/// Why the host read from the device.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ReadKind {
    /// Tensor values: losses, checks, images, states.
    Values = 0,
    /// Tile-list lengths, which size the renderer's list buffers: one per GPU render without a
    /// given capacity, or one for all the views of a loop whose caller sizes the buffers.
    TileListLength = 1,
    /// The projection's PCG convergence test (every few solver iterations, GPU only).
    SolverConvergence = 2,
}

/// Counts of the process so far; subtract two with [`Traffic::since`].
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Traffic {
    /// Device-to-host reads of every kind (one per read call, however many buffers it reads).
    pub reads: u64,
    /// Of which: the renderer's tile-list lengths.
    pub tile_list_reads: u64,
    /// Of which: the projection solver's convergence tests.
    pub solver_reads: u64,
    /// Kernel launches, `0` unless [`count_launches`] is on.
    pub launches: u64,
}

impl Traffic {
    /// The counts now.
    pub fn now() -> Self {
        let [values, tile_lists, solver] = READS.each_ref().map(|r| r.load(Ordering::Relaxed));
        Self {
            reads: values + tile_lists + solver,
            tile_list_reads: tile_lists,
            solver_reads: solver,
            launches: LAUNCHES.load(Ordering::Relaxed),
        }
    }

    /// What happened between `earlier` and `self`.
    pub fn since(self, earlier: Traffic) -> Traffic {
        Traffic {
            reads: self.reads - earlier.reads,
            tile_list_reads: self.tile_list_reads - earlier.tile_list_reads,
            solver_reads: self.solver_reads - earlier.solver_reads,
            launches: self.launches - earlier.launches,
        }
    }
}

/// Records one device-to-host read made outside [`read_floats`].
pub fn note_read(kind: ReadKind) {
    READS[kind as usize].fetch_add(1, Ordering::Relaxed);
}

/// Reads a float tensor's values to the host (one counted read).
pub fn read_floats<const D: usize>(tensor: Tensor<D>) -> Vec<f32> {
    read_floats_for(tensor, ReadKind::Values)
}

/// [`read_floats`], counted as a read of `kind`.
#[allow(clippy::disallowed_methods)] // the one place allowed to read
pub fn read_floats_for<const D: usize>(tensor: Tensor<D>, kind: ReadKind) -> Vec<f32> {
    note_read(kind);
    tensor
        .into_data()
        .try_into_vec_as::<f32>()
        .expect("float tensors read back as f32")
}

/// Reads a one-element float tensor (one counted read).
pub fn read_scalar<const D: usize>(tensor: Tensor<D>) -> f32 {
    read_floats(tensor).first().copied().unwrap_or(f32::NAN)
}

/// Starts counting kernel launches, process-wide and for good; returns whether launches can
/// be counted in this build (a cube backend is compiled in). Calling it again does nothing.
pub fn count_launches() -> bool {
    #[cfg(feature = "cube")]
    {
        launches::install();
        true
    }
    #[cfg(not(feature = "cube"))]
    {
        false
    }
}

#[cfg(feature = "cube")]
mod launches {
    use std::sync::atomic::Ordering;
    use std::sync::{Arc, OnceLock};

    use cubecl::logging::{LaunchObservation, LaunchObserver};

    struct Counter;

    impl LaunchObserver for Counter {
        fn launched(&self, _kernel: &'static str) {
            super::LAUNCHES.fetch_add(1, Ordering::Relaxed);
        }
    }

    /// Held for the process's life: dropping it would stop the count.
    static INSTALLED: OnceLock<LaunchObservation> = OnceLock::new();

    pub fn install() {
        INSTALLED.get_or_init(|| LaunchObservation::new(Arc::new(Counter)));
    }
}
