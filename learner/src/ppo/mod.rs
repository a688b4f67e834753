//! PPO, readable top to bottom: GAE → losses → the update over epochs and minibatches .

pub mod gae;
pub mod loss;
pub mod update;

pub use gae::{Advantages, GaeInput, gae};
pub use update::{TrainingBatch, UpdateStats, UpdateStep, update};
