//! Rollouts to the learner, weights to the actors: the one interface both transports
//! (iceoryx2 on one machine, gRPC across machines) implement, so actor and learner code is the
//! same over either.

use std::time::Duration;

use rollout::{ChunkLimits, RolloutChunk};

/// How rollouts and weights travel between actors and the learner.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Transport {
    /// iceoryx2 shared memory (actors on the learner's machine).
    Shm,
    /// gRPC streams (actors anywhere).
    Grpc,
}

impl Transport {
    /// Its `--transport` value, as the processes' command lines spell it.
    pub fn flag(self) -> &'static str {
        match self {
            Transport::Shm => "shm",
            Transport::Grpc => "grpc",
        }
    }

    /// What it runs on, for a person reading a log line.
    pub fn label(self) -> &'static str {
        match self {
            Transport::Shm => "iceoryx2",
            Transport::Grpc => "gRPC",
        }
    }
}

impl std::str::FromStr for Transport {
    type Err = String;

    /// A `--transport` value: `shm` or `grpc`.
    fn from_str(flag: &str) -> Result<Self, String> {
        [Transport::Shm, Transport::Grpc]
            .into_iter()
            .find(|t| t.flag() == flag)
            .ok_or_else(|| format!("{flag:?} is neither shm (iceoryx2, actors on this machine) nor grpc (actors anywhere)"))
    }
}

/// Weights as they travel to actors.
#[derive(Clone, Debug, PartialEq)]
pub struct WeightsUpdate {
    /// The learner process lifetime that produced them (versions restart with a learner).
    pub learner_epoch: u64,
    /// Policy version.
    pub version: u64,
    /// Versions a rollout may lag behind (0: synchronous, actors wait for every version).
    pub max_policy_lag: u32,
    /// `policy::WeightsBlob` bytes.
    pub blob: Vec<u8>,
}

/// A rollout as the learner receives it.
#[derive(Clone, Debug, PartialEq)]
pub struct Delivery {
    /// Sending actor's name.
    pub actor: String,
    /// Learner epoch of the weights the rollout was collected with.
    pub learner_epoch: u64,
    /// The rollout.
    pub chunk: RolloutChunk,
}

/// What the learner reports about itself (the gRPC `Status` answer is made from it).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct LearnerStatus {
    /// Identifies this learner lifetime (changes on every restart).
    pub learner_epoch: u64,
    /// Iterations done (= current policy version).
    pub iteration: u64,
    /// Environment steps trained on.
    pub env_steps: u64,
    /// Training env-steps/s of the last iteration.
    pub sps: f64,
    /// Actors that delivered a rollout within the actor timeout.
    pub connected_actors: Vec<String>,
    /// Largest version lag among the rollouts of the last update.
    pub policy_lag: u64,
}

/// A transport failure (the peer is gone, a resource could not be opened, …).
#[derive(Debug, thiserror::Error)]
#[error("{0}")]
pub struct LinkError(pub String);

impl LinkError {
    /// Wraps any displayable error with context.
    pub fn new(context: &str, error: impl std::fmt::Display) -> Self {
        Self(format!("{context}: {error}"))
    }
}

/// The actor's end: send rollouts, pick up the newest weights (used on the thread that opened it:
/// iceoryx2 ports are single-threaded).
pub trait ActorLink {
    /// Sends one whole rollout; it arrives whole or not at all.
    fn send_rollout(&mut self, actor: &str, learner_epoch: u64, chunk: &RolloutChunk) -> Result<(), LinkError>;
    /// The newest weights that arrived since the last call, if any (never blocks).
    fn newest_weights(&mut self) -> Result<Option<WeightsUpdate>, LinkError>;
}

/// What the learner's end of a link hands over: a rollout it admitted, or word of one it refused
/// (a refusal still shows which actors are alive).
#[derive(Clone, Debug, PartialEq)]
#[allow(clippy::large_enum_variant, reason = "one per rollout; the chunk's arrays are on the heap either way")]
pub enum Received {
    /// Admitted under the current [`Admission`]: the learner trains on it as it is.
    Rollout(Delivery),
    /// Refused, with the reason.
    Refused {
        /// Sending actor's name (as claimed).
        actor: String,
        /// Why.
        refusal: Refusal,
    },
}

/// The learner's end: take rollouts, publish weights. The link is where rollouts are admitted
/// (the one place [`Admission::check`] is applied to what the learner trains on).
pub trait LearnerLink {
    /// Rollouts handed over from now on must pass `admission` (the learner calls this whenever
    /// its version changes, before publishing the weights).
    fn admit(&mut self, admission: Admission);
    /// The next rollout or refusal, waiting at most `timeout`.
    fn receive(&mut self, timeout: Duration) -> Result<Option<Received>, LinkError>;
    /// Makes `weights` the newest for every actor, including those that connect later.
    fn publish(&mut self, weights: &WeightsUpdate) -> Result<(), LinkError>;
}

/// What a learner at `(epoch, version)` accepts from actors.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Admission {
    /// Current learner epoch.
    pub learner_epoch: u64,
    /// Version being trained.
    pub version: u64,
    /// Versions a rollout may lag.
    pub max_policy_lag: u32,
    /// Observation length of the policy.
    pub observation_dim: usize,
    /// Action length of the policy.
    pub action_dim: usize,
    /// The policy acts on camera images (a vision agent): its rollouts carry them, others must not.
    pub images: bool,
    /// Environments in the whole run (global indices must fall below it).
    pub total_envs: usize,
    /// Steps per environment in one rollout (PPO's `n_steps`): no chunk holds more.
    pub rollout_steps: usize,
}

/// Why a rollout is refused.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum Refusal {
    /// The learner has not admitted anything yet (it is starting).
    #[error("the learner is starting: no rollouts are admitted yet")]
    Starting,
    /// Shapes, numbers or environment ids are wrong.
    #[error("malformed rollout: {0}")]
    Malformed(String),
    /// Collected with weights of another learner lifetime, or too old, or from the future.
    #[error(
        "rollout of policy version {version} (learner epoch {epoch:#x}) while training version {current} (epoch {current_epoch:#x}, max_policy_lag {lag})"
    )]
    WrongVersion {
        /// Version in the rollout.
        version: u64,
        /// Epoch in the rollout.
        epoch: u64,
        /// Version being trained.
        current: u64,
        /// Current epoch.
        current_epoch: u64,
        /// Allowed lag.
        lag: u32,
    },
}

impl Refusal {
    /// A short, stable name of the reason (for logs and counts): `learner_starting`, `malformed`,
    /// `other_learner_epoch` (collected for a learner that has since restarted), `too_old` or
    /// `future_version`.
    pub fn kind(&self) -> &'static str {
        match self {
            Self::Starting => "learner_starting",
            Self::Malformed(_) => "malformed",
            Self::WrongVersion { epoch, current_epoch, .. } if epoch != current_epoch => "other_learner_epoch",
            Self::WrongVersion { version, current, .. } if version > current => "future_version",
            Self::WrongVersion { .. } => "too_old",
        }
    }
}

impl Admission {
    /// The shape a rollout's bytes may announce: what a link checks before decoding them.
    pub fn limits(&self) -> ChunkLimits {
        ChunkLimits {
            observation_dim: self.observation_dim,
            action_dim: self.action_dim,
            max_envs: self.total_envs,
            max_steps: self.rollout_steps,
            images: self.images,
        }
    }

    /// What the link hands over for `delivery` under the current admission.
    pub fn receive(admission: Option<&Admission>, delivery: Delivery) -> Received {
        match Self::check_current(admission, &delivery.actor, delivery.learner_epoch, &delivery.chunk) {
            Ok(()) => Received::Rollout(delivery),
            Err(refusal) => Received::Refused { actor: delivery.actor, refusal },
        }
    }

    /// [`Admission::check`] under the learner's current admission, refusing everything while
    /// it has none yet.
    pub fn check_current(admission: Option<&Admission>, actor: &str, learner_epoch: u64, chunk: &RolloutChunk) -> Result<(), Refusal> {
        admission.ok_or(Refusal::Starting)?.check(actor, learner_epoch, chunk)
    }

    /// Accepts a rollout the learner can train on now, or says why not.
    pub fn check(&self, actor: &str, learner_epoch: u64, chunk: &RolloutChunk) -> Result<(), Refusal> {
        check_actor_name(actor).map_err(|e| Refusal::Malformed(e.to_string()))?;
        chunk.check(self.observation_dim, self.action_dim, self.images).map_err(|e| Refusal::Malformed(e.to_string()))?;
        if chunk.steps > self.rollout_steps {
            return Err(Refusal::Malformed(format!("{} steps per environment, more than the run's {}", chunk.steps, self.rollout_steps)));
        }
        if chunk.first_env.checked_add(chunk.envs).is_none_or(|end| end > self.total_envs) {
            return Err(Refusal::Malformed(format!(
                "environments {}..{} are not all known (the run has {})",
                chunk.first_env,
                chunk.first_env.saturating_add(chunk.envs),
                self.total_envs
            )));
        }
        let v = chunk.policy_version;
        if learner_epoch != self.learner_epoch || v > self.version || self.version - v > u64::from(self.max_policy_lag) {
            return Err(Refusal::WrongVersion {
                version: v,
                epoch: learner_epoch,
                current: self.version,
                current_epoch: self.learner_epoch,
                lag: self.max_policy_lag,
            });
        }
        Ok(())
    }
}

/// An actor name that is not 1–64 characters of `[A-Za-z0-9_.-]`.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
#[error("actor name {0:?} must be 1-64 characters of A-Z a-z 0-9 _ . -")]
pub struct BadActorName(pub String);

/// Actor names: 1–64 characters of `[A-Za-z0-9_.-]` (they become log keys and shm headers).
pub fn check_actor_name(actor: &str) -> Result<(), BadActorName> {
    let ok = !actor.is_empty() && actor.len() <= 64 && actor.bytes().all(|b| b.is_ascii_alphanumeric() || b"_.-".contains(&b));
    if ok { Ok(()) } else { Err(BadActorName(actor.to_owned())) }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn chunk(version: u64, first_env: usize) -> RolloutChunk {
        RolloutChunk::zeroed(version, first_env, 2, 1, 3, 2)
    }

    #[test]
    fn admission_takes_versions_within_the_lag_of_this_epoch_only() {
        let sync = Admission {
            learner_epoch: 7,
            version: 10,
            max_policy_lag: 0,
            observation_dim: 3,
            action_dim: 2,
            images: false,
            total_envs: 4,
            rollout_steps: 1,
        };
        assert_eq!(sync.check("a", 7, &chunk(10, 2)), Ok(()));
        assert_eq!(sync.check("a", 7, &chunk(9, 2)).map_err(|r| r.kind()), Err("too_old"));
        assert_eq!(sync.check("a", 7, &chunk(11, 2)).map_err(|r| r.kind()), Err("future_version"));
        assert_eq!(sync.check("a", 8, &chunk(10, 2)).map_err(|r| r.kind()), Err("other_learner_epoch"));
        let lagged = Admission { max_policy_lag: 2, ..sync };
        assert_eq!(lagged.check("a", 7, &chunk(8, 0)), Ok(()));
        assert!(matches!(lagged.check("a", 7, &chunk(7, 0)), Err(Refusal::WrongVersion { .. })));
        assert!(matches!(sync.check("a", 7, &chunk(10, 3)), Err(Refusal::Malformed(m)) if m.contains("not all known")));
        assert_eq!(sync.check("a b", 7, &chunk(10, 0)).map_err(|r| r.kind()), Err("malformed"));
        let mut short = chunk(10, 0);
        short.rewards.pop();
        assert!(matches!(sync.check("a", 7, &short), Err(Refusal::Malformed(m)) if m.contains("rewards")));
        // A vision learner refuses a rollout without camera images at the link, before training.
        let vision = Admission { images: true, ..sync };
        assert!(matches!(vision.check("a", 7, &chunk(10, 2)), Err(Refusal::Malformed(m)) if m.contains("camera images")));
        let long = RolloutChunk::zeroed(10, 0, 2, 2, 3, 2);
        assert!(matches!(sync.check("a", 7, &long), Err(Refusal::Malformed(m)) if m.contains("more than the run's 1")));
    }
}
