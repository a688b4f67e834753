//! The rollout chunk: what an actor sends the learner after each rollout, tagged with the
//! policy version that produced it.

use serde::{Deserialize, Serialize};

/// One finished episode, for metrics.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct EpisodeRecord {
    /// Global environment index.
    pub env: usize,
    /// Sum of rewards.
    pub episode_return: f64,
    /// Steps.
    pub length: u32,
    /// Completed laps.
    pub laps: u32,
    /// Fastest lap (s).
    pub fastest_lap: Option<f64>,
    /// Ended in a crash (not by the time limit).
    pub crashed: bool,
}

/// `steps` consecutive policy steps of environments `first_env .. first_env + envs`, all
/// step-major (`[step][env]`, then the feature).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct RolloutChunk {
    /// Version of the policy that chose every action here.
    pub policy_version: u64,
    /// Global index of the first environment.
    pub first_env: usize,
    /// Environments in the chunk.
    pub envs: usize,
    /// Steps per environment.
    pub steps: usize,
    /// Raw (un-normalised) observations at decision time.
    pub observations: Vec<f32>,
    /// Sampled actions, before clipping.
    pub actions: Vec<f32>,
    /// Log-probabilities of those samples.
    pub log_probs: Vec<f32>,
    /// Value estimates at decision time.
    pub values: Vec<f32>,
    /// Rewards.
    pub rewards: Vec<f32>,
    /// The step crashed.
    pub terminated: Vec<bool>,
    /// The step hit the time limit.
    pub truncated: Vec<bool>,
    /// V(final observation) where truncated, else 0.
    pub truncation_values: Vec<f32>,
    /// V(observation after the last step), per environment.
    pub last_values: Vec<f32>,
    /// Episodes that ended in this rollout.
    pub episodes: Vec<EpisodeRecord>,
}

impl RolloutChunk {
    /// Sum of each environment's rewards in this rollout (what the task controller scores).
    pub fn cumulative_rewards(&self) -> Vec<f64> {
        let mut sums = vec![0.0; self.envs];
        for (i, r) in self.rewards.iter().enumerate() {
            sums[i % self.envs] += f64::from(*r);
        }
        sums
    }

    /// Number of transitions.
    pub fn transitions(&self) -> usize {
        self.envs * self.steps
    }
}
