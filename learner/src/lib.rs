//! The PPO learner: configuration and profiles, GAE, the clipped-surrogate update, the
//! `Learner` that trains on rollout chunks, its checkpoint sections, a benchmark of its
//! gradient step, and the vision student's distillation from a state-based teacher. The run
//! around it (directory, metrics, process loops) is the `runtime` crate.

pub mod bench;
pub mod checkpoint;
pub mod config;
pub mod distill;
pub mod learner;
pub mod ppo;

pub use config::{Frozen, PpoConfig, Profile};
pub use learner::{IterationReport, Learner, LearnerError};
