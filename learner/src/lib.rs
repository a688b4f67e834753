//! The PPO learner: configuration and profiles, GAE, the clipped-surrogate update, the
//! `Learner` that trains on rollout chunks, its checkpoint sections, the export of a
//! checkpoint's policy, a benchmark of its gradient step. The run around it (directory, metrics, process loops) is the `runtime`
//! crate; distillation, which trains the same networks by regression, the `distill` crate.

pub mod adam;
pub mod bench;
pub mod checkpoint;
pub mod config;
pub mod export;
pub mod learner;
pub mod ppo;

pub use config::{Frozen, LearnerConfig, PpoConfig, Profile};
pub use learner::{IterationReport, Learner, LearnerError, Network};
