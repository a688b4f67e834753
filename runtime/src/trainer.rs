//! Training in one process: the distributed runtime's own loops — the actor's
//! [`ActorLoop`], the learner's [`LearnerProcess`] and the task controller's
//! [`TaskService`] — taking turns on one thread over an in-memory link (sample-factory's serial
//! runner). For debugging, tests and experiments; `dronerace train` runs them as processes.
//!
//! One iteration (thesis Algorithm 1): the actor collects n_steps in every environment with
//! policy version k, sends the rollout and reports each environment's cumulative reward (the
//! controller switches tracks) → the learner's PPO update → version k + 1. Checkpoints hold the
//! actor's environments and the curriculum beside the learner, so a resumed run continues bit
//! for bit.

use std::path::{Path, PathBuf};
use std::sync::atomic::AtomicBool;

use crate::actor_process::{ActorLoop, ActorSettings, Pass};
use actor::ActorState;
use taskctl::{LocalTasks, TaskController, TaskService};
use transport::board::LearnerBoard;
use transport::memory::{MemoryActorLink, MemoryLearnerLink, memory_link};

use crate::config::{LearnerSettings, ResolvedRun};
use crate::error::TrainError;
use crate::learner_process::LearnerProcess;
use crate::progress::IterationSummary;
use crate::run::Run;
use learner::checkpoint::Checkpoint;
use learner::learner::Learner;

/// The actor's name in the task controller (one actor holds every environment).
const ACTOR: &str = "in-process";

/// The actor, learner and task controller of one run, in this process.
pub struct Trainer {
    learner: LearnerProcess<MemoryLearnerLink>,
    actor: ActorLoop,
    link: MemoryActorLink,
    tasks: LocalTasks,
    /// Never raised: nothing here waits on a peer that could be gone.
    stop: AtomicBool,
}

/// The one actor's settings: every environment, and no timeout (its learner never misses a turn).
fn actor_settings(resolved: &ResolvedRun) -> ActorSettings {
    ActorSettings { weights_timeout: std::time::Duration::MAX, ..resolved.actor_settings(ACTOR, resolved.envs()) }
}

impl Trainer {
    /// Starts a new run in `dir` (which must not hold checkpoints already).
    pub fn start(resolved: ResolvedRun, dir: &Path) -> Result<Self, TrainError> {
        let tasks = LocalTasks::new(resolved.task_controller()?, None);
        let settings = actor_settings(&resolved);
        let stop = AtomicBool::new(false);
        let actor =
            ActorLoop::register(&settings, &tasks, &stop)?.ok_or_else(|| TrainError::TurnOrder("stopped while registering".into()))?;
        let run = Run::create(resolved, dir)?;
        Self::assemble(run, None, actor, tasks)
    }

    /// Continues the run in `dir` from its newest checkpoint.
    pub fn resume(dir: &Path) -> Result<Self, TrainError> {
        let (run, checkpoint) = Run::open(dir)?;
        let origin = dir.join("checkpoints");
        let state: ActorState = serde_json::from_slice(checkpoint.get("actor")?)
            .map_err(|e| TrainError::Encoding { what: format!("{}: actor", origin.display()), reason: e.to_string() })?;
        let tasks = LocalTasks::new(TaskController::from_snapshot_bytes(checkpoint.get("taskctl")?, &origin)?, None);
        let settings = actor_settings(run.resolved());
        // The controller knows the actor already: registering again tells where its reports continue.
        let next_rollout = tasks.register(ACTOR, settings.envs)?.next_rollout;
        let actor = ActorLoop::restore(&settings, state, next_rollout);
        Self::assemble(run, Some(&checkpoint), actor, tasks)
    }

    fn assemble(run: Run, checkpoint: Option<&Checkpoint>, actor: ActorLoop, tasks: LocalTasks) -> Result<Self, TrainError> {
        let (link, learner_end) = memory_link();
        let board = std::sync::Arc::new(LearnerBoard::default());
        let learner = LearnerProcess::start(run, checkpoint, learner_end, board, LearnerSettings::default())?;
        Ok(Self { learner, actor, link, tasks, stop: AtomicBool::new(false) })
    }

    /// The learner (weights, version, counters).
    pub fn learner(&self) -> &Learner {
        self.learner.learner()
    }

    /// The task controller.
    pub fn tasks(&self) -> &LocalTasks {
        &self.tasks
    }

    /// Iterations done.
    pub fn iteration(&self) -> u64 {
        self.learner.run().iteration()
    }

    /// Wall seconds of training so far, over every sitting.
    pub fn wall_seconds(&self) -> f64 {
        self.learner.run().wall_seconds()
    }

    /// Highest validation S_pw so far.
    pub fn best_validation(&self) -> Option<f64> {
        self.learner.run().best_validation()
    }

    /// True once the run's environment-step budget is spent.
    pub fn finished(&self) -> bool {
        self.learner.finished()
    }

    /// One iteration: the actor's turn (collect, send, report, switch), then the learner's
    /// (update, publish, log, validate, checkpoint when due).
    pub fn iteration_step(&mut self) -> Result<IterationSummary, TrainError> {
        // The learner published before this turn, so a rollout is always due.
        match self.actor.pass(&mut self.link, &self.tasks, &self.stop)? {
            Pass::Sent => {}
            pass => return Err(TrainError::TurnOrder(format!("the actor's turn ended with {pass:?} instead of a rollout"))),
        }
        let (actor, tasks) = (&self.actor, &self.tasks);
        let sections = |c: &mut Checkpoint| Self::add_sections(actor, tasks, c);
        self.learner
            .iteration_step(&self.stop, Some(&self.tasks), &sections)?
            .ok_or_else(|| TrainError::TurnOrder("the learner's turn found no rollout".into()))
    }

    #[allow(clippy::expect_used, reason = "actor state serialises")]
    fn add_sections(actor: &ActorLoop, tasks: &LocalTasks, checkpoint: &mut Checkpoint) {
        checkpoint.put("actor", serde_json::to_vec(&actor.state()).expect("actor state serialises"));
        checkpoint.put("taskctl", tasks.read(TaskController::to_snapshot_bytes));
    }

    /// Trains until the budget is spent, `iterations` more are done, or `stop` rises, reporting
    /// each iteration to the run's `train.log`; then checkpoints, and returns where.
    pub fn train(&mut self, iterations: Option<u64>, stop: &AtomicBool) -> Result<PathBuf, TrainError> {
        let mut log = crate::progress::ProgressLog::open(self.dir())?;
        let first = self.iteration();
        log.report(&format!("training in {} (from iteration {first}, in one process)", self.dir().display()))?;
        while !self.finished() && !stop.load(std::sync::atomic::Ordering::SeqCst) && iterations.is_none_or(|n| self.iteration() - first < n)
        {
            let s = self.iteration_step()?;
            log.report(&crate::progress::progress_line(&s, self.eta_seconds()))?;
        }
        self.checkpoint()
    }

    /// Writes a periodic checkpoint of the current state.
    pub fn checkpoint(&self) -> Result<PathBuf, TrainError> {
        self.learner.checkpoint(&|c| Self::add_sections(&self.actor, &self.tasks, c))
    }

    /// Estimated seconds to the end of the run.
    pub fn eta_seconds(&self) -> f64 {
        self.learner.eta_seconds()
    }

    /// The run directory.
    pub fn dir(&self) -> &Path {
        self.learner.run().dir()
    }
}
