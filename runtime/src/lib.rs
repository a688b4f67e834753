//! The training runtime: the run configuration and run directory (`run`), metrics files
//! (`metrics`), validation during training (`validation`), the actor's and the learner's
//! process loops (`actor_process`, `learner_process`), training in one process by turns of
//! those same loops over an in-memory link (`trainer`), experiment files (`experiment`), config
//! files as overrides of a config's own defaults (`overrides`), the progress line (`progress`),
//! and a trained policy serving actions without a
//! transport (`pilot`). The processes' commands, their servers, the supervisor and the
//! stop flag that SIGINT and SIGTERM raise are the binary's (`src/commands`, `src/signal.rs`).

pub mod actor_process;
pub mod experiment;
pub mod learner_process;
pub mod metrics;
pub mod overrides;
pub mod pilot;
pub mod progress;
pub mod run;
pub mod run_lock;
pub mod trainer;
pub mod validation;

pub use progress::IterationSummary;
pub use run::{Run, TrackSource, TrainConfig, TrainError};
pub use trainer::Trainer;
pub use validation::{EvalSettings, Validation, Validator};
