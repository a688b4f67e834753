//! A run's configuration: [`TrainConfig`], what a config file and the command line say, and
//! [`ResolvedRun`], what it resolves to — validated once, with the profile's sizes and the PPO
//! settings filled in. The resolved run is what `config.toml` in a run directory holds and what
//! every process of the run reads.

use std::path::{Path, PathBuf};
use std::sync::Arc;

use learner::config::{LearnerConfig, PpoConfig, Profile};
use learner::learner::Learner;
use policy::Agent;
use racetracks::TrackGenerator;
use serde::{Deserialize, Serialize};
use sim::EnvConfig;
use taskctl::{SwitchParams, TaskController};

use crate::error::{ConfigError, TrainError};

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
                    .map_err(|e| ConfigError::new("", e.to_string()))?
                    .into_iter()
                    .map(Arc::new)
                    .collect();
                if chosen.is_empty() {
                    return Err(ConfigError::new("tracks", "name at least one library track (names) or track file (files)").into());
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
    pub network: transport::NetworkConfig,
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
    /// `[ppo]` table overrides the run's PPO settings ([`PpoConfig::recipe`] in the named
    /// profile's minibatches) field by field, so `gamma = 0.995` alone keeps the cpu profile's
    /// minibatches.
    pub fn from_toml(text: &str) -> Result<Self, ConfigError> {
        let text = crate::overrides::retire(text).map_err(|e| ConfigError::new("", e.to_string()))?;
        let text = text.as_ref();
        let config: Self = toml::from_str(text).map_err(|e| ConfigError::new("", e.to_string()))?;
        let mut defaults = Self::defaults_for(config.agent);
        if config.ppo.is_some() && defaults.ppo.is_none() {
            defaults.ppo = Profile::named(&config.profile).map(|profile| profile.sized(PpoConfig::recipe()));
        }
        crate::overrides::parse_over(&defaults, text).map_err(|e| ConfigError::new("", e.to_string()))
    }

    /// Reads a config file; errors name the file and the field.
    pub fn read(path: &Path) -> Result<Self, TrainError> {
        let text = durable::read_text_limited(path, durable::MAX_TEXT_FILE_BYTES)
            .map_err(|source| TrainError::Io { file: path.to_path_buf(), source })?;
        Ok(Self::from_toml(&text).map_err(|e| e.in_file(path))?)
    }

    /// Sets what `dronerace train`'s flags name over this config.
    pub fn with_flags(mut self, flags: &TrainFlags) -> Result<Self, ConfigError> {
        if let Some(p) = &flags.profile {
            self.profile = p.clone();
        }
        if let Some(t) = &flags.track {
            // A path (a file that exists, or anything ending in .toml) is a track file; otherwise
            // a library name. Either way the validation flies the same track.
            let is_file = t.ends_with(".toml") || Path::new(t).is_file();
            // Absolute, so that the run's config.toml still finds the file from elsewhere (resume).
            let file = || std::fs::canonicalize(t).map_err(|e| ConfigError::new("--track", format!("{t}: {e}")));
            let (names, files) = if is_file { (Vec::new(), vec![file()?]) } else { (vec![t.clone()], Vec::new()) };
            racetracks::chosen_tracks(["--track"; 2], &names, &files).map_err(|e| ConfigError::new("", e.to_string()))?;
            self.eval.library = names.clone();
            self.eval.files = files.clone();
            self.tracks = TrackSource::Chosen { names, files };
            self.switching.policy = taskctl::SwitchPolicy::None;
        }
        if let Some(n) = flags.total_env_steps {
            self.total_env_steps = n;
        }
        if let Some(s) = flags.seed {
            self.seed = s;
        }
        if let Some(p) = &flags.init_from {
            self.init_from = Some(p.clone());
        }
        Ok(self)
    }

    /// Validates every setting once and fills in what the profile and the agent decide: the
    /// run every process of it reads.
    pub fn resolve(mut self) -> Result<ResolvedRun, ConfigError> {
        let profile = Profile::named(&self.profile)
            .ok_or_else(|| ConfigError::new("profile", format!("unknown profile {:?} (cpu, paper)", self.profile)))?;
        let mut learner = profile.learner_config(self.ppo.unwrap_or_else(|| profile.sized(PpoConfig::recipe())));
        if let Some(envs) = self.envs {
            learner.envs = envs;
        }
        if let Some(hidden) = &self.hidden {
            if hidden.is_empty() || hidden.contains(&0) {
                return Err(ConfigError::new("hidden", format!("{hidden:?} needs at least one layer, every width ≥ 1")));
            }
            learner.architecture.hidden = hidden.clone();
        }
        let timeout = self.learner.actor_timeout_seconds;
        if !(timeout.is_finite() && timeout > 0.0) {
            return Err(ConfigError::new("learner.actor_timeout_seconds", format!("{timeout} must be a positive number of seconds")));
        }
        let memory = self.learner.rollout_memory_mib;
        if memory == 0 || memory > 1 << 20 {
            return Err(ConfigError::new("learner.rollout_memory_mib", format!("{memory} must be 1 to 1048576 (1 TiB)")));
        }
        // The network reads the observations the environments write.
        let spacing = self.env.observation.line_spacing;
        if self.env.observation.line_points > 0 && !(spacing.is_finite() && spacing >= 0.0) {
            return Err(ConfigError::new("env.observation.line_spacing", format!("{spacing} m must be a distance ≥ 0")));
        }
        learner.architecture.set_observation_layout(self.env.observation);
        learner.architecture.agent = self.agent;
        let mirror = learner.ppo.mirror_coef;
        if mirror != 0.0 {
            if !(mirror.is_finite() && mirror > 0.0) {
                return Err(ConfigError::new("ppo.mirror_coef", format!("{mirror} must be a weight ≥ 0")));
            }
            if self.agent != Agent::State || self.env.observation.mirror().is_none() {
                return Err(ConfigError::new(
                    "ppo.mirror_coef",
                    "the mirror term (on by default) needs the state-based agent and an observation frame with a mirror (world or heading, not body); set ppo.mirror_coef = 0 to train without it",
                ));
            }
        }
        if !learner.ppo.frozen.is_nothing() && self.agent != Agent::Vision {
            return Err(ConfigError::new("ppo.frozen", "only the vision agent has image layers to freeze (agent = \"vision\")"));
        }
        if let Some(log_std) = self.init_log_std
            && (self.init_from.is_none() || !log_std.is_finite())
        {
            return Err(ConfigError::new("init_log_std", format!("{log_std} needs init_from and a finite value")));
        }
        if learner.envs == 0 {
            return Err(ConfigError::new("envs", "must be ≥ 1"));
        }
        if self.eval.average == 0 {
            return Err(ConfigError::new("eval.average", "0 must be at least 1 (the last validated policy alone)"));
        }
        learner.ppo.check().map_err(|e| ConfigError::new(format!("ppo.{}", e.field), e.reason))?;
        self.env.disturbance.check().map_err(|e| ConfigError::new(format!("env.disturbance.{}", e.field), e.reason))?;
        let weak = self.env.randomization.motor_thrust;
        if !(weak.is_finite() && (0.0..0.9).contains(&weak)) {
            return Err(ConfigError::new("env.randomization.motor_thrust", format!("{weak} must be a share of thrust in 0..0.9")));
        }
        self.switching.check().map_err(|e| ConfigError::new(format!("switching.{}", e.field), e.reason))?;
        // A gRPC learner must be able to hold at least one rollout of every environment, as
        // sent and as decoded.
        let arch = &learner.architecture;
        let limits = rollout::ChunkLimits {
            observation_dim: arch.observation_dim,
            action_dim: arch.action_dim,
            max_envs: learner.envs,
            max_steps: learner.ppo.n_steps,
            images: self.agent == Agent::Vision,
        };
        let whole_run = 2 * limits.decoded_bytes(learner.envs * learner.ppo.n_steps);
        if memory.saturating_mul(1 << 20) < whole_run {
            return Err(ConfigError::new(
                "learner.rollout_memory_mib",
                format!(
                    "{memory} MiB cannot hold one rollout of all {} environments ({} MiB as sent and decoded)",
                    learner.envs,
                    whole_run.div_ceil(1 << 20)
                ),
            ));
        }
        // What config.toml holds: every size and PPO setting written out, so that a later
        // change of a default does not change a run that exists.
        self.envs = Some(learner.envs);
        self.hidden = Some(learner.architecture.hidden.clone());
        self.ppo = Some(learner.ppo);
        Ok(ResolvedRun { config: self, learner })
    }
}

/// What `dronerace train`'s flags set over a config file; `None` keeps the file's value.
#[derive(Clone, Debug, Default, clap::Args)]
pub struct TrainFlags {
    /// Profile (overrides the config): cpu (256×256, 96 environments) or paper (SPEC §10's sizes).
    #[arg(long, value_parser = ["cpu", "paper"])]
    pub profile: Option<String>,
    /// Train on this one track instead of generated tracks: a library track's name (e.g.
    /// Figure8) or a track file (e.g. my-track.toml); validation then flies it too.
    #[arg(long)]
    pub track: Option<String>,
    /// Environment steps of the run (overrides the config).
    #[arg(long)]
    pub total_env_steps: Option<u64>,
    /// Seed (overrides the config).
    #[arg(long)]
    pub seed: Option<u64>,
    /// Start from this trained policy (checkpoint or weights blob): fine-tuning. Pair it with
    /// a lower learning rate in the config's [ppo] section.
    #[arg(long)]
    pub init_from: Option<PathBuf>,
}

/// A run's configuration validated once, with the learner it trains: what every process of the
/// run reads. Made by [`TrainConfig::resolve`].
#[derive(Clone, Debug, PartialEq)]
pub struct ResolvedRun {
    config: TrainConfig,
    learner: LearnerConfig,
}

impl ResolvedRun {
    /// The configuration, with its sizes and PPO settings filled in.
    pub fn config(&self) -> &TrainConfig {
        &self.config
    }

    /// What the learner trains with: network, PPO settings, environments.
    pub fn learner(&self) -> &LearnerConfig {
        &self.learner
    }

    /// Environments of the whole run, over all actors.
    pub fn envs(&self) -> usize {
        self.learner.envs
    }

    /// Steps each environment takes per iteration.
    pub fn n_steps(&self) -> usize {
        self.learner.ppo.n_steps
    }

    /// An actor of this run named `name` with `envs` environments: the run's seed, environment
    /// and rollout length, waiting for new weights as long as the learner waits for rollouts.
    pub fn actor_settings(&self, name: &str, envs: usize) -> crate::actor_process::ActorSettings {
        let c = &self.config;
        crate::actor_process::ActorSettings {
            name: name.into(),
            envs,
            seed: c.seed,
            env: c.env,
            n_steps: self.n_steps(),
            weights_timeout: std::time::Duration::from_secs_f64(c.learner.actor_timeout_seconds.max(0.1)),
            max_rollouts: None,
        }
    }

    /// The text of the run directory's `config.toml`.
    #[allow(clippy::expect_used, reason = "a config always serialises")]
    pub fn to_toml(&self) -> String {
        toml::to_string(&self.config).expect("a config always serialises")
    }

    /// Reads and resolves a config file; errors name the file and the field.
    pub fn read(path: &Path) -> Result<Self, TrainError> {
        Ok(TrainConfig::read(path)?.resolve().map_err(|e| e.in_file(path))?)
    }

    /// The task controller of this run's environments.
    pub fn task_controller(&self) -> Result<TaskController, TrainError> {
        let c = &self.config;
        c.tracks.task_controller(self.envs(), c.generator, c.switching, c.seed)
    }

    /// The learner a new run starts with: fresh, or from `init_from`.
    pub fn initial_learner(&self) -> Result<Learner, TrainError> {
        let c = &self.config;
        let learner = self.learner.clone();
        Ok(match &c.init_from {
            None => Learner::new(learner, c.total_env_steps, c.seed),
            Some(path) => {
                let config_error = |e: &dyn std::fmt::Display| ConfigError::new("init_from", format!("{}: {e}", path.display()));
                let mut policy = learner::checkpoint::read_policy(path)?;
                if let Some(log_std) = c.init_log_std {
                    policy = policy.with_log_std(log_std as f32).map_err(|e| config_error(&e))?;
                }
                // A wider run than its start: the start's function, with room to grow.
                if policy.architecture.hidden != learner.architecture.hidden {
                    policy = policy.with_hidden(&learner.architecture.hidden, c.seed).map_err(|e| config_error(&e))?;
                }
                Learner::from_policy(learner, c.total_env_steps, c.seed, &policy).map_err(|e| config_error(&e))?
            }
        })
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_actor_timeout_that_is_not_a_positive_duration_is_refused_by_name() {
        for value in ["inf", "nan", "0.0", "-3.0"] {
            let config = TrainConfig::from_toml(&format!("[learner]\nactor_timeout_seconds = {value}\n")).unwrap();
            let error = config.resolve().unwrap_err().to_string();
            assert!(error.contains("learner.actor_timeout_seconds"), "{value}: {error}");
        }
        assert!(TrainConfig::from_toml("[learner]\nactor_timeout_seconds = 0.5\n").unwrap().resolve().is_ok());
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
            let error = TrainConfig::from_toml(text).unwrap().resolve().unwrap_err().to_string();
            assert!(error.contains(field), "{text:?}: {error}");
        }
        assert!(TrainConfig::default().resolve().is_ok());
    }

    #[test]
    fn frozen_layers_need_the_vision_agent_and_a_start_log_std_needs_a_start() {
        let refused = |text: &str| TrainConfig::from_toml(text).unwrap().resolve().unwrap_err().to_string();
        assert!(refused("[ppo]\nfrozen = \"encoder\"\n").contains("ppo.frozen"));
        let vision = TrainConfig::from_toml("agent = \"vision\"\n[ppo]\nfrozen = \"convolutions\"\n").unwrap();
        assert_eq!(vision.resolve().unwrap().learner().ppo.frozen, learner::Frozen::Convolutions);
        assert!(refused("init_log_std = -1.5\n").contains("init_log_std: -1.5 needs init_from"));
        assert!(TrainConfig::from_toml("init_from = \"student.bin\"\ninit_log_std = -1.5\n").unwrap().resolve().is_ok());
    }

    #[test]
    fn the_mirror_term_needs_a_frame_with_a_mirror_and_a_state_based_agent() {
        let resolved = |text: &str| TrainConfig::from_toml(text).unwrap().resolve();
        let refused = |text: &str| resolved(text).unwrap_err().to_string();
        assert!(refused("[env.observation]\nframe = \"body\"\n[ppo]\nmirror_coef = 1.0\n").contains("not body"));
        assert!(refused("agent = \"vision\"\n[ppo]\nmirror_coef = 1.0\n").contains("state-based agent"));
        assert!(refused("[ppo]\nmirror_coef = -1.0\n").contains("ppo.mirror_coef: -1"));
        assert_eq!(resolved("[env.observation]\nframe = \"heading\"\n[ppo]\nmirror_coef = 0.5\n").unwrap().learner().ppo.mirror_coef, 0.5);
        // On by default, off in the vision agent's column, and refused in the body frame with a
        // hint to turn it off.
        assert_eq!(resolved("").unwrap().learner().ppo.mirror_coef, 1.0);
        assert_eq!(resolved("").unwrap().learner().ppo.mirror_fraction, 0.25, "on a quarter of each minibatch");
        assert_eq!(resolved("profile = \"paper\"\n").unwrap().learner().ppo.mirror_coef, 1.0, "the same algorithm under every profile");
        assert_eq!(resolved("agent = \"vision\"\n").unwrap().learner().ppo.mirror_coef, 0.0);
        assert!(refused("[env.observation]\nframe = \"body\"\n").contains("set ppo.mirror_coef = 0"));
        assert!(resolved("[env.observation]\nframe = \"body\"\n[ppo]\nmirror_coef = 0.0\n").is_ok());
        // An explicit 0 survives the run directory's config file, whose reader starts from
        // the recipe's 1.
        let off = TrainConfig::from_toml("[ppo]\nmirror_coef = 0.0\n").unwrap();
        let saved = TrainConfig::from_toml(&toml::to_string(&off).unwrap()).unwrap();
        assert_eq!(saved.resolve().unwrap().learner().ppo.mirror_coef, 0.0);
    }

    #[test]
    fn a_ppo_table_overrides_the_recipe_in_the_profiles_minibatches_field_by_field() {
        let ppo = |text: &str| TrainConfig::from_toml(text).unwrap().resolve().unwrap().learner().ppo;
        let cpu = ppo("[ppo]\ngae_lambda = 0.9\n");
        assert_eq!((cpu.gae_lambda, cpu.batch_size, cpu.n_epochs), (0.9, 4000, 5), "the cpu profile's minibatches stay");
        assert_eq!(PpoConfig { gae_lambda: 0.95, ..cpu }, Profile::cpu().sized(PpoConfig::recipe()));
        let paper = ppo("profile = \"paper\"\n[ppo]\ngae_lambda = 0.9\n");
        assert_eq!(PpoConfig { gae_lambda: 0.95, ..paper }, Profile::paper().sized(PpoConfig::recipe()));
        // The vision agent's column stays under a partial table too.
        let vision = ppo("agent = \"vision\"\n[ppo]\ngae_lambda = 0.9\n");
        assert_eq!(PpoConfig { gae_lambda: 0.95, ..vision }, PpoConfig::vision_based());
        let err = TrainConfig::from_toml("[ppo]\ngama = 0.998\n").unwrap_err().to_string();
        assert!(err.contains("gama"), "{err}");
    }

    #[test]
    fn config_toml_holds_the_resolved_run_and_reads_back_to_it() {
        let resolved = TrainConfig::from_toml("profile = \"paper\"\n[ppo]\ngamma = 0.995\nmirror_coef = 0.0\n").unwrap().resolve().unwrap();
        let text = resolved.to_toml();
        for line in ["envs = 96", "hidden = [512, 512]", "gamma = 0.995", "batch_size = 28000", "mirror_coef = 0.0"] {
            assert!(text.contains(line), "config.toml names {line:?}:\n{text}");
        }
        assert_eq!(TrainConfig::from_toml(&text).unwrap().resolve().unwrap(), resolved);
        // The thesis as written: SPEC §10's column, bit for bit.
        let spec =
            learner::Profile::paper().sized(PpoConfig { gamma: 0.995, mirror_coef: 0.0, mirror_fraction: 1.0, ..PpoConfig::recipe() });
        assert_eq!(spec, PpoConfig::default());
    }

    #[test]
    fn config_errors_name_the_file_and_the_field() {
        let error = ConfigError::new("ppo.gamma", "1.5 is outside 0..=1").in_file(Path::new("runs/x/config.toml"));
        assert_eq!(error.to_string(), "runs/x/config.toml: ppo.gamma: 1.5 is outside 0..=1");
        let refused = TrainConfig::from_toml("[ppo]\ngamma = 1.5\n").unwrap().resolve().unwrap_err();
        assert_eq!((refused.field.as_str(), refused.file.as_deref()), ("ppo.gamma", None));
        let flags = TrainFlags { track: Some("NoSuchTrack".into()), ..TrainFlags::default() };
        assert!(TrainConfig::default().with_flags(&flags).unwrap_err().to_string().contains("NoSuchTrack"));
    }
}
