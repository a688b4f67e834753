//! The learner process's loop: publish version k → gather rollouts from the actors over a
//! [`LearnerLink`] → PPO update → version k + 1, with the run's metrics and checkpoints.
//!
//! Synchronous by default: the update for version k waits for a version-k rollout from every
//! member actor (one that delivered since it was last dropped). A member that has not delivered
//! `actor_timeout` after the iteration's first rollout is dropped and training goes on with the
//! others; it rejoins with its next rollout (one too old to use counts as a sign of life).
//! Rollouts arrive whole or not at all, so a killed actor's partial rollout never reaches the
//! update. With `max_policy_lag > 0` rollouts up to that many versions old are also used.

use std::collections::BTreeSet;
use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use taskctl::TaskService;
use transport::board::LearnerBoard;
use transport::{Admission, Delivery, LearnerLink, LearnerStatus, Received, WeightsUpdate};

use crate::config::LearnerSettings;
use crate::error::TrainError;
use crate::progress::IterationSummary;
use crate::run::{IterationTiming, Run};
use crate::validation::Validator;
use learner::checkpoint::Checkpoint;
use learner::learner::Learner;

/// State saved beside the learner's in every checkpoint by whoever owns it: training in one
/// process adds the actor and the curriculum (so it resumes exactly); processes keep their own.
pub type CheckpointSections<'a> = &'a dyn Fn(&mut Checkpoint);

/// Updates refused in a row before the run stops: one diverged batch is bad luck, three mean the
/// training itself diverges.
const MAX_REFUSED_UPDATES: u32 = 3;

/// Checkpoint writes failed in a row before the run stops.
const MAX_FAILED_CHECKPOINTS: u32 = 3;

/// Which actor holds each environment, as the task controller assigned them; read again when a
/// rollout does not match (a range that moved, an actor that just registered), at most once
/// per [`Owners::REFRESH`] so that mismatching rollouts cannot flood the controller.
#[derive(Default)]
struct Owners {
    by_env: Vec<Option<String>>,
    read_at: Option<Instant>,
}

impl Owners {
    const REFRESH: Duration = Duration::from_secs(1);

    fn holds_now(&self, actor: &str, first_env: usize, envs: usize) -> bool {
        first_env
            .checked_add(envs)
            .and_then(|end| self.by_env.get(first_env..end))
            .is_some_and(|held| !held.is_empty() && held.iter().all(|owner| owner.as_deref() == Some(actor)))
    }

    /// Whether `actor` holds environments `first_env..first_env + envs`.
    fn hold(&mut self, tasks: &dyn TaskService, actor: &str, first_env: usize, envs: usize) -> bool {
        if self.holds_now(actor, first_env, envs) {
            return true;
        }
        if self.read_at.is_none_or(|t| t.elapsed() >= Self::REFRESH) {
            self.read_at = Some(Instant::now());
            match tasks.tasks() {
                Ok(list) => {
                    let mut by_env = vec![None; list.len()];
                    for task in list {
                        if let Some(owner) = by_env.get_mut(task.env) {
                            *owner = task.actor;
                        }
                    }
                    self.by_env = by_env;
                }
                Err(e) => tracing::warn!("reading which actor holds which environments: {e}"),
            }
        }
        self.holds_now(actor, first_env, envs)
    }
}

/// No sections beside the learner's.
pub fn learner_only(_: &mut Checkpoint) {}

/// The learner process: run directory, PPO learner, transport and status.
pub struct LearnerProcess<L: LearnerLink> {
    run: Run,
    learner: Learner,
    link: L,
    board: Arc<LearnerBoard>,
    settings: LearnerSettings,
    epoch: u64,
    total_envs: usize,
    members: BTreeSet<String>,
    iterations_here: u64,
    /// Updates refused (and rolled back) in a row.
    refused_updates: u32,
    /// Checkpoint writes that failed in a row.
    failed_checkpoints: u32,
    validator: Option<Validator>,
    /// Who holds which environments, as last read from the task controller.
    owners: Owners,
    /// When the previous iteration published its weights: an iteration's wall time runs from
    /// there, so it covers the collection whether actors run beside the learner or before it.
    previous_publish: Instant,
}

impl<L: LearnerLink> LearnerProcess<L> {
    /// A learner for `run`, continuing from `checkpoint` when there is one, then publishing
    /// its weights.
    pub fn start(
        run: Run,
        checkpoint: Option<&Checkpoint>,
        link: L,
        board: Arc<LearnerBoard>,
        settings: LearnerSettings,
    ) -> Result<Self, TrainError> {
        let resolved = run.resolved();
        let learner = match checkpoint {
            Some(c) => Learner::resume(c, resolved.learner(), resolved.config().total_env_steps)?,
            None => resolved.initial_learner()?,
        };
        let total_envs = resolved.envs();
        // A fresh epoch per process lifetime: versions repeat after a restart, epochs do not.
        let clock = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).unwrap_or_default().as_nanos() as u64;
        let epoch = sim::seed::mix(clock ^ u64::from(std::process::id()));
        let validator = Validator::new(&run.config().eval)?;
        let mut process = Self {
            run,
            learner,
            link,
            board,
            settings,
            epoch,
            total_envs,
            members: BTreeSet::new(),
            iterations_here: 0,
            refused_updates: 0,
            failed_checkpoints: 0,
            validator,
            owners: Owners::default(),
            previous_publish: Instant::now(),
        };
        process.publish()?;
        process.set_status(0.0, 0);
        Ok(process)
    }

    fn set_status(&self, sps: f64, policy_lag: u64) {
        self.board.set_status(LearnerStatus {
            learner_epoch: self.epoch,
            iteration: self.learner.version(),
            env_steps: self.learner.env_steps(),
            sps,
            connected_actors: self.members.iter().cloned().collect(),
            policy_lag,
        });
    }

    fn admission(&self) -> Admission {
        let arch = &self.learner.config().architecture;
        Admission {
            learner_epoch: self.epoch,
            version: self.learner.version(),
            max_policy_lag: self.settings.max_policy_lag,
            observation_dim: arch.observation_dim,
            action_dim: arch.action_dim,
            images: arch.agent == policy::Agent::Vision,
            total_envs: self.total_envs,
            rollout_steps: self.learner.config().ppo.n_steps,
        }
    }

    fn publish(&mut self) -> Result<(), TrainError> {
        let update = WeightsUpdate {
            learner_epoch: self.epoch,
            version: self.learner.version(),
            max_policy_lag: self.settings.max_policy_lag,
            blob: self.learner.weights().to_bytes(),
        };
        self.link.admit(self.admission());
        self.link.publish(&update)?;
        Ok(())
    }

    /// The run.
    pub fn run(&self) -> &Run {
        &self.run
    }

    /// The PPO learner.
    pub fn learner(&self) -> &Learner {
        &self.learner
    }

    /// True once the run's environment-step budget is spent.
    pub fn finished(&self) -> bool {
        self.learner.env_steps() >= self.run.config().total_env_steps
    }

    /// Takes what the link handed over: an admitted rollout into `batch`; a refusal is counted,
    /// and one that was merely too old still shows its actor is alive: the actor is a member
    /// again, so the next iteration waits for it (a dropped actor slower than the others would
    /// otherwise never get back in).
    ///
    /// A rollout for environments its sender does not hold (by the task controller's
    /// assignment, when there is one to ask) is refused and counted: an actor cannot train the
    /// policy on data it claims for another's environments.
    fn take(&mut self, received: Received, batch: &mut Vec<Delivery>, tasks: Option<&dyn TaskService>) {
        match received {
            Received::Rollout(d) if tasks.is_some_and(|t| !self.owners.hold(t, &d.actor, d.chunk.first_env, d.chunk.envs)) => {
                self.board.count_refused();
                tracing::warn!(
                    actor = %d.actor,
                    reason = "not_its_environments",
                    "rollout refused: environments {}..{} are not actor {}'s",
                    d.chunk.first_env,
                    d.chunk.first_env + d.chunk.envs,
                    d.actor
                );
            }
            Received::Rollout(d) => {
                self.members.insert(d.actor.clone());
                batch.push(d);
            }
            Received::Refused { actor, refusal } => {
                self.board.count_refused();
                tracing::info!(%actor, reason = refusal.kind(), "rollout not used: {refusal}");
                if refusal.kind() == "too_old" && self.members.insert(actor.clone()) {
                    tracing::info!("actor {actor} rejoins");
                }
            }
        }
    }

    /// Rollouts of the current version from every live actor (see the module docs); `None`
    /// when `stop` was raised while waiting.
    fn gather(&mut self, stop: &AtomicBool, tasks: Option<&dyn TaskService>) -> Result<Option<Vec<Delivery>>, TrainError> {
        let timeout = Duration::from_secs_f64(self.settings.actor_timeout_seconds.max(0.1));
        let version = self.learner.version();
        let mut batch: Vec<Delivery> = Vec::new();
        let mut first_arrival: Option<Instant> = None;
        // Runs from the start of the wait: rollouts that are all refused (or none at all) do
        // not start the timeout above, and must not leave the wait silent forever.
        let mut watchdog = Instant::now();
        let mut refused_before = self.board.refused();
        loop {
            if stop.load(Ordering::SeqCst) {
                return Ok(None);
            }
            if let Some(received) = self.link.receive(Duration::from_millis(50))? {
                self.take(received, &mut batch, tasks);
                if !batch.is_empty() {
                    first_arrival.get_or_insert_with(Instant::now);
                }
            }
            let delivered: BTreeSet<&String> = batch.iter().map(|d| &d.actor).collect();
            let missing: Vec<String> = self.members.iter().filter(|a| !delivered.contains(a)).cloned().collect();
            let enough = self.iterations_here > 0 || delivered.len() >= self.settings.expected_actors;
            if !batch.is_empty() && missing.is_empty() && enough {
                // Rollouts already waiting (e.g. from a dropped actor coming back) join this
                // update rather than arriving one version too old at the next.
                while let Some(received) = self.link.receive(Duration::ZERO)? {
                    self.take(received, &mut batch, tasks);
                }
                return Ok(Some(batch));
            }
            if first_arrival.is_some_and(|t| t.elapsed() >= timeout) {
                for actor in &missing {
                    tracing::warn!("dropping actor {actor}: no rollout of version {version} within {timeout:?}");
                    self.members.remove(actor);
                }
                return Ok(Some(batch));
            }
            // Says so, with what was refused meanwhile, rather than wait silently; the actors
            // stay members (a slow collection is not a gone actor).
            if batch.is_empty() && watchdog.elapsed() >= timeout.max(Duration::from_secs(30)) {
                let refused = self.board.refused() - refused_before;
                tracing::warn!(
                    "no rollout of version {version} admitted for {:?} ({refused} refused meanwhile); still waiting",
                    watchdog.elapsed()
                );
                (watchdog, refused_before) = (Instant::now(), self.board.refused());
            }
        }
    }

    /// One iteration; `None` when stopped while waiting for rollouts. `tasks` (when reachable)
    /// gives the progress line its switch count and mean q; `sections` go into checkpoints.
    pub fn iteration_step(
        &mut self,
        stop: &AtomicBool,
        tasks: Option<&dyn TaskService>,
        sections: CheckpointSections,
    ) -> Result<Option<IterationSummary>, TrainError> {
        let Some(mut batch) = self.gather(stop, tasks)? else { return Ok(None) };
        // Environment order, not arrival order (nor which actor registered first): the update
        // draws its minibatches from the chunks' concatenation, and an actor's data depends on
        // its environments alone (its seed is drawn from them), so the seed decides the update.
        batch.sort_by_key(|d| d.chunk.first_env);
        let version = self.learner.version();
        let version_lag = batch.iter().map(|d| version - d.chunk.policy_version).max().unwrap_or(0);
        let chunks: Vec<rollout::RolloutChunk> = batch.into_iter().map(|d| d.chunk).collect();
        let updating = Instant::now();
        let report = self.learner.train(&chunks)?;
        let update_seconds = updating.elapsed().as_secs_f64();
        match &report.refused_update {
            Some(reason) => {
                self.refused_updates += 1;
                tracing::error!(
                    iteration = report.version,
                    in_a_row = self.refused_updates,
                    "update refused and rolled back to the last good weights: {reason}"
                );
                if self.refused_updates >= MAX_REFUSED_UPDATES {
                    return Err(TrainError::Diverged { count: self.refused_updates, last: reason.clone() });
                }
            }
            None => self.refused_updates = 0,
        }
        self.publish()?;
        let seconds = std::mem::replace(&mut self.previous_publish, Instant::now()).elapsed().as_secs_f64();
        // Two numbers, not every environment's track: a summary is a small message.
        let summary = tasks.and_then(|t| t.summary().ok());
        let (switches, mean_q) = summary.map_or((0, f64::NAN), |s| (s.switches as usize, s.mean_q.unwrap_or(f64::NAN)));
        let timing = IterationTiming { seconds, update_seconds, switches, mean_q, version_lag };
        // After publishing: the actors collect the next rollout while this runs.
        let validation = Validator::evaluate_if_due(self.validator.as_ref(), self.run.next_iteration(), || self.learner.weights())?;
        let (summary, best) = self.run.record(&chunks, report, timing, validation.as_ref())?;
        if best {
            let saved = self.run.save_best(self.learner.weights());
            self.count_checkpoint(saved)?;
        }
        if self.run.checkpoint_due() {
            let saved = self.checkpoint(sections).map(drop);
            self.count_checkpoint(saved)?;
        }
        self.iterations_here += 1;
        self.set_status(summary.sps, version_lag);
        tracing::debug!(iteration = summary.iteration, chunks = chunks.len(), "update done");
        Ok(Some(summary))
    }

    /// A failed checkpoint write is logged and training goes on (the next may succeed: a disk
    /// filled for a moment), up to [`MAX_FAILED_CHECKPOINTS`] in a row; then the run stops
    /// rather than train what no checkpoint keeps (or restart into the same full disk).
    fn count_checkpoint(&mut self, saved: Result<(), TrainError>) -> Result<(), TrainError> {
        match saved {
            Ok(()) => self.failed_checkpoints = 0,
            Err(e) => {
                self.failed_checkpoints += 1;
                tracing::error!(in_a_row = self.failed_checkpoints, "checkpoint not written: {e}");
                if self.failed_checkpoints >= MAX_FAILED_CHECKPOINTS {
                    return Err(TrainError::CheckpointsFailing { count: self.failed_checkpoints, last: e.to_string() });
                }
            }
        }
        Ok(())
    }

    /// Writes a periodic checkpoint (learner state, run bookkeeping and `sections`).
    pub fn checkpoint(&self, sections: CheckpointSections) -> Result<PathBuf, TrainError> {
        let mut checkpoint = self.learner.checkpoint();
        sections(&mut checkpoint);
        self.run.save(checkpoint)
    }

    /// Estimated seconds to the end of the run.
    pub fn eta_seconds(&self) -> f64 {
        self.run.eta_seconds(self.learner.env_steps())
    }
}
