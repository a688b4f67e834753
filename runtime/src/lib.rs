//! The training runtime: the run configuration, resolved once (`config`), why a run stops (`error`), the run directory (`run`), metrics files
//! (`metrics`), validation during training (`validation`), the actor's and the learner's
//! process loops (`actor_process`, `learner_process`), training in one process by turns of
//! those same loops over an in-memory link (`trainer`), experiment files (`experiment`), config
//! files as overrides of a config's own defaults (`overrides`), the progress line (`progress`),
//! the three processes with their servers (`services`), the supervisor that runs them on one
//! machine (`supervisor`) and the chaos test that kills them (`chaos`). The command line and
//! the stop flag that SIGINT and SIGTERM raise are the binary's (`src/`).

pub mod actor_process;
pub mod chaos;
pub mod config;
pub mod error;
pub mod experiment;
pub mod learner_process;
pub mod metrics;
pub mod overrides;
pub mod progress;
pub mod run;
pub mod run_lock;
pub mod services;
pub mod supervisor;
pub mod trainer;
pub mod validation;

pub use config::{LearnerSettings, ResolvedRun, TrackSource, TrainConfig, TrainFlags};
pub use error::{ConfigError, TrainError};
pub use progress::IterationSummary;
pub use run::Run;
pub use trainer::Trainer;
pub use validation::{EvalSettings, Validation, Validator};

/// Keeps freed memory in the process instead of handing it back to the kernel.
///
/// burn allocates and frees activation and gradient buffers of tens of MB in every layer of
/// every gradient step; glibc serves blocks that large with mmap and returns them with munmap,
/// so every reuse page-faults fresh zeroed pages. Measured here (BENCHMARKS.md): the paper
/// profile's gradient step went from 58 to 83 GFLOP/s and the cpu profile's from 25 to 37–53 once
/// allocations stay on the heap. The cost is a resident size that stays at its peak. Call it first thing in `main`.
pub fn keep_freed_memory() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: mallopt only changes allocator parameters; the binary calls this before any thread starts.
    unsafe {
        libc::mallopt(libc::M_MMAP_MAX, 0);
        libc::mallopt(libc::M_TRIM_THRESHOLD, i32::MAX);
    }
}
