//! A training run: its configuration, its directory (resolved config, checkpoints,
//! `metrics.csv`, TensorBoard events) and the bookkeeping every iteration adds to it, shared
//! by the in-process trainer and the learner process.

use std::path::{Path, PathBuf};
use std::sync::Arc;

use policy::{Agent, RolloutChunk, WeightsBlob};
use racetracks::TrackGenerator;
use serde::{Deserialize, Serialize};
use sim::EnvConfig;
use taskctl::{SwitchParams, TaskController};

use crate::metrics::{MetricsRow, MetricsWriter};
use crate::progress::{Eta, IterationSummary};
use crate::validation::Validation;
use learner::checkpoint::{Checkpoint, CheckpointDir, CheckpointError};
use learner::config::{PpoConfig, Profile};
use learner::learner::{IterationReport, Learner, LearnerError};

/// Where the training tracks come from.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)]
pub enum TrackSource {
    /// Every environment gets a generated track; switching replaces them.
    Generated,
    /// Environments share these tracks round robin: library tracks by name (e.g.
    /// `["Figure8"]`) and a user's track files or directories of them (`files`); switching then
    /// replaces them with generated tracks as usual. `kind = "chosen"` (or, as earlier files
    /// say, `"library"`).
    #[serde(alias = "library")]
    Chosen {
        /// Library track names.
        #[serde(default)]
        names: Vec<String>,
        /// Track files, or directories of `*.toml` track files (relative paths are read from
        /// the working directory of the process that builds the task controller).
        #[serde(default, skip_serializing_if = "Vec::is_empty")]
        files: Vec<PathBuf>,
    },
}

impl TrackSource {
    /// A task controller for `envs` environments on these tracks, generating with `generator`
    /// and switching with `switching`.
    pub fn task_controller(
        &self,
        envs: usize,
        generator: TrackGenerator,
        switching: SwitchParams,
        seed: u64,
    ) -> Result<TaskController, TrainError> {
        Ok(match self {
            TrackSource::Generated => TaskController::new(envs, generator, switching, seed)?,
            TrackSource::Chosen { names, files } => {
                let chosen: Vec<Arc<sim::Track>> = racetracks::chosen_tracks(["tracks.names", "tracks.files"], names, files)
                    .map_err(|e| TrainError::Config(e.to_string()))?
                    .into_iter()
                    .map(Arc::new)
                    .collect();
                if chosen.is_empty() {
                    return Err(TrainError::Config("tracks: name at least one library track (names) or track file (files)".into()));
                }
                let tracks = (0..envs).map(|i| chosen[i % chosen.len()].clone()).collect();
                TaskController::with_tracks(tracks, generator, switching, seed)?
            }
        })
    }
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
    /// Hidden layer widths of actor and critic (default: the profile's, e.g. `[256, 256]`).
    pub hidden: Option<Vec<usize>>,
    /// PPO settings over the profile's: a config file's `[ppo]` table sets the fields it
    /// names, the rest keep the profile's values.
    pub ppo: Option<PpoConfig>,
    /// Training tracks.
    pub tracks: TrackSource,
    /// Track generator.
    pub generator: TrackGenerator,
    /// Task switching.
    pub switching: SwitchParams,
    /// Environment (dynamics, randomisation, reward); a state-based run's default observation
    /// ends with 4 racing-line points.
    pub env: EnvConfig,
    /// Iterations between checkpoints.
    pub checkpoint_every: u64,
    /// Periodic checkpoints kept.
    pub keep_checkpoints: usize,
    /// How the learner process treats its actors.
    pub learner: LearnerSettings,
    /// TLS and bearer-token settings of every server and client of the run.
    pub network: proto::NetworkConfig,
    /// Evaluation on the validation set during training (default 100 tracks; a vision run's
    /// 20).
    pub eval: crate::validation::EvalSettings,
    /// Start from this trained policy (checkpoint or weights blob) instead of a fresh network:
    /// fine-tuning. Its architecture must match the profile's, except that its hidden layers
    /// may be narrower than `hidden` (same depth): they are widened without changing what the
    /// policy does (`policy::WeightsBlob::with_hidden`).
    pub init_from: Option<PathBuf>,
    /// Log standard deviation the policy of `init_from` starts PPO with, in every action
    /// dimension; unset keeps the policy's own. A distilled student's is whatever its
    /// distillation started with (regression does not train it).
    pub init_log_std: Option<f64>,
    /// Kind of agent: `state` (default) or `vision` (SPEC §5's camera and CNN). A config file
    /// with `agent = "vision"` starts from [`TrainConfig::vision`], so everything it does not
    /// set takes its VB column.
    pub agent: Agent,
}

impl Default for TrainConfig {
    fn default() -> Self {
        Self {
            name: "generalist".into(),
            profile: "cpu".into(),
            total_env_steps: 60_000_000,
            seed: 0,
            envs: None,
            hidden: None,
            ppo: None,
            tracks: TrackSource::Generated,
            generator: TrackGenerator::default(),
            switching: SwitchParams::default(),
            env: EnvConfig::state_agent(),
            checkpoint_every: 10,
            keep_checkpoints: 3,
            learner: Default::default(),
            network: Default::default(),
            // 100 validation tracks: 20 cannot rank checkpoints a few points apart, and
            // best.bin is the policy a run ships (docs/notebook/generalist.md).
            eval: crate::validation::EvalSettings { tracks: 100, ..Default::default() },
            init_from: None,
            init_log_std: None,
            agent: Agent::State,
        }
    }
}

impl TrainConfig {
    /// The vision agent's defaults: SPEC's VB columns for PPO (§10), randomisation (§3), reward
    /// (§5) and the switching sensitivity α = 100 (§8); the rest as the state-based defaults.
    pub fn vision() -> Self {
        let mut config = Self { name: "vision".into(), agent: Agent::Vision, ppo: Some(PpoConfig::vision_based()), ..Self::default() };
        config.env = EnvConfig::vision_agent();
        config.switching.alpha = 100.0;
        // Its validation renders and runs the CNN: 20 tracks keep it to minutes.
        config.eval = crate::validation::EvalSettings::default();
        config
    }

    /// The defaults of `agent`.
    pub fn defaults_for(agent: Agent) -> Self {
        match agent {
            Agent::State => Self::default(),
            Agent::Vision => Self::vision(),
        }
    }

    /// Parses a run config: the text's values over the defaults of the agent it names. A
    /// `[ppo]` table overrides the named profile's PPO settings field by field, so `gamma =
    /// 0.998` alone keeps the cpu profile's minibatches.
    pub fn from_toml(text: &str) -> Result<Self, TrainError> {
        let text = crate::overrides::retire(text).map_err(|e| TrainError::Config(e.to_string()))?;
        let text = text.as_ref();
        let config: Self = toml::from_str(text).map_err(|e| TrainError::Config(e.to_string()))?;
        let mut defaults = Self::defaults_for(config.agent);
        if config.ppo.is_some() && defaults.ppo.is_none() {
            defaults.ppo = Profile::named(&config.profile).map(|profile| profile.ppo);
        }
        crate::overrides::parse_over(&defaults, text).map_err(|e| TrainError::Config(e.to_string()))
    }

    /// Reads a config file; errors name the file and the field.
    pub fn read(path: &Path) -> Result<Self, TrainError> {
        let text = durable::read_text_limited(path, durable::MAX_TEXT_FILE_BYTES)
            .map_err(|source| TrainError::Io { file: path.to_path_buf(), source })?;
        Self::from_toml(&text).map_err(|e| match e {
            TrainError::Config(message) => TrainError::Config(format!("{}: {message}", path.display())),
            other => other,
        })
    }

    /// The task controller for `envs` environments this config describes.
    pub fn task_controller(&self, envs: usize) -> Result<TaskController, TrainError> {
        self.tracks.task_controller(envs, self.generator, self.switching, self.seed)
    }

    /// The learner a new run of this configuration starts with: fresh, or from `init_from`.
    pub fn initial_learner(&self) -> Result<Learner, TrainError> {
        let profile = self.resolved_profile()?;
        Ok(match &self.init_from {
            None => Learner::new(profile, self.total_env_steps, self.seed),
            Some(path) => {
                let config_error = |e: &dyn std::fmt::Display| TrainError::Config(format!("init_from {}: {e}", path.display()));
                let mut policy = learner::checkpoint::read_policy(path)?;
                if let Some(log_std) = self.init_log_std {
                    policy = policy.with_log_std(log_std as f32).map_err(|e| config_error(&e))?;
                }
                // A wider run than its start: the start's function, with room to grow.
                if policy.architecture.hidden != profile.architecture.hidden {
                    policy = policy.with_hidden(&profile.architecture.hidden, self.seed).map_err(|e| config_error(&e))?;
                }
                Learner::from_policy(profile, self.total_env_steps, self.seed, &policy).map_err(|e| config_error(&e))?
            }
        })
    }

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
        if let Some(hidden) = &self.hidden {
            if hidden.is_empty() || hidden.contains(&0) {
                return Err(TrainError::Config(format!("hidden: {hidden:?} needs at least one layer, every width ≥ 1")));
            }
            profile.architecture.hidden = hidden.clone();
        }
        let timeout = self.learner.actor_timeout_seconds;
        if !(timeout.is_finite() && timeout > 0.0) {
            return Err(TrainError::Config(format!("learner.actor_timeout_seconds: {timeout} must be a positive number of seconds")));
        }
        let memory = self.learner.rollout_memory_mib;
        if memory == 0 || memory > 1 << 20 {
            return Err(TrainError::Config(format!("learner.rollout_memory_mib: {memory} must be 1 to 1048576 (1 TiB)")));
        }
        // The network reads the observations the environments write.
        let spacing = self.env.observation.line_spacing;
        if self.env.observation.line_points > 0 && !(spacing.is_finite() && spacing >= 0.0) {
            return Err(TrainError::Config(format!("env.observation.line_spacing: {spacing} m must be a distance ≥ 0")));
        }
        profile.architecture.set_observation_layout(self.env.observation);
        profile.architecture.agent = self.agent;
        let mirror = profile.ppo.mirror_coef;
        if mirror != 0.0 {
            if !(mirror.is_finite() && mirror > 0.0) {
                return Err(TrainError::Config(format!("ppo.mirror_coef: {mirror} must be a weight ≥ 0")));
            }
            if self.agent != Agent::State || self.env.observation.mirror().is_none() {
                return Err(TrainError::Config(
                    "ppo.mirror_coef: the mirror term (on in the cpu profile) needs the state-based agent and an observation frame with a mirror (world or heading, not body); set ppo.mirror_coef = 0 to train without it".into(),
                ));
            }
        }
        if !profile.ppo.frozen.is_nothing() && self.agent != Agent::Vision {
            return Err(TrainError::Config("ppo.frozen: only the vision agent has image layers to freeze (agent = \"vision\")".into()));
        }
        if let Some(log_std) = self.init_log_std
            && (self.init_from.is_none() || !log_std.is_finite())
        {
            return Err(TrainError::Config(format!("init_log_std: {log_std} needs init_from and a finite value")));
        }
        if profile.envs == 0 {
            return Err(TrainError::Config("envs must be ≥ 1".into()));
        }
        if self.eval.average == 0 {
            return Err(TrainError::Config("eval.average: 0 must be at least 1 (the last validated policy alone)".into()));
        }
        profile.ppo.check().map_err(|e| TrainError::Config(e.to_string()))?;
        self.switching.check().map_err(|e| TrainError::Config(e.to_string()))?;
        // A gRPC learner must be able to hold at least one rollout of every environment, as
        // sent and as decoded.
        let arch = &profile.architecture;
        let limits = policy::ChunkLimits {
            observation_dim: arch.observation_dim,
            action_dim: arch.action_dim,
            max_envs: profile.envs,
            max_steps: profile.ppo.n_steps,
            images: self.agent == Agent::Vision,
        };
        let whole_run = 2 * limits.decoded_bytes(profile.envs * profile.ppo.n_steps);
        if memory.saturating_mul(1 << 20) < whole_run {
            return Err(TrainError::Config(format!(
                "learner.rollout_memory_mib: {memory} MiB cannot hold one rollout of all {} environments ({} MiB as sent and decoded)",
                profile.envs,
                whole_run.div_ceil(1 << 20)
            )));
        }
        Ok(profile)
    }
}

/// How the learner process treats its actors (`[learner]` in the run config).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct LearnerSettings {
    /// Versions a rollout may lag behind the one being trained (0: synchronous).
    pub max_policy_lag: u32,
    /// Seconds an iteration waits, after its first rollout, for the other actors' rollouts;
    /// an actor that misses it is dropped (and rejoins with its next rollout).
    pub actor_timeout_seconds: f64,
    /// Actors the first iteration of a learner waits for (up to the timeout), so it does not
    /// train on whichever actor happened to be first.
    pub expected_actors: usize,
    /// MiB of rollouts a gRPC learner holds between arrival and training (parts being
    /// reassembled, chunks being decoded, chunks queued), across every stream; beyond it an
    /// actor's push is refused and sent again later.
    pub rollout_memory_mib: usize,
}

impl Default for LearnerSettings {
    fn default() -> Self {
        Self { max_policy_lag: 0, actor_timeout_seconds: 30.0, expected_actors: 1, rollout_memory_mib: 512 }
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
    /// A task-controller call failed.
    #[error(transparent)]
    TaskService(#[from] taskctl::TaskServiceError),
    /// Actor error.
    #[error(transparent)]
    Actor(#[from] actor::ActorError),
    /// The actor's loop failed (training in one process).
    #[error(transparent)]
    ActorLoop(#[from] crate::actor_process::ActorProcessError),
    /// Training in one process lost its turn order (a bug, reported rather than hidden).
    #[error("in-process training: {0}")]
    TurnOrder(String),
    /// The validation set could not be built.
    #[error("validation set: {0}")]
    ValidationSet(#[from] crate::validation::ValidationSetError),
    /// The test set could not be built.
    #[error("test set: {0}")]
    TestSet(#[from] racetracks::TrackSetError),
    /// A weights blob could not be used.
    #[error(transparent)]
    Blob(#[from] policy::BlobError),
    /// Updates kept diverging: each was refused and rolled back, and the next one diverged too.
    #[error(
        "{count} updates in a row were refused (non-finite or exploding) and rolled back; the last: {last}. The run stops at its last good weights: lower the learning rate or check the rollouts"
    )]
    Diverged {
        /// Refused updates in a row.
        count: u32,
        /// Why the last was refused.
        last: String,
    },
    /// Checkpoints (or the task controller's snapshots) kept failing to be written (a full or
    /// failing disk): going on would train what nothing keeps.
    #[error("{count} writes of the run's state in a row failed; the last: {last}. Free space in the run directory, then resume")]
    CheckpointsFailing {
        /// Failed writes in a row.
        count: u32,
        /// The last error.
        last: String,
    },
    /// A file or directory of the run could not be read or written.
    #[error("{}: {source}", file.display())]
    Io {
        /// The file or directory.
        file: PathBuf,
        /// What the system said.
        #[source]
        source: std::io::Error,
    },
    /// A section of a checkpoint or a config could not be encoded or decoded.
    #[error("{what}: {reason}")]
    Encoding {
        /// Which file and section.
        what: String,
        /// Why.
        reason: String,
    },
    /// The rollout transport failed.
    #[error(transparent)]
    Link(#[from] proto::LinkError),
    /// The task-controller snapshot inside a checkpoint is unusable.
    #[error(transparent)]
    Snapshot(#[from] taskctl::SnapshotError),
}

impl TrainError {
    /// A failure that restarting the process from its checkpoint would only repeat: the
    /// supervisor stops the run instead (see [`crate::supervisor::EXIT_FATAL`]).
    pub fn is_fatal(&self) -> bool {
        match self {
            Self::Diverged { .. } | Self::CheckpointsFailing { .. } => true,
            // A full disk stays full across a restart (which would lose the iterations since
            // the last checkpoint each time).
            Self::Io { source, .. } => matches!(source.kind(), std::io::ErrorKind::StorageFull | std::io::ErrorKind::QuotaExceeded),
            _ => false,
        }
    }
}

/// Run bookkeeping saved with checkpoints.
#[derive(Clone, Debug, Serialize, Deserialize)]
struct Progress {
    iteration: u64,
    wall_seconds: f64,
    best_return: Option<f64>,
    /// Highest validation S_pw so far (the thesis' "max S_pw").
    #[serde(default)]
    best_validation: Option<f64>,
}

/// Timing and curriculum figures of one iteration, measured by the loop that ran it.
#[derive(Clone, Copy, Debug)]
pub struct IterationTiming {
    /// Wall seconds from the previous iteration's publication of weights to this one's:
    /// collection and update, and the validation that followed the previous iteration.
    pub seconds: f64,
    /// Seconds of the PPO update.
    pub update_seconds: f64,
    /// Task switches so far.
    pub switches: usize,
    /// Mean flatness score q over environments (NaN when unknown).
    pub mean_q: f64,
    /// Largest policy-version lag among the chunks used.
    pub version_lag: u64,
}

/// A run directory and its bookkeeping.
pub struct Run {
    config: TrainConfig,
    dir: PathBuf,
    checkpoints: CheckpointDir,
    metrics: MetricsWriter,
    progress: Progress,
    /// Seconds of the validation recorded with the last iteration: it runs in the next
    /// iteration's interval, which must not count it as training time.
    pending_validation_seconds: f64,
    eta: Eta,
}

impl Run {
    /// Starts a new run in `dir` (which must not hold checkpoints already) and writes the
    /// resolved config into it.
    pub fn create(config: TrainConfig, dir: &Path) -> Result<Self, TrainError> {
        config.resolved_profile()?;
        std::fs::create_dir_all(dir).map_err(|source| TrainError::Io { file: dir.to_path_buf(), source })?;
        let checkpoints = CheckpointDir::new(dir.join("checkpoints"), config.keep_checkpoints)?;
        if checkpoints.latest().is_some() {
            return Err(TrainError::Config(format!(
                "{} already holds checkpoints: resume it, or choose another run directory",
                dir.display()
            )));
        }
        let text = toml::to_string(&config).map_err(|e| TrainError::Encoding { what: "config".into(), reason: e.to_string() })?;
        durable::write_atomic(&dir.join("config.toml"), text.as_bytes())
            .map_err(|source| TrainError::Io { file: dir.join("config.toml"), source })?;
        let metrics = MetricsWriter::open(dir).map_err(|source| TrainError::Io { file: dir.to_path_buf(), source })?;
        let progress = Progress { iteration: 0, wall_seconds: 0.0, best_return: None, best_validation: None };
        Ok(Self { config, dir: dir.to_path_buf(), checkpoints, metrics, progress, pending_validation_seconds: 0.0, eta: Eta::default() })
    }

    /// Opens the run in `dir` with its newest readable checkpoint: one that is cut off or
    /// corrupt (a disk fault, a copy gone wrong) is skipped with a warning naming it, and the
    /// one before it is used. Removes the temporary files of checkpoint writes cut off by a
    /// kill (the caller is the run's one writer).
    pub fn open(dir: &Path) -> Result<(Self, Checkpoint), TrainError> {
        let config = TrainConfig::read(&dir.join("config.toml"))?;
        let checkpoints = CheckpointDir::new(dir.join("checkpoints"), config.keep_checkpoints)?;
        for stale in durable::remove_stale_temporaries(checkpoints.dir())
            .map_err(|source| TrainError::Io { file: checkpoints.dir().to_path_buf(), source })?
        {
            tracing::warn!("removed {}, left by a checkpoint write that was cut off", stale.display());
        }
        let candidates = checkpoints.periodic();
        if candidates.is_empty() {
            return Err(TrainError::Config(format!("{} has no checkpoint to resume from", dir.display())));
        }
        let readable = |path: &Path| -> Result<(Checkpoint, Progress), TrainError> {
            let ckpt = Checkpoint::read(path)?;
            let progress: Progress = serde_json::from_slice(ckpt.get("progress")?)
                .map_err(|e| TrainError::Encoding { what: format!("{}: progress", path.display()), reason: e.to_string() })?;
            learner::Learner::from_checkpoint(&ckpt)?;
            Ok((ckpt, progress))
        };
        let mut skipped = Vec::new();
        let mut found = None;
        for path in candidates.iter().rev() {
            match readable(path) {
                Ok(ok) => {
                    found = Some(ok);
                    break;
                }
                Err(e) => {
                    tracing::warn!("cannot resume from {}: {e}; trying the checkpoint before it", path.display());
                    skipped.push(format!("{}: {e}", path.display()));
                }
            }
        }
        let Some((ckpt, progress)) = found else {
            return Err(TrainError::Config(format!("no checkpoint of {} is readable: {}", dir.display(), skipped.join("; "))));
        };
        if !skipped.is_empty() {
            tracing::warn!("resuming from iteration {} after skipping {} unreadable checkpoint(s)", progress.iteration, skipped.len());
        }
        let metrics = MetricsWriter::open(dir).map_err(|source| TrainError::Io { file: dir.to_path_buf(), source })?;
        Ok((
            Self { config, dir: dir.to_path_buf(), checkpoints, metrics, progress, pending_validation_seconds: 0.0, eta: Eta::default() },
            ckpt,
        ))
    }

    /// Opens the run in `dir` if it has a checkpoint, else starts it with `config`.
    pub fn open_or_create(config: TrainConfig, dir: &Path) -> Result<(Self, Option<Checkpoint>), TrainError> {
        let has_checkpoint = CheckpointDir::new(dir.join("checkpoints"), config.keep_checkpoints)?.latest().is_some();
        if has_checkpoint {
            let (run, ckpt) = Self::open(dir)?;
            Ok((run, Some(ckpt)))
        } else {
            Ok((Self::create(config, dir)?, None))
        }
    }

    /// The run's configuration.
    pub fn config(&self) -> &TrainConfig {
        &self.config
    }

    /// The run directory.
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// Iterations done.
    pub fn iteration(&self) -> u64 {
        self.progress.iteration
    }

    /// Wall seconds of training so far, over every sitting.
    pub fn wall_seconds(&self) -> f64 {
        self.progress.wall_seconds
    }

    /// Highest validation S_pw so far (`None` before the first evaluation).
    pub fn best_validation(&self) -> Option<f64> {
        self.progress.best_validation
    }

    /// The iteration about to be recorded (1-based).
    pub fn next_iteration(&self) -> u64 {
        self.progress.iteration + 1
    }

    /// Counts one iteration, writes its metrics row and says whether `best.bin` is to be
    /// written again ([`Run::save_best`]): after every validation when evaluation is on, else
    /// when the mean training return is the highest so far.
    pub fn record(
        &mut self,
        chunks: &[RolloutChunk],
        report: IterationReport,
        timing: IterationTiming,
        validation: Option<&Validation>,
    ) -> Result<(IterationSummary, bool), TrainError> {
        self.progress.iteration += 1;
        // `timing.seconds` runs from publication to publication, so it already holds the
        // validation that followed the previous iteration's.
        self.progress.wall_seconds += timing.seconds;
        let episodes: Vec<&policy::EpisodeRecord> = chunks.iter().flat_map(|c| &c.episodes).collect();
        let mean = |f: &dyn Fn(&policy::EpisodeRecord) -> f64| {
            if episodes.is_empty() { f64::NAN } else { episodes.iter().map(|e| f(e)).sum::<f64>() / episodes.len() as f64 }
        };
        let fastest = episodes.iter().filter_map(|e| e.fastest_lap).fold(f64::NAN, f64::min);
        let transitions: usize = chunks.iter().map(RolloutChunk::transitions).sum();
        let validation_seconds = std::mem::take(&mut self.pending_validation_seconds).min(timing.seconds);
        let training_seconds = timing.seconds - validation_seconds;
        let summary = IterationSummary {
            iteration: self.progress.iteration,
            sps: transitions as f64 / training_seconds.max(1e-9),
            collect_seconds: training_seconds - timing.update_seconds,
            validation_seconds,
            update_seconds: timing.update_seconds,
            mean_return: mean(&|e| e.episode_return),
            laps_per_episode: mean(&|e| f64::from(e.laps)),
            switches: timing.switches,
            validation: validation.map(|v| (v.report.s_pw, v.report.success_rate)),
            report,
        };
        if let Some(v) = validation {
            self.pending_validation_seconds = v.seconds;
            self.eta.validation_seconds = Some(v.seconds);
        }
        self.eta.observe(summary.sps);
        let eval = validation.map(|v| &v.report);
        let eval_value = |f: &dyn Fn(&sim::eval::EvalReport) -> f64| eval.map_or(f64::NAN, f);
        let s = &summary.report.stats;
        let row = MetricsRow {
            episodic_return: summary.mean_return,
            episodic_length: mean(&|e| f64::from(e.length)),
            laps_per_episode: summary.laps_per_episode,
            crash_rate: mean(&|e| if e.crashed { 1.0 } else { 0.0 }),
            fastest_lap: fastest,
            sps: summary.sps,
            learning_rate: summary.report.learning_rate,
            policy_loss: s.policy_loss,
            value_loss: s.value_loss,
            approx_kl: s.approx_kl,
            clip_fraction: s.clip_fraction,
            explained_variance: s.explained_variance,
            grad_norm: s.grad_norm,
            actor_grad_norm: s.actor_grad_norm,
            critic_grad_norm: s.critic_grad_norm,
            log_std: s.log_std,
            version_lag: timing.version_lag as f64,
            switches: summary.switches as f64,
            mean_q: timing.mean_q,
            eval_s_pw: eval_value(&|r| r.s_pw),
            eval_success: eval_value(&|r| r.success_rate),
            eval_mean_lap: eval_value(&|r| r.mean_lap.unwrap_or(f64::NAN)),
            eval_crash_ground: eval_value(&|r| r.outcomes.fraction(r.outcomes.ground)),
            eval_crash_ceiling: eval_value(&|r| r.outcomes.fraction(r.outcomes.ceiling)),
            eval_crash_wall: eval_value(&|r| r.outcomes.fraction(r.outcomes.wall)),
            eval_crash_gate: eval_value(&|r| r.outcomes.fraction(r.outcomes.gate_total())),
            eval_no_lap: eval_value(&|r| r.outcomes.fraction(r.outcomes.no_lap)),
            eval_seconds: validation.map_or(f64::NAN, |v| v.seconds),
            mirror_loss: s.mirror_loss,
        };
        self.metrics
            .write(self.progress.iteration, summary.report.env_steps, self.progress.wall_seconds, &row)
            .map_err(|source| TrainError::Io { file: self.dir.join("metrics.csv"), source })?;
        if let Some(v) = validation {
            crate::metrics::append_validation(&self.dir, self.progress.iteration, summary.report.env_steps, &v.report)
                .map_err(|source| TrainError::Io { file: self.dir.join("validation.csv"), source })?;
        }
        let best = if self.config.eval.every > 0 {
            if let Some(r) = eval
                && self.progress.best_validation.is_none_or(|b| r.s_pw > b)
            {
                self.progress.best_validation = Some(r.s_pw);
            }
            eval.is_some()
        } else {
            let best = summary.mean_return.is_finite() && self.progress.best_return.is_none_or(|b| summary.mean_return > b);
            if best {
                self.progress.best_return = Some(summary.mean_return);
            }
            best
        };
        Ok((summary, best))
    }

    /// True when a periodic checkpoint is due after the iteration just recorded: every
    /// `checkpoint_every` iterations, and after every validation, so that a resumed run never
    /// validates again past a policy [`Run::save_best`] has since removed from `validated/`.
    pub fn checkpoint_due(&self) -> bool {
        let every = self.config.eval.every;
        self.progress.iteration.is_multiple_of(self.config.checkpoint_every.max(1))
            || (every > 0 && self.progress.iteration.is_multiple_of(every))
    }

    /// Adds the run's bookkeeping to `ckpt` and writes it as the periodic checkpoint.
    #[allow(clippy::expect_used, reason = "progress serialises")]
    pub fn save(&self, mut ckpt: Checkpoint) -> Result<PathBuf, TrainError> {
        ckpt.put("progress", serde_json::to_vec(&self.progress).expect("progress serialises"));
        Ok(self.checkpoints.save(&ckpt, self.progress.iteration)?)
    }

    /// Writes `best.bin`, the run's policy, after [`Run::record`] asked for it: with evaluation
    /// on, `policy` (the one just validated) joins the last validated policies and `best.bin` is
    /// the weight average of the last `eval.average` of them; else `policy` itself (the highest
    /// mean training return so far).
    pub fn save_best(&self, policy: WeightsBlob) -> Result<(), TrainError> {
        let best = if self.config.eval.every > 0 {
            let keep = if policy.architecture.agent == Agent::Vision { 1 } else { self.config.eval.average };
            let kept = self.checkpoints.save_validated(&policy, self.progress.iteration, keep)?;
            let policies = kept.iter().map(|p| learner::checkpoint::read_policy(p)).collect::<Result<Vec<_>, _>>()?;
            policy::averaging::average(&policies)?
        } else {
            policy
        };
        let path = self.checkpoints.best();
        durable::write_atomic(&path, &best.to_bytes()).map_err(|source| TrainError::Io { file: path.clone(), source })
    }

    /// Estimated seconds to the end of the run after `env_steps`, from the smoothed training
    /// rate and the validations still due.
    pub fn eta_seconds(&self, env_steps: u64) -> f64 {
        let steps_left = self.config.total_env_steps.saturating_sub(env_steps);
        let every = self.config.eval.every;
        let validations_left = if every == 0 || env_steps == 0 {
            0
        } else {
            // Iterations left, at this run's steps per iteration so far.
            let iterations_left = steps_left.div_ceil(env_steps.div_ceil(self.progress.iteration.max(1)));
            (self.progress.iteration + iterations_left) / every - self.progress.iteration / every
        };
        self.eta.seconds_left(steps_left, validations_left)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_actor_timeout_that_is_not_a_positive_duration_is_refused_by_name() {
        for value in ["inf", "nan", "0.0", "-3.0"] {
            let config = TrainConfig::from_toml(&format!("[learner]\nactor_timeout_seconds = {value}\n")).unwrap();
            let error = config.resolved_profile().unwrap_err().to_string();
            assert!(error.contains("learner.actor_timeout_seconds"), "{value}: {error}");
        }
        assert!(TrainConfig::from_toml("[learner]\nactor_timeout_seconds = 0.5\n").unwrap().resolved_profile().is_ok());
    }

    #[test]
    fn numbers_out_of_range_are_refused_naming_their_field() {
        let cases = [
            ("[ppo]\ngamma = 1.5\n", "ppo.gamma"),
            ("[ppo]\nlearning_rate_start = -1e-3\n", "ppo.learning_rate_start"),
            ("[ppo]\nclip_range = 0.0\n", "ppo.clip_range"),
            ("[ppo]\nmax_grad_norm = inf\n", "ppo.max_grad_norm"),
            ("[ppo]\nadam_epsilon = nan\n", "ppo.adam_epsilon"),
            ("[ppo]\nn_epochs = 0\n", "ppo.n_epochs"),
            ("[ppo]\nmirror_fraction = 0.0\n", "ppo.mirror_fraction"),
            ("[ppo]\nmirror_fraction = 1.5\n", "ppo.mirror_fraction"),
            ("[switching]\nalpha = -1.0\n", "switching.alpha"),
            ("[switching]\nrandom_probability = 2.0\n", "switching.random_probability"),
            ("[switching]\nwindow = 1\n", "switching.window"),
            ("[learner]\nrollout_memory_mib = 0\n", "learner.rollout_memory_mib"),
        ];
        for (text, field) in cases {
            let error = TrainConfig::from_toml(text).unwrap().resolved_profile().unwrap_err().to_string();
            assert!(error.contains(field), "{text:?}: {error}");
        }
        assert!(TrainConfig::default().resolved_profile().is_ok());
    }

    #[test]
    fn frozen_layers_need_the_vision_agent_and_a_start_log_std_needs_a_start() {
        let refused = |text: &str| TrainConfig::from_toml(text).unwrap().resolved_profile().unwrap_err().to_string();
        assert!(refused("[ppo]\nfrozen = \"encoder\"\n").contains("ppo.frozen"));
        let vision = TrainConfig::from_toml("agent = \"vision\"\n[ppo]\nfrozen = \"convolutions\"\n").unwrap();
        assert_eq!(vision.resolved_profile().unwrap().ppo.frozen, learner::Frozen::Convolutions);
        assert!(refused("init_log_std = -1.5\n").contains("init_log_std: -1.5 needs init_from"));
        assert!(TrainConfig::from_toml("init_from = \"student.bin\"\ninit_log_std = -1.5\n").unwrap().resolved_profile().is_ok());
    }

    #[test]
    fn the_mirror_term_needs_a_frame_with_a_mirror_and_a_state_based_agent() {
        let resolved = |text: &str| TrainConfig::from_toml(text).unwrap().resolved_profile();
        let refused = |text: &str| resolved(text).unwrap_err().to_string();
        assert!(refused("[env.observation]\nframe = \"body\"\n[ppo]\nmirror_coef = 1.0\n").contains("not body"));
        assert!(refused("agent = \"vision\"\n[ppo]\nmirror_coef = 1.0\n").contains("state-based agent"));
        assert!(refused("[ppo]\nmirror_coef = -1.0\n").contains("ppo.mirror_coef: -1"));
        assert_eq!(resolved("[env.observation]\nframe = \"heading\"\n[ppo]\nmirror_coef = 0.5\n").unwrap().ppo.mirror_coef, 0.5);
        // On by default in the cpu profile, off in SPEC's columns, and refused in the body
        // frame with a hint to turn it off.
        assert_eq!(resolved("").unwrap().ppo.mirror_coef, 1.0);
        assert_eq!(resolved("").unwrap().ppo.mirror_fraction, 0.25, "on a quarter of each minibatch");
        assert_eq!(resolved("profile = \"paper\"\n").unwrap().ppo.mirror_fraction, 1.0);
        assert_eq!(resolved("profile = \"paper\"\n").unwrap().ppo.mirror_coef, 0.0);
        assert_eq!(resolved("agent = \"vision\"\n").unwrap().ppo.mirror_coef, 0.0);
        assert!(refused("[env.observation]\nframe = \"body\"\n").contains("set ppo.mirror_coef = 0"));
        assert!(resolved("[env.observation]\nframe = \"body\"\n[ppo]\nmirror_coef = 0.0\n").is_ok());
        // An explicit 0 survives the run directory's config file, whose reader starts from
        // the profile's 1.
        let off = TrainConfig::from_toml("[ppo]\nmirror_coef = 0.0\n").unwrap();
        let saved = TrainConfig::from_toml(&toml::to_string(&off).unwrap()).unwrap();
        assert_eq!(saved.resolved_profile().unwrap().ppo.mirror_coef, 0.0);
    }

    #[test]
    fn a_ppo_table_overrides_the_profiles_settings_field_by_field() {
        let ppo = |text: &str| TrainConfig::from_toml(text).unwrap().resolved_profile().unwrap().ppo;
        let cpu = ppo("[ppo]\ngae_lambda = 0.9\n");
        assert_eq!((cpu.gae_lambda, cpu.batch_size, cpu.n_epochs), (0.9, 4000, 5), "the cpu profile's minibatches stay");
        assert_eq!(PpoConfig { gae_lambda: 0.95, ..cpu }, Profile::cpu().ppo);
        let paper = ppo("profile = \"paper\"\n[ppo]\ngae_lambda = 0.9\n");
        assert_eq!(PpoConfig { gae_lambda: 0.95, ..paper }, Profile::paper().ppo);
        // The vision agent's column stays under a partial table too.
        let vision = ppo("agent = \"vision\"\n[ppo]\ngae_lambda = 0.9\n");
        assert_eq!(PpoConfig { gae_lambda: 0.95, ..vision }, PpoConfig::vision_based());
        let err = TrainConfig::from_toml("[ppo]\ngama = 0.998\n").unwrap_err().to_string();
        assert!(err.contains("gama"), "{err}");
    }
}
