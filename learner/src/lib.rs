//! The PPO learner: configuration, GAE, the clipped-surrogate update.

pub mod config;
pub mod ppo;
