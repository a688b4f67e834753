//! In-process training: the task controller, one actor and the learner exchanging the same
//! messages the distributed runtime carries (weights blob → actor, rollout chunk → learner,
//! cumulative rewards → task controller, new tracks → actor).
//!
//! One iteration (thesis Algorithm 1): collect n_steps in every environment with policy
//! version k → report each environment's cumulative reward, apply switches → PPO update →
//! version k + 1.

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Instant;

use actor::{Actor, ActorState};
use serde::{Deserialize, Serialize};
use sim::EnvConfig;
use taskctl::{SwitchParams, TaskController, TrackGenerator};

use crate::checkpoint::{Checkpoint, CheckpointDir, CheckpointError};
use crate::config::{PpoConfig, Profile};
use crate::learner::{IterationReport, Learner, LearnerError};
use crate::metrics::{METRICS, MetricsWriter};

/// Where the training tracks come from.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)]
pub enum TrackSource {
    /// Every environment gets a generated track; switching replaces them.
    Generated,
    /// Environments share these library tracks round robin (e.g. `["Figure8"]`).
    Library {
        /// Library track names.
        names: Vec<String>,
    },
}

/// A training run's configuration (`dronerace train --config FILE`); every field optional.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct TrainConfig {
    /// Run name (the default run directory is `runs/<name>`).
    pub name: String,
    /// Profile: `cpu` or `paper`.
    pub profile: String,
    /// Environment steps of the whole run (the learning-rate schedule's length).
    pub total_env_steps: u64,
    /// Seed of everything.
    pub seed: u64,
    /// Parallel environments (default: the profile's).
    pub envs: Option<usize>,
    /// PPO settings replacing the profile's (missing fields take SPEC §10's values).
    pub ppo: Option<PpoConfig>,
    /// Training tracks.
    pub tracks: TrackSource,
    /// Track generator.
    pub generator: TrackGenerator,
    /// Task switching.
    pub switching: SwitchParams,
    /// Environment (dynamics, randomisation, reward).
    pub env: EnvConfig,
    /// Iterations between checkpoints.
    pub checkpoint_every: u64,
    /// Periodic checkpoints kept.
    pub keep_checkpoints: usize,
}

impl Default for TrainConfig {
    fn default() -> Self {
        Self {
            name: "generalist".into(),
            profile: "cpu".into(),
            total_env_steps: 50_000_000,
            seed: 0,
            envs: None,
            ppo: None,
            tracks: TrackSource::Generated,
            generator: TrackGenerator::default(),
            switching: SwitchParams::default(),
            env: EnvConfig::default(),
            checkpoint_every: 10,
            keep_checkpoints: 3,
        }
    }
}

impl TrainConfig {
    /// The profile with this configuration's overrides applied.
    pub fn resolved_profile(&self) -> Result<Profile, TrainError> {
        let mut profile = Profile::named(&self.profile)
            .ok_or_else(|| TrainError::Config(format!("profile: unknown profile {:?} (cpu, paper)", self.profile)))?;
        if let Some(envs) = self.envs {
            profile.envs = envs;
        }
        if let Some(ppo) = self.ppo {
            profile.ppo = ppo;
        }
        if profile.envs == 0 || profile.ppo.n_steps == 0 || profile.ppo.batch_size == 0 || profile.ppo.n_epochs == 0 {
            return Err(TrainError::Config("envs, ppo.n_steps, ppo.batch_size and ppo.n_epochs must be ≥ 1".into()));
        }
        Ok(profile)
    }
}

/// Why training cannot go on.
#[derive(Debug, thiserror::Error)]
pub enum TrainError {
    /// Bad configuration.
    #[error("config: {0}")]
    Config(String),
    /// Learner refused a rollout or a state.
    #[error(transparent)]
    Learner(#[from] LearnerError),
    /// Checkpoint I/O.
    #[error(transparent)]
    Checkpoint(#[from] CheckpointError),
    /// Task controller error.
    #[error(transparent)]
    Task(#[from] taskctl::TaskError),
    /// Actor error.
    #[error(transparent)]
    Actor(#[from] actor::ActorError),
    /// Other I/O.
    #[error("{0}")]
    Io(String),
}

/// What one iteration produced, for the progress line.
#[derive(Clone, Debug)]
pub struct IterationSummary {
    /// Iteration number (1-based, equals the new policy version).
    pub iteration: u64,
    /// Learner report.
    pub report: IterationReport,
    /// Environment steps per second of this iteration (collection and update).
    pub sps: f64,
    /// Seconds spent collecting the rollout (simulation and inference).
    pub collect_seconds: f64,
    /// Seconds spent in the PPO update.
    pub update_seconds: f64,
    /// Mean return of the episodes that ended.
    pub mean_return: f64,
    /// Mean laps per ended episode.
    pub laps_per_episode: f64,
    /// Task switches so far.
    pub switches: usize,
}

/// Trainer bookkeeping saved with checkpoints.
#[derive(Clone, Debug, Serialize, Deserialize)]
struct Progress {
    iteration: u64,
    wall_seconds: f64,
    best_return: Option<f64>,
}

/// The in-process training loop and its run directory.
pub struct Trainer {
    config: TrainConfig,
    dir: PathBuf,
    learner: Learner,
    actor: Actor,
    tasks: TaskController,
    checkpoints: CheckpointDir,
    metrics: MetricsWriter,
    progress: Progress,
}

impl Trainer {
    /// Starts a new run in `dir` (which must not hold checkpoints already).
    pub fn start(config: TrainConfig, dir: &Path) -> Result<Self, TrainError> {
        let profile = config.resolved_profile()?;
        let checkpoints = CheckpointDir::new(dir.join("checkpoints"), config.keep_checkpoints)?;
        if checkpoints.latest().is_some() {
            return Err(TrainError::Config(format!(
                "{} already holds checkpoints: resume it, or choose another run directory",
                dir.display()
            )));
        }
        let generator = config.generator;
        let tasks = match &config.tracks {
            TrackSource::Generated => TaskController::new(profile.envs, generator, config.switching, config.seed)?,
            TrackSource::Library { names } => {
                let library = taskctl::library().map_err(|e| TrainError::Config(e.to_string()))?;
                let mut chosen = Vec::new();
                for name in names {
                    let track = library
                        .iter()
                        .find(|t| t.name.eq_ignore_ascii_case(name))
                        .ok_or_else(|| TrainError::Config(format!("tracks.names: no library track {name:?}")))?;
                    chosen.push(Arc::new(track.clone()));
                }
                if chosen.is_empty() {
                    return Err(TrainError::Config("tracks.names: name at least one library track".into()));
                }
                let tracks = (0..profile.envs).map(|i| chosen[i % chosen.len()].clone()).collect();
                TaskController::with_tracks(tracks, generator, config.switching, config.seed)?
            }
        };
        let actor = Actor::new(tasks.tracks(), config.env, config.seed, 0);
        let learner = Learner::new(profile, config.total_env_steps, config.seed);
        std::fs::write(dir.join("config.toml"), toml::to_string(&config).map_err(|e| TrainError::Io(e.to_string()))?)
            .map_err(|e| TrainError::Io(format!("{}: {e}", dir.display())))?;
        let metrics = MetricsWriter::open(dir).map_err(|e| TrainError::Io(format!("{}: {e}", dir.display())))?;
        let progress = Progress { iteration: 0, wall_seconds: 0.0, best_return: None };
        Ok(Self { config, dir: dir.to_path_buf(), learner, actor, tasks, checkpoints, metrics, progress })
    }

    /// Continues the run in `dir` from its newest checkpoint.
    pub fn resume(dir: &Path) -> Result<Self, TrainError> {
        let text = std::fs::read_to_string(dir.join("config.toml"))
            .map_err(|e| TrainError::Io(format!("{}: {e}", dir.join("config.toml").display())))?;
        let config: TrainConfig = toml::from_str(&text).map_err(|e| TrainError::Config(format!("{}: {e}", dir.join("config.toml").display())))?;
        let checkpoints = CheckpointDir::new(dir.join("checkpoints"), config.keep_checkpoints)?;
        let path = checkpoints
            .latest()
            .ok_or_else(|| TrainError::Config(format!("{} has no checkpoint to resume from", dir.display())))?;
        let ckpt = Checkpoint::read(&path)?;
        let learner = Learner::restore_state(ckpt.get("weights")?, ckpt.get("optimizer")?, ckpt.get("learner")?)?;
        let state: ActorState = serde_json::from_slice(ckpt.get("actor")?).map_err(|e| TrainError::Io(format!("{}: actor: {e}", path.display())))?;
        let tasks = TaskController::from_snapshot_bytes(ckpt.get("taskctl")?, &path).map_err(|e| TrainError::Io(e.to_string()))?;
        let progress: Progress = serde_json::from_slice(ckpt.get("progress")?).map_err(|e| TrainError::Io(format!("{}: progress: {e}", path.display())))?;
        let metrics = MetricsWriter::open(dir).map_err(|e| TrainError::Io(format!("{}: {e}", dir.display())))?;
        Ok(Self { config, dir: dir.to_path_buf(), learner, actor: Actor::restore(state), tasks, checkpoints, metrics, progress })
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
        self.progress.iteration
    }

    /// True once the run's environment-step budget is spent.
    pub fn finished(&self) -> bool {
        self.learner.env_steps() >= self.config.total_env_steps
    }

    /// One iteration: collect, report, switch, update, log, and checkpoint when due.
    pub fn iteration_step(&mut self) -> Result<IterationSummary, TrainError> {
        let started = Instant::now();
        let n_steps = self.learner.profile().ppo.n_steps;
        self.actor.set_weights(&self.learner.weights())?;
        let chunk = self.actor.collect(n_steps)?;
        let iteration = self.progress.iteration;
        for (e, reward) in chunk.cumulative_rewards().into_iter().enumerate() {
            let env = chunk.first_env + e;
            if let Some(track) = self.tasks.report(env, iteration, reward)? {
                self.actor.set_track(env, track)?;
            }
        }
        let collected = Instant::now();
        let report = self.learner.train(std::slice::from_ref(&chunk))?;
        let update_seconds = collected.elapsed().as_secs_f64();
        self.progress.iteration += 1;
        let seconds = started.elapsed().as_secs_f64();
        self.progress.wall_seconds += seconds;

        let episodes = &chunk.episodes;
        let mean = |f: &dyn Fn(&policy::EpisodeRecord) -> f64| {
            if episodes.is_empty() { f64::NAN } else { episodes.iter().map(f).sum::<f64>() / episodes.len() as f64 }
        };
        let fastest = episodes.iter().filter_map(|e| e.fastest_lap).fold(f64::NAN, f64::min);
        let mean_q = {
            let qs: Vec<f64> = self.tasks.slots().iter().filter_map(|s| s.q).collect();
            if qs.is_empty() { f64::NAN } else { qs.iter().sum::<f64>() / qs.len() as f64 }
        };
        let summary = IterationSummary {
            iteration: self.progress.iteration,
            sps: chunk.transitions() as f64 / seconds,
            collect_seconds: seconds - update_seconds,
            update_seconds,
            mean_return: mean(&|e| e.episode_return),
            laps_per_episode: mean(&|e| f64::from(e.laps)),
            switches: self.tasks.history().len(),
            report,
        };
        let s = &summary.report.stats;
        let values: [f64; METRICS.len()] = [
            summary.mean_return,
            mean(&|e| f64::from(e.length)),
            summary.laps_per_episode,
            mean(&|e| if e.crashed { 1.0 } else { 0.0 }),
            fastest,
            summary.sps,
            summary.report.learning_rate,
            s.policy_loss,
            s.value_loss,
            s.approx_kl,
            s.clip_fraction,
            s.explained_variance,
            s.grad_norm,
            0.0,
            summary.switches as f64,
            mean_q,
            f64::NAN,
        ];
        self.metrics
            .write(self.progress.iteration, summary.report.env_steps, self.progress.wall_seconds, &values)
            .map_err(|e| TrainError::Io(format!("{}: metrics: {e}", self.dir.display())))?;

        if summary.mean_return.is_finite() && self.progress.best_return.is_none_or(|best| summary.mean_return > best) {
            self.progress.best_return = Some(summary.mean_return);
            self.checkpoint_to(&self.checkpoints.best())?;
        }
        if self.progress.iteration % self.config.checkpoint_every.max(1) == 0 {
            self.checkpoint()?;
        }
        Ok(summary)
    }

    /// Writes a periodic checkpoint of the current state.
    pub fn checkpoint(&self) -> Result<PathBuf, TrainError> {
        Ok(self.checkpoints.save(&self.snapshot(), self.progress.iteration)?)
    }

    fn checkpoint_to(&self, path: &Path) -> Result<(), TrainError> {
        Ok(self.snapshot().write(path)?)
    }

    fn snapshot(&self) -> Checkpoint {
        let (weights, optimizer, learner) = self.learner.save_state();
        let mut c = Checkpoint::default();
        c.put("weights", weights);
        c.put("optimizer", optimizer);
        c.put("learner", learner);
        c.put("actor", serde_json::to_vec(&self.actor.state()).expect("actor state serialises"));
        c.put("taskctl", self.tasks.to_snapshot_bytes());
        c.put("progress", serde_json::to_vec(&self.progress).expect("progress serialises"));
        c
    }

    /// Estimated seconds to the end of the run at the given rate.
    pub fn eta_seconds(&self, sps: f64) -> f64 {
        self.config.total_env_steps.saturating_sub(self.learner.env_steps()) as f64 / sps.max(1e-9)
    }

    /// The run directory.
    pub fn dir(&self) -> &Path {
        &self.dir
    }
}
