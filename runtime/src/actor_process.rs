//! The actor process's loop: register with the task controller → wait for weights → collect a
//! rollout → send it to the learner → report its rewards to the task controller and apply the
//! switches → again. [`ActorLoop::pass`] is one turn of it, so training in one process can
//! interleave it with the learner's loop. Every peer may die and come back: the loop waits,
//! retries and resyncs instead of failing.

use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use policy::WeightsBlob;
use sim::EnvConfig;
use taskctl::{TaskService, TaskServiceError};
use transport::ActorLink;

use actor::{Actor, ActorError, ActorState};

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
    /// lost rollout or a restarting learner must not stall the actor forever); doubled after
    /// each such resend of the same version, since a slow update is likelier than a lost one.
    pub weights_timeout: Duration,
    /// Stop after this many rollouts (for tests and benchmarks).
    pub max_rollouts: Option<u64>,
}

/// Why an actor process stops with an error.
#[derive(Debug, thiserror::Error)]
pub enum ActorProcessError {
    /// The task controller refused the registration for good.
    #[error("registration refused: {0}")]
    Registration(TaskServiceError),
    /// The actor refused weights or a track.
    #[error(transparent)]
    Actor(#[from] ActorError),
    /// The task controller gave this actor's name another range after it fell silent beyond
    /// the actor timeout; the process restarts to take it up.
    #[error("this actor's environments moved from {from} to {to} while it was silent; restarting on the new range")]
    RangeMoved {
        /// First environment it held.
        from: usize,
        /// First environment it holds now.
        to: usize,
    },
}

/// Calls `f` until it succeeds, a permanent error comes back, or `stop` is raised.
fn retry<T>(what: &str, stop: &AtomicBool, mut f: impl FnMut() -> Result<T, TaskServiceError>) -> Option<Result<T, TaskServiceError>> {
    let mut delay = Duration::from_millis(100);
    loop {
        if stop.load(Ordering::SeqCst) {
            return None;
        }
        match f() {
            Ok(v) => return Some(Ok(v)),
            Err(e) if e.is_transient() => {
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

/// What one pass of the loop did.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Pass {
    /// A rollout was collected, sent and reported.
    Sent,
    /// No rollout is due yet (no weights, or a synchronous learner has not published the next
    /// version): call again shortly.
    Waiting,
    /// `stop` was raised during a retry.
    Stopped,
}

/// An actor process's loop state between rollouts: the environments, the policy version in
/// hand and the next report's index.
pub struct ActorLoop {
    settings: ActorSettings,
    actor: Actor,
    /// (learner epoch, version, max_policy_lag) of the weights in hand.
    current: Option<(u64, u64, u32)>,
    /// (learner epoch, version) of the last rollout collected.
    used: Option<(u64, u64)>,
    rollout: u64,
    sent: u64,
    waiting_since: Instant,
    /// Rollouts collected again with the version in hand because no newer one came.
    resends: u32,
}

impl ActorLoop {
    /// Registers with the task controller (retrying while it is unreachable) and builds the
    /// environments on the tracks it assigns; `None` when `stop` was raised first.
    pub fn register(settings: &ActorSettings, tasks: &dyn TaskService, stop: &AtomicBool) -> Result<Option<Self>, ActorProcessError> {
        let Some(registration) = retry("register", stop, || tasks.register(&settings.name, settings.envs)) else { return Ok(None) };
        let registration = registration.map_err(ActorProcessError::Registration)?;
        let seed = actor_seed(settings.seed, registration.first_env, registration.next_rollout);
        let actor = Actor::new(registration.tracks.clone(), settings.env, seed, registration.first_env);
        tracing::info!("actor {}: environments {}..{}", settings.name, registration.first_env, registration.first_env + settings.envs);
        Ok(Some(Self::with_actor(settings, actor, registration.next_rollout)))
    }

    /// Continues from a saved [`ActorState`] (training in one process resumes exactly);
    /// `next_rollout` is the index of the next report.
    pub fn restore(settings: &ActorSettings, state: ActorState, next_rollout: u64) -> Self {
        Self::with_actor(settings, Actor::restore(state), next_rollout)
    }

    fn with_actor(settings: &ActorSettings, actor: Actor, rollout: u64) -> Self {
        Self { settings: settings.clone(), actor, current: None, used: None, rollout, sent: 0, waiting_since: Instant::now(), resends: 0 }
    }

    /// The environments mid-episode and the noise stream, for a checkpoint.
    pub fn state(&self) -> ActorState {
        self.actor.state()
    }

    /// Rollouts sent so far by this loop.
    pub fn sent(&self) -> u64 {
        self.sent
    }

    /// One pass: take the newest weights; when a rollout is due, collect it, send it to the
    /// learner, report its rewards to the task controller and apply the switches.
    pub fn pass(&mut self, link: &mut dyn ActorLink, tasks: &dyn TaskService, stop: &AtomicBool) -> Result<Pass, ActorProcessError> {
        let name = self.settings.name.as_str();
        match link.newest_weights() {
            Ok(Some(update)) => {
                let blob = WeightsBlob::from_bytes(&update.blob).map_err(ActorError::from)?;
                self.actor.set_weights(&blob)?;
                self.current = Some((update.learner_epoch, update.version, update.max_policy_lag));
            }
            Ok(None) => {}
            Err(e) => tracing::warn!("actor {name}: weights: {e}"),
        }
        let Some((epoch, version, lag)) = self.current else { return Ok(Pass::Waiting) };
        // Synchronous learners want one rollout per version: wait for the next one, unless it
        // is overdue (then the learner lost ours or restarted; send another). The wait doubles
        // with each resend: a vision update with validation outlasts the timeout, and a
        // rollout collected during it would only take the learner's cores and be dropped.
        let fresh = self.used != Some((epoch, version));
        if fresh {
            self.resends = 0;
        }
        if lag == 0 && !fresh {
            let overdue_after = self.settings.weights_timeout.saturating_mul(1 << self.resends.min(6));
            if self.waiting_since.elapsed() < overdue_after {
                return Ok(Pass::Waiting);
            }
            self.resends = self.resends.saturating_add(1);
        }
        let chunk = self.actor.collect(self.settings.n_steps)?;
        self.used = Some((epoch, version));
        self.waiting_since = Instant::now();
        if let Err(e) = link.send_rollout(name, epoch, &chunk) {
            tracing::warn!("actor {name}: rollout of version {version} not delivered: {e}");
        }
        self.sent += 1;
        let rewards = chunk.cumulative_rewards();
        let Some(result) = retry("report", stop, || tasks.report(name, self.rollout, &rewards)) else { return Ok(Pass::Stopped) };
        match result {
            Ok(switches) => {
                for (env, track) in switches {
                    self.actor.set_track(env, track)?;
                }
                self.rollout += 1;
            }
            Err(e) => {
                // The controller may have applied the report and died before answering, or
                // restarted from a snapshot: take its view of our environments and go on.
                tracing::warn!("actor {name}: report {}: {e}; resyncing with the task controller", self.rollout);
                let Some(r) = retry("register", stop, || tasks.register(name, self.settings.envs)) else { return Ok(Pass::Stopped) };
                let registration = r.map_err(ActorProcessError::Registration)?;
                if registration.first_env != self.actor.first_env() {
                    // Our range went to another actor while we were silent: start afresh.
                    return Err(ActorProcessError::RangeMoved { from: self.actor.first_env(), to: registration.first_env });
                }
                for (i, track) in registration.tracks.iter().enumerate() {
                    self.actor.set_track_if_changed(registration.first_env + i, track.clone())?;
                }
                self.rollout = registration.next_rollout;
            }
        }
        Ok(Pass::Sent)
    }
}

/// Runs the actor until `stop` is raised (or `max_rollouts` are sent).
pub fn run_actor(
    settings: &ActorSettings,
    link: &mut dyn ActorLink,
    tasks: &dyn TaskService,
    stop: &AtomicBool,
) -> Result<(), ActorProcessError> {
    let Some(mut actor) = ActorLoop::register(settings, tasks, stop)? else { return Ok(()) };
    while !stop.load(Ordering::SeqCst) && settings.max_rollouts.is_none_or(|n| actor.sent() < n) {
        match actor.pass(link, tasks, stop)? {
            Pass::Sent => {}
            Pass::Waiting => std::thread::sleep(Duration::from_millis(1)),
            Pass::Stopped => break,
        }
    }
    Ok(())
}
