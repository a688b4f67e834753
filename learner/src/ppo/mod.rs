//! PPO, readable top to bottom: GAE → losses → the update over epochs and minibatches (with an
//! optional mirror-symmetry term).

pub mod gae;
pub mod loss;
pub mod mirror;
pub mod update;

pub use gae::{Advantages, GaeInput, gae};
pub use mirror::MirrorTerm;
pub use update::{TrainingBatch, UpdateStats, UpdateStep, update};
