//! The actor process's loop: register with the task controller → wait for weights → collect a
//! rollout → send it to the learner → report its rewards to the task controller and apply the
//! switches → again. Every peer may die and come back: the loop waits, retries and resyncs
//! instead of failing.

use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use policy::WeightsBlob;
use proto::ActorLink;
use sim::EnvConfig;
use taskctl::client::{ClientError, TaskClient};

use crate::{Actor, ActorError};

/// What an actor process runs.
#[derive(Clone, Debug)]
pub struct ActorSettings {
    /// Stable name (a restarted actor with the same name takes back its environments).
    pub name: String,
    /// Environments it runs.
    pub envs: usize,
    /// Run seed.
    pub seed: u64,
    /// Environment configuration.
    pub env: EnvConfig,
    /// Policy steps per rollout.
    pub n_steps: usize,
    /// How long to wait for a newer policy before collecting again with the current one (a
    /// lost rollout or a restarting learner must not stall the actor forever).
    pub weights_timeout: Duration,
    /// Stop after this many rollouts (for tests and benchmarks).
    pub max_rollouts: Option<u64>,
}

/// Why an actor process stops with an error.
#[derive(Debug, thiserror::Error)]
pub enum ActorProcessError {
    /// The task controller refused the registration for good.
    #[error("registration refused: {0}")]
    Registration(ClientError),
    /// The actor refused weights or a track.
    #[error(transparent)]
    Actor(#[from] ActorError),
}

/// Calls `f` until it succeeds, a permanent error comes back, or `stop` is raised.
fn retry<T>(what: &str, stop: &AtomicBool, mut f: impl FnMut() -> Result<T, ClientError>) -> Option<Result<T, ClientError>> {
    let mut delay = Duration::from_millis(100);
    loop {
        if stop.load(Ordering::SeqCst) {
            return None;
        }
        match f() {
            Ok(v) => return Some(Ok(v)),
            Err(e) if e.transient => {
                tracing::info!("actor: {what}: {e}; retrying in {delay:?}");
                std::thread::sleep(delay);
                delay = (delay * 2).min(Duration::from_secs(2));
            }
            Err(e) => return Some(Err(e)),
        }
    }
}

/// Seed of this actor's environments and noise: distinct per range and per registration, so
/// actors (and a restarted actor) do not replay each other's randomness.
fn actor_seed(seed: u64, first_env: usize, next_rollout: u64) -> u64 {
    sim::seed::mix(seed ^ sim::seed::mix(first_env as u64 ^ (next_rollout << 32)))
}

/// Runs the actor until `stop` is raised (or `max_rollouts` are sent).
pub fn run_actor(
    settings: &ActorSettings,
    link: &mut dyn ActorLink,
    tasks: &TaskClient,
    stop: &AtomicBool,
) -> Result<(), ActorProcessError> {
    let name = settings.name.as_str();
    let Some(registration) = retry("register", stop, || tasks.register(name, settings.envs)) else { return Ok(()) };
    let mut registration = registration.map_err(ActorProcessError::Registration)?;
    let seed = actor_seed(settings.seed, registration.first_env, registration.next_rollout);
    let mut actor = Actor::new(registration.tracks.clone(), settings.env, seed, registration.first_env);
    tracing::info!("actor {name}: environments {}..{}", registration.first_env, registration.first_env + settings.envs);
    let mut current: Option<(u64, u64, u32)> = None; // (epoch, version, max_policy_lag)
    let mut used: Option<(u64, u64)> = None;
    let mut rollout = registration.next_rollout;
    let mut sent = 0u64;
    let mut waiting_since = Instant::now();
    while !stop.load(Ordering::SeqCst) && settings.max_rollouts.is_none_or(|n| sent < n) {
        match link.newest_weights() {
            Ok(Some(update)) => {
                let blob = WeightsBlob::from_bytes(&update.blob).map_err(ActorError::from)?;
                actor.set_weights(&blob)?;
                current = Some((update.learner_epoch, update.version, update.max_policy_lag));
            }
            Ok(None) => {}
            Err(e) => tracing::warn!("actor {name}: weights: {e}"),
        }
        let Some((epoch, version, lag)) = current else {
            std::thread::sleep(Duration::from_millis(2));
            continue;
        };
        // Synchronous learners want one rollout per version: wait for the next one, unless it
        // is overdue (then the learner lost ours or restarted; send another).
        let fresh = used != Some((epoch, version));
        if lag == 0 && !fresh && waiting_since.elapsed() < settings.weights_timeout {
            std::thread::sleep(Duration::from_millis(1));
            continue;
        }
        let chunk = actor.collect(settings.n_steps)?;
        used = Some((epoch, version));
        waiting_since = Instant::now();
        if let Err(e) = link.send_rollout(name, epoch, &chunk) {
            tracing::warn!("actor {name}: rollout of version {version} not delivered: {e}");
        }
        sent += 1;
        let rewards = chunk.cumulative_rewards();
        let Some(result) = retry("report", stop, || tasks.report(name, rollout, &rewards)) else { break };
        match result {
            Ok(switches) => {
                for (env, track) in switches {
                    actor.set_track(env, track)?;
                }
                rollout += 1;
            }
            Err(e) => {
                // The controller may have applied the report and died before answering, or
                // restarted from a snapshot: take its view of our environments and go on.
                tracing::warn!("actor {name}: report {rollout}: {e}; resyncing with the task controller");
                let Some(r) = retry("register", stop, || tasks.register(name, settings.envs)) else { break };
                registration = r.map_err(ActorProcessError::Registration)?;
                for (i, track) in registration.tracks.iter().enumerate() {
                    actor.set_track_if_changed(registration.first_env + i, track.clone())?;
                }
                rollout = registration.next_rollout;
            }
        }
    }
    Ok(())
}
