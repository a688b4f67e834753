//! The PPO learner: configuration, GAE, the clipped-surrogate update, checkpoints, metrics and
//! the in-process training loop.

pub mod bench;
pub mod checkpoint;
pub mod config;
pub mod learner;
pub mod metrics;
pub mod ppo;
pub mod trainer;

pub use config::{PpoConfig, Profile};
pub use learner::{IterationReport, Learner, LearnerError};
pub use trainer::{IterationSummary, TrackSource, TrainConfig, TrainError, Trainer};
