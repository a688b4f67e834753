//! PPO, readable top to bottom: GAE → losses → the update over epochs and minibatches (with an
//! optional imitation and mirror-symmetry terms).

pub mod gae;
pub mod imitation;
pub mod loss;
pub mod mirror;
pub mod update;

pub use gae::{Advantages, GaeInput, gae};
pub use imitation::{ImitationSet, ImitationTerm};
pub use mirror::MirrorTerm;
pub use update::{TrainingBatch, UpdateStats, UpdateStep, update};
