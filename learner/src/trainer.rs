//! In-process training: the task controller, one actor and the learner exchanging the same
//! messages the distributed runtime carries (weights blob → actor, rollout chunk → learner,
//! cumulative rewards → task controller, new tracks → actor). For debugging and tests; the
//! `dronerace train` default runs them as processes.
//!
//! One iteration (thesis Algorithm 1): collect n_steps in every environment with policy
//! version k → report each environment's cumulative reward, apply switches → PPO update →
//! version k + 1.

use std::path::{Path, PathBuf};
use std::time::Instant;

use actor::{Actor, ActorState};
use taskctl::TaskController;

use crate::checkpoint::Checkpoint;
use crate::learner::Learner;
use crate::run::{IterationSummary, IterationTiming, Run, TrainConfig, TrainError};
use crate::validation::Validator;

/// The in-process training loop and its run directory.
pub struct Trainer {
    run: Run,
    learner: Learner,
    actor: Actor,
    tasks: TaskController,
    validator: Option<Validator>,
}

impl Trainer {
    /// Starts a new run in `dir` (which must not hold checkpoints already).
    pub fn start(config: TrainConfig, dir: &Path) -> Result<Self, TrainError> {
        let profile = config.resolved_profile()?;
        let tasks = config.task_controller(profile.envs)?;
        let actor = Actor::new(tasks.tracks(), config.env, config.seed, 0);
        let learner = config.initial_learner()?;
        let validator = Validator::new(&config.eval)?;
        let run = Run::create(config, dir)?;
        Ok(Self { run, learner, actor, tasks, validator })
    }

    /// Continues the run in `dir` from its newest checkpoint.
    pub fn resume(dir: &Path) -> Result<Self, TrainError> {
        let (run, ckpt) = Run::open(dir)?;
        let learner = Learner::restore_state(ckpt.get("weights")?, ckpt.get("optimizer")?, ckpt.get("learner")?)?;
        let origin = dir.join("checkpoints");
        let state: ActorState = serde_json::from_slice(ckpt.get("actor")?)
            .map_err(|e| TrainError::Encoding { what: format!("{}: actor", origin.display()), reason: e.to_string() })?;
        let tasks = TaskController::from_snapshot_bytes(ckpt.get("taskctl")?, &origin)?;
        let validator = Validator::new(&run.config().eval)?;
        Ok(Self { run, learner, actor: Actor::restore(state), tasks, validator })
    }

    /// The learner (weights, version, counters).
    pub fn learner(&self) -> &Learner {
        &self.learner
    }

    /// The task controller.
    pub fn tasks(&self) -> &TaskController {
        &self.tasks
    }

    /// Iterations done.
    pub fn iteration(&self) -> u64 {
        self.run.iteration()
    }

    /// Wall seconds of training so far, over every sitting.
    pub fn wall_seconds(&self) -> f64 {
        self.run.wall_seconds()
    }

    /// Highest validation S_pw so far.
    pub fn best_validation(&self) -> Option<f64> {
        self.run.best_validation()
    }

    /// True once the run's environment-step budget is spent.
    pub fn finished(&self) -> bool {
        self.learner.env_steps() >= self.run.config().total_env_steps
    }

    /// One iteration: collect, report, switch, update, log, and checkpoint when due.
    pub fn iteration_step(&mut self) -> Result<IterationSummary, TrainError> {
        let started = Instant::now();
        let n_steps = self.learner.profile().ppo.n_steps;
        self.actor.set_weights(&self.learner.weights())?;
        let chunk = self.actor.collect(n_steps)?;
        let iteration = self.run.iteration();
        for (e, reward) in chunk.cumulative_rewards().into_iter().enumerate() {
            let env = chunk.first_env + e;
            if let Some(track) = self.tasks.report(env, iteration, reward)? {
                self.actor.set_track(env, track)?;
            }
        }
        let collected = Instant::now();
        let report = self.learner.train(std::slice::from_ref(&chunk))?;
        let timing = IterationTiming {
            seconds: started.elapsed().as_secs_f64(),
            update_seconds: collected.elapsed().as_secs_f64(),
            switches: self.tasks.history().len(),
            mean_q: self.tasks.mean_q().unwrap_or(f64::NAN),
            version_lag: 0,
        };
        let validation = Validator::evaluate_if_due(self.validator.as_ref(), self.run.next_iteration(), || self.learner.weights())?;
        let (summary, best) = self.run.record(std::slice::from_ref(&chunk), report, timing, validation.as_ref())?;
        if best {
            self.run.save_best(self.snapshot())?;
        }
        if self.run.checkpoint_due() {
            self.checkpoint()?;
        }
        Ok(summary)
    }

    /// Writes a periodic checkpoint of the current state.
    pub fn checkpoint(&self) -> Result<PathBuf, TrainError> {
        self.run.save(self.snapshot())
    }

    #[allow(clippy::expect_used, reason = "actor state serialises")]
    fn snapshot(&self) -> Checkpoint {
        let mut c = self.learner.checkpoint();
        c.put("actor", serde_json::to_vec(&self.actor.state()).expect("actor state serialises"));
        c.put("taskctl", self.tasks.to_snapshot_bytes());
        c
    }

    /// Estimated seconds to the end of the run at the given rate.
    pub fn eta_seconds(&self, sps: f64) -> f64 {
        self.run.eta_seconds(self.learner.env_steps(), sps)
    }

    /// The run directory.
    pub fn dir(&self) -> &Path {
        self.run.dir()
    }
}
