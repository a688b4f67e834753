//! The PPO learner: configuration, GAE, the clipped-surrogate update, checkpoints, metrics and
//! the training run, the learner process's loop, and training in one process by turns of the
//! actor's and the learner's loops.

pub mod bench;
pub mod checkpoint;
pub mod config;
pub mod experiment;
pub mod learner;
pub mod metrics;
pub mod ppo;
pub mod process;
pub mod run;
pub mod trainer;
pub mod validation;

pub use config::{PpoConfig, Profile};
pub use learner::{IterationReport, Learner, LearnerError};
pub use run::{IterationSummary, Run, TrackSource, TrainConfig, TrainError};
pub use trainer::Trainer;
pub use validation::{EvalSettings, Validation, Validator};
