//! The actor: runs many environments, acts with the newest policy it was given, and turns each
//! rollout into a [`RolloutChunk`] tagged with that policy's version. The actor process's loop
//! around it is `runtime::actor_process`.

pub mod bench;

use std::sync::Arc;

use policy::{ActingPolicy, BlobError, WeightsBlob};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rollout::{EpisodeRecord, RolloutChunk};
use serde::{Deserialize, Serialize};
use sim::{EnvConfig, RaceEnv, Track, VecEnv};

/// Why an actor cannot collect.
#[derive(Debug, thiserror::Error)]
pub enum ActorError {
    /// No weights have arrived yet.
    #[error("the actor has no policy yet")]
    NoPolicy,
    /// The weights blob was refused.
    #[error(transparent)]
    Blob(#[from] BlobError),
    /// The policy reads other observations than the environments write (another frame or
    /// another number of obstacle gates, e.g. a run resumed with a changed `[env]`).
    #[error("the policy reads {reads:?} observations but the environments write {writes:?}")]
    LayoutMismatch {
        /// Layout of the policy.
        reads: sim::ObservationLayout,
        /// Layout of the environments.
        writes: sim::ObservationLayout,
    },
    /// An environment index outside this actor's range.
    #[error("environment {env} is not in this actor's range {first}..{end}")]
    UnknownEnv {
        /// Global index given.
        env: usize,
        /// First global index held.
        first: usize,
        /// One past the last.
        end: usize,
    },
}

/// Everything needed to continue an actor exactly where it stopped.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct ActorState {
    first_env: usize,
    envs: Vec<RaceEnv>,
    rng: ChaCha8Rng,
}

/// Environments `first_env ..` with their policy and sampling noise.
pub struct Actor {
    first_env: usize,
    env: VecEnv,
    policy: Option<ActingPolicy>,
    rng: ChaCha8Rng,
}

impl Actor {
    /// Environments on `tracks` (global indices from `first_env`), seeded by `seed`.
    pub fn new(tracks: Vec<Arc<Track>>, config: EnvConfig, seed: u64, first_env: usize) -> Self {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        // Sampling noise gets its own stream, apart from the environments' streams.
        rng.set_stream(u64::MAX - first_env as u64);
        Self { first_env, env: VecEnv::new(tracks, config, seed), policy: None, rng }
    }

    /// Restores an actor saved with [`Actor::state`].
    pub fn restore(state: ActorState) -> Self {
        Self { first_env: state.first_env, env: VecEnv::from_envs(state.envs), policy: None, rng: state.rng }
    }

    /// The actor's state (environments mid-episode and noise stream), without the policy.
    pub fn state(&self) -> ActorState {
        ActorState { first_env: self.first_env, envs: self.env.envs().to_vec(), rng: self.rng.clone() }
    }

    /// Number of environments.
    pub fn len(&self) -> usize {
        self.env.len()
    }

    /// True when there are no environments.
    pub fn is_empty(&self) -> bool {
        self.env.is_empty()
    }

    /// Global index of the first environment.
    pub fn first_env(&self) -> usize {
        self.first_env
    }

    /// Version of the current policy.
    pub fn policy_version(&self) -> Option<u64> {
        self.policy.as_ref().map(ActingPolicy::version)
    }

    /// Adopts new weights; later rollouts are tagged with their version. A vision policy turns
    /// the environments' cameras on (its rollouts carry the images it acted on).
    pub fn set_weights(&mut self, blob: &WeightsBlob) -> Result<(), ActorError> {
        let policy = ActingPolicy::from_blob(blob)?;
        if let Some(env) = self.env.envs().first() {
            let (reads, writes) = (policy.observation_layout(), env.config().observation);
            if reads != writes {
                return Err(ActorError::LayoutMismatch { reads, writes });
            }
        }
        if policy.sees_images() {
            self.env.enable_images();
        }
        self.policy = Some(policy);
        Ok(())
    }

    /// Gives global environment `env` a new track (task switch); it restarts at once.
    pub fn set_track(&mut self, env: usize, track: Arc<Track>) -> Result<(), ActorError> {
        let end = self.first_env + self.len();
        if !(self.first_env..end).contains(&env) {
            return Err(ActorError::UnknownEnv { env, first: self.first_env, end });
        }
        self.env.set_track(env - self.first_env, track);
        Ok(())
    }

    /// Like [`Actor::set_track`], but leaves the environment alone when it flies `track` already.
    pub fn set_track_if_changed(&mut self, env: usize, track: Arc<Track>) -> Result<(), ActorError> {
        let index = env.checked_sub(self.first_env).filter(|&i| i < self.len());
        if index.is_some_and(|i| **self.env.envs()[i].track() == *track) {
            return Ok(());
        }
        self.set_track(env, track)
    }

    /// Runs `steps` policy steps in every environment and packs them into a chunk.
    pub fn collect(&mut self, steps: usize) -> Result<RolloutChunk, ActorError> {
        let policy = self.policy.as_ref().ok_or(ActorError::NoPolicy)?;
        let n = self.env.len();
        let mut chunk = RolloutChunk {
            policy_version: policy.version(),
            first_env: self.first_env,
            envs: n,
            steps,
            observations: Vec::with_capacity(steps * n * self.env.observation_dim()),
            actions: Vec::with_capacity(steps * n * sim::ACTION_DIM),
            log_probs: Vec::with_capacity(steps * n),
            values: Vec::with_capacity(steps * n),
            rewards: Vec::with_capacity(steps * n),
            terminated: Vec::with_capacity(steps * n),
            truncated: Vec::with_capacity(steps * n),
            truncation_values: Vec::with_capacity(steps * n),
            last_values: Vec::new(),
            episodes: Vec::new(),
            images: Vec::new(),
        };
        let dim = self.env.observation_dim();
        let images = policy.sees_images();
        for _ in 0..steps {
            let acting = policy.act(&self.env.observations, &self.env.images, &mut self.rng);
            chunk.observations.extend_from_slice(&self.env.observations);
            if images {
                chunk.images.extend_from_slice(&self.env.images);
            }
            self.env.step(&acting.actions);
            chunk.actions.extend(acting.actions);
            chunk.log_probs.extend(acting.log_probs);
            chunk.values.extend(acting.values);
            chunk.rewards.extend_from_slice(&self.env.rewards);
            chunk.terminated.extend_from_slice(&self.env.terminated);
            chunk.truncated.extend_from_slice(&self.env.truncated);
            // Truncated episodes are bootstrapped with the value of where they stopped.
            let truncated: Vec<usize> = (0..n).filter(|&e| self.env.truncated[e]).collect();
            let mut bootstrap = vec![0.0; n];
            if !truncated.is_empty() {
                let rows: Vec<f32> = truncated.iter().flat_map(|&e| self.env.final_observations[e * dim..(e + 1) * dim].to_vec()).collect();
                for (&e, v) in truncated.iter().zip(policy.values(&rows)) {
                    bootstrap[e] = v;
                }
            }
            chunk.truncation_values.extend(bootstrap);
            chunk.episodes.extend(self.env.finished.iter().map(|f| EpisodeRecord {
                env: self.first_env + f.env,
                episode_return: f.stats.episode_return,
                length: f.stats.length,
                laps: f.stats.laps,
                fastest_lap: f.stats.fastest_lap,
                crashed: f.stats.crash.is_some(),
            }));
        }
        chunk.last_values = policy.values(&self.env.observations);
        Ok(chunk)
    }
}
