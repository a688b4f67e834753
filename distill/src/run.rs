//! A distillation run (`dronerace distill`): each round the environments fly `steps_per_round`
//! steps — every step by the teacher with probability β = `teacher_decay`^round, else by the
//! student (round 0: the teacher alone), and with `takeover` set by the teacher also wherever
//! the student's action strays further than that from the teacher's — while the teacher labels
//! every visited state with its action; the labelled states join the data set
//! ([`crate::dataset`]), the task controller switches tracks on the round's rewards as in
//! training, and the student takes `updates_per_round` regression steps on minibatches drawn
//! from the whole data set. Like `train`: `metrics.csv` and TensorBoard events, validation on
//! the held-out validation tracks (`best.bin`), periodic checkpoints holding everything
//! (teacher, student, optimiser, data set, environments, curriculum, random state), and resume
//! that continues bit for bit.

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, bail, ensure};
use learner::checkpoint::{Checkpoint, CheckpointDir, read_policy};
use policy::{ActingPolicy, Agent, Architecture, Policy, WeightsBlob};
use racetracks::TrackGenerator;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use sim::{
    ACTION_DIM, Controller, EnvConfig, PilotMemory, PilotParams, RaceEnv, RandomizationParams, ReferencePilot, RewardParams, VecEnv,
};
use taskctl::{LocalTasks, SwitchParams, TaskController, TaskService};

use runtime::TrackSource;
use runtime::metrics::{MetricsWriter, append_validation};
use runtime::validation::{EvalSettings, Validator};

use crate::dataset::DistillDataset;
use crate::student::Student;

/// The student's name in the task controller.
const ACTOR: &str = "distill";

/// The `teacher` that names the reference pilot rather than a policy file.
pub const PILOT_TEACHER: &str = "pilot";

/// `dronerace distill --config FILE`: every field optional except the teacher.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct DistillConfig {
    /// The teacher: a state-based policy (checkpoint or weights blob), or `pilot` for the
    /// reference pilot.
    pub teacher: PathBuf,
    /// The student's agent: `vision` (default) or `state`.
    pub student: Agent,
    /// Hidden widths of a student taught by the pilot (default: the `cpu` profile's); a
    /// policy's student takes its teacher's.
    pub hidden: Option<Vec<usize>>,
    /// Seed of everything (student init, environments, curriculum, sampling).
    pub seed: u64,
    /// Parallel environments. Default 32.
    pub envs: usize,
    /// Steps every environment flies per round. Default 100.
    pub steps_per_round: usize,
    /// Rounds of the whole run. Default 60.
    pub rounds: u64,
    /// β of round r is `teacher_decay`^r: the share of steps the teacher flies. Default 0.8.
    pub teacher_decay: f64,
    /// Expert intervention: on a step the student flies, the teacher flies instead when any
    /// component of the student's action differs from the teacher's label by more than this
    /// (actions are in [−1, 1]). Keeps the student's flights near the teacher's, so the data
    /// set holds states it can recover from rather than the run-up to its crashes. Default
    /// none (pure DAgger).
    pub takeover: Option<f64>,
    /// Samples the data set keeps (reservoir sampling beyond). Default 1,000,000 (~250 MB).
    pub capacity: usize,
    /// Regression steps per round. Default 160.
    pub updates_per_round: usize,
    /// Samples per regression step. Default 64: the CNN learns from more, smaller steps faster
    /// than from fewer large ones at the same cost (~2 ms a sample on one core).
    pub minibatch: usize,
    /// Adam's learning rate, constant. Default 5e-4.
    pub learning_rate: f64,
    /// The vision student's actor also reads its previous action (beyond SPEC §5's VB actor
    /// input). The teacher's observation holds the previous action and its labels depend on
    /// it as much as they depend on anything the image shows (docs/notebook/vision.md, "The
    /// teacher's previous action"), so a student without it cannot copy them. A start (`init_from`)
    /// without it is widened with zero weights. Default false.
    pub previous_action: bool,
    /// The student's log standard deviation, for vision PPO started from it (SPEC §10 VB: 0).
    pub initial_log_std: f64,
    /// Start the student's CNN and actor from this policy (checkpoint or blob of the
    /// teacher's shape; e.g. a student distilled on one track) instead of a fresh network.
    pub init_from: Option<PathBuf>,
    /// Tracks the student flies (default generated, as in training).
    pub tracks: TrackSource,
    /// Track generator.
    pub generator: TrackGenerator,
    /// Task switching, once per round. Default adaptive with α = 100 (SPEC §8's VB column) and
    /// a window of 5 rounds: a round is 100 steps, not the 250 of a PPO rollout, and a whole
    /// distillation has only tens of them.
    pub switching: SwitchParams,
    /// Environments: the VB column of SPEC §3's randomisation and the VB reward (rewards only
    /// steer switching here). The observation layout is always the teacher's.
    pub env: EnvConfig,
    /// Rounds between checkpoints. Default 5.
    pub checkpoint_every: u64,
    /// Periodic checkpoints kept. Default 3.
    pub keep_checkpoints: usize,
    /// Validation of the student during distillation (`every` counts rounds). Default every 10
    /// rounds, 10 validation tracks × 4 deployments.
    pub eval: EvalSettings,
}

impl Default for DistillConfig {
    fn default() -> Self {
        Self {
            teacher: PathBuf::new(),
            student: Agent::Vision,
            hidden: None,
            seed: 0,
            envs: 32,
            steps_per_round: 100,
            rounds: 60,
            teacher_decay: 0.8,
            takeover: None,
            capacity: 1_000_000,
            updates_per_round: 160,
            minibatch: 64,
            previous_action: false,
            learning_rate: 5e-4,
            initial_log_std: 0.0,
            init_from: None,
            tracks: TrackSource::Generated,
            generator: TrackGenerator::default(),
            switching: SwitchParams { window: 5, alpha: 100.0, ..SwitchParams::default() },
            env: EnvConfig {
                randomization: RandomizationParams::vision_based(),
                reward: RewardParams::vision_based(),
                ..EnvConfig::default()
            },
            checkpoint_every: 5,
            keep_checkpoints: 3,
            eval: EvalSettings { every: 10, tracks: 10, runs: 4, ..EvalSettings::default() },
        }
    }
}

/// What `dronerace distill`'s flags set over a config file; `None` keeps the file's value.
#[derive(Clone, Debug, Default)]
pub struct DistillFlags {
    /// `--student`.
    pub student: Option<Agent>,
    /// `--teacher`: a state-based checkpoint or weights blob, or `pilot`.
    pub teacher: Option<PathBuf>,
    /// `--total-rounds`.
    pub rounds: Option<u64>,
    /// `--seed`.
    pub seed: Option<u64>,
}

impl DistillConfig {
    /// The defaults of a `student`: a vision student's as [`Default`]; a state-based
    /// student's take SPEC's SB columns of randomisation (§3), reward (§5) and α = 1000 (§8),
    /// and the log std −2 (σ 0.14), so that PPO from the student keeps what it imitated.
    pub fn defaults_for(student: Agent) -> Self {
        match student {
            Agent::Vision => Self::default(),
            Agent::State => {
                let env = EnvConfig::default();
                let switching = SwitchParams { alpha: SwitchParams::default().alpha, ..Self::default().switching };
                Self { student, env, switching, initial_log_std: -2.0, ..Self::default() }
            }
        }
    }

    /// Reads a config file over the defaults of the student it names; errors name the file and
    /// the field.
    pub fn read(path: &Path) -> anyhow::Result<Self> {
        let text = durable::read_text_limited(path, durable::MAX_TEXT_FILE_BYTES).with_context(|| format!("reading {}", path.display()))?;
        let error = |e: runtime::overrides::OverrideError| anyhow::anyhow!("{}: {e}", path.display());
        let student = runtime::overrides::parse_over(&Self::default(), &text).map_err(error)?.student;
        runtime::overrides::parse_over(&Self::defaults_for(student), &text).map_err(error)
    }

    /// A new distillation's config: the file's (or the defaults of the student the flags name,
    /// a vision student without one), with the flags set over it.
    pub fn with_flags(file: Option<&Path>, flags: &DistillFlags) -> anyhow::Result<Self> {
        let mut config = match file {
            Some(path) => Self::read(path)?,
            None => Self::defaults_for(flags.student.unwrap_or(Agent::Vision)),
        };
        if let Some(student) = flags.student {
            config.student = student;
        }
        if let Some(teacher) = &flags.teacher {
            config.teacher = teacher.clone();
        }
        if let Some(rounds) = flags.rounds {
            config.rounds = rounds;
        }
        if let Some(seed) = flags.seed {
            config.seed = seed;
        }
        Ok(config)
    }

    /// Writes the config as TOML, atomically.
    pub fn write(&self, path: &Path) -> anyhow::Result<()> {
        let text = toml::to_string(self).context("serialising the config")?;
        durable::write_atomic(path, text.as_bytes()).with_context(|| format!("writing {}", path.display()))
    }

    /// True when the teacher is the reference pilot.
    pub fn pilot_teaches(&self) -> bool {
        self.teacher.as_os_str() == PILOT_TEACHER
    }

    fn check(&self) -> anyhow::Result<()> {
        ensure!(!self.teacher.as_os_str().is_empty(), "teacher: name the state-based policy to learn from, or `pilot` (--teacher)");
        ensure!(
            self.hidden.is_none() || self.pilot_teaches(),
            "hidden: only a student of the pilot chooses its widths; a policy's student takes its teacher's"
        );
        if let Some(hidden) = &self.hidden {
            ensure!(!hidden.is_empty() && !hidden.contains(&0), "hidden: {hidden:?} needs at least one layer, every width ≥ 1");
        }
        ensure!(
            self.envs > 0 && self.steps_per_round > 0 && self.minibatch > 0 && self.capacity > 0,
            "envs, steps_per_round, minibatch and capacity must be ≥ 1"
        );
        ensure!((0.0..=1.0).contains(&self.teacher_decay), "teacher_decay: {} is not in [0, 1]", self.teacher_decay);
        if let Some(t) = self.takeover {
            ensure!(t >= 0.0, "takeover: {t} must be ≥ 0 (the largest allowed difference from the teacher's action)");
        }
        ensure!(self.learning_rate > 0.0, "learning_rate: {} must be positive", self.learning_rate);
        ensure!(
            !self.previous_action || self.student == Agent::Vision,
            "previous_action: only a vision student's actor is limited to proprioception; a state student reads the whole observation"
        );
        Ok(())
    }
}

/// What a round did, for the progress line and the metrics.
#[derive(Clone, Debug, PartialEq)]
pub struct RoundSummary {
    /// Rounds done.
    pub round: u64,
    /// Share of steps the teacher flew.
    pub teacher_share: f64,
    /// Samples offered to the data set so far.
    pub samples_seen: u64,
    /// Samples it holds.
    pub dataset: usize,
    /// Mean regression loss of the round's steps (NaN when none were taken).
    pub loss: f64,
    /// Episodes that ended this round.
    pub episodes: usize,
    /// Their mean completed laps.
    pub laps_per_episode: f64,
    /// Fraction of them that crashed.
    pub crash_rate: f64,
    /// Seconds flying (and rendering, labelling).
    pub fly_seconds: f64,
    /// Seconds of the regression steps.
    pub fit_seconds: f64,
    /// Validation S_pw and success, when the round was validated.
    pub validation: Option<(f64, f64)>,
}

/// What one round's flying counted.
#[derive(Debug, Default)]
struct Flight {
    episodes: usize,
    laps: u64,
    crashes: usize,
    teacher_steps: usize,
}

/// Counters and random state saved in the checkpoint's `distiller` section.
#[derive(Clone, Debug, Serialize, Deserialize)]
struct Progress {
    round: u64,
    rollout: u64,
    wall_seconds: f64,
    best_validation: Option<f64>,
    rng: ChaCha8Rng,
    envs: Vec<RaceEnv>,
    /// The pilots' memories when the pilot teaches (one per environment).
    #[serde(default)]
    pilots: Vec<Option<PilotMemory>>,
}

/// Who labels the visited states.
enum Teacher {
    /// A state-based policy, and its blob's bytes (saved in every checkpoint).
    Policy(Box<Policy>, Vec<u8>),
    /// The reference pilot, one per environment (it remembers its path and progress).
    Pilot(Vec<ReferencePilot>),
}

impl Teacher {
    /// The teacher's actions for the environments' current states.
    fn labels(&mut self, env: &VecEnv) -> Vec<f32> {
        match self {
            Teacher::Policy(policy, _) => policy.deterministic_actions(&env.observations),
            Teacher::Pilot(pilots) => pilots.par_iter_mut().zip(env.envs().par_iter()).flat_map_iter(|(p, e)| p.act(e)).collect(),
        }
    }

    /// Tells the teacher that environment `i` starts an episode.
    fn episode_started(&mut self, i: usize, env: &VecEnv) {
        if let Teacher::Pilot(pilots) = self {
            pilots[i].reset(&env.envs()[i]);
        }
    }
}

/// A distillation run in its directory.
pub struct Distiller {
    config: DistillConfig,
    dir: PathBuf,
    teacher: Teacher,
    student: Student,
    data: DistillDataset,
    env: VecEnv,
    tasks: LocalTasks,
    progress: Progress,
    checkpoints: CheckpointDir,
    metrics: MetricsWriter,
    validator: Option<Validator>,
}

/// `metrics.csv` columns after `iteration,env_steps,wall_seconds` (iteration = round,
/// env_steps = samples seen).
const COLUMNS: [&str; 9] = [
    "distill/loss",
    "distill/teacher_share",
    "distill/dataset",
    "charts/laps_per_episode",
    "charts/crash_rate",
    "eval/S_pw",
    "eval/success",
    "eval/mean_lap",
    "eval/seconds",
];

impl Distiller {
    /// Starts a new distillation in `dir` (which must not hold checkpoints already); the
    /// config, with the teacher's observation layout filled in, is written to `dir/config.toml`.
    pub fn start(mut config: DistillConfig, dir: &Path) -> anyhow::Result<Self> {
        config.check()?;
        let checkpoints = CheckpointDir::new(dir.join("checkpoints"), config.keep_checkpoints)?;
        ensure!(
            checkpoints.latest().is_none(),
            "{} already holds checkpoints: resume it (--resume), or choose another run directory",
            dir.display()
        );
        let teacher_blob = match config.pilot_teaches() {
            true => None,
            false => Some(read_policy(&config.teacher).with_context(|| format!("teacher {}", config.teacher.display()))?),
        };
        let architecture = match &teacher_blob {
            Some(blob) => {
                if blob.architecture.agent != Agent::State {
                    bail!("teacher {}: a {} policy; the teacher must be state-based", config.teacher.display(), blob.architecture.agent);
                }
                // The teacher's observation is the student's state input and its critic's.
                config.env.observation = blob.architecture.observation;
                Architecture { agent: config.student, vision_previous_action: config.previous_action, ..blob.architecture.clone() }
            }
            None => {
                let mut architecture = learner::config::Profile::cpu().architecture;
                if let Some(hidden) = &config.hidden {
                    architecture.hidden = hidden.clone();
                }
                architecture.set_observation_layout(config.env.observation);
                Architecture { agent: config.student, vision_previous_action: config.previous_action, ..architecture }
            }
        };
        config.write(&dir.join("config.toml"))?;
        let tasks = LocalTasks::new(config.tracks.task_controller(config.envs, config.generator, config.switching, config.seed)?, None);
        let registration = tasks.register(ACTOR, config.envs)?;
        let env = with_images(VecEnv::new(registration.tracks, config.env, config.seed), &config);
        let start = match &config.init_from {
            Some(path) => Some(read_policy(path).with_context(|| format!("init_from {}", path.display()))?),
            None => None,
        };
        let student = Student::new(&architecture, teacher_blob.as_ref(), start.as_ref(), config.initial_log_std, config.seed)
            .with_context(|| config.init_from.as_ref().map_or(String::new(), |p| format!("init_from {}", p.display())))?;
        let progress = Progress {
            round: 0,
            rollout: registration.next_rollout,
            wall_seconds: 0.0,
            best_validation: None,
            rng: ChaCha8Rng::seed_from_u64(config.seed ^ 0xDA66_E400),
            envs: Vec::new(),
            pilots: Vec::new(),
        };
        let teacher_bytes = teacher_blob.as_ref().map(WeightsBlob::to_bytes);
        let data = DistillDataset::new(config.capacity, architecture.observation_dim);
        let mut teacher = match teacher_blob.zip(teacher_bytes) {
            Some((blob, bytes)) => Teacher::Policy(Box::new(Policy::from_blob(&blob)?), bytes),
            None => Teacher::Pilot(vec![ReferencePilot::new(PilotParams::default()); env.len()]),
        };
        for i in 0..env.len() {
            teacher.episode_started(i, &env);
        }
        let (metrics, validator) = Self::around(&config, dir)?;
        let dir = dir.to_path_buf();
        Ok(Self { config, dir, teacher, student, data, env, tasks, progress, checkpoints, metrics, validator })
    }

    /// Continues the distillation in `dir` from its newest checkpoint, `total_rounds` long if
    /// given (written to its config.toml: the run is extended or shortened).
    pub fn resume_for(dir: &Path, total_rounds: Option<u64>) -> anyhow::Result<Self> {
        if let Some(rounds) = total_rounds {
            let path = dir.join("config.toml");
            let mut config = DistillConfig::read(&path)?;
            config.rounds = rounds;
            config.write(&path)?;
        }
        Self::resume(dir)
    }

    /// Continues the distillation in `dir` from its newest checkpoint.
    pub fn resume(dir: &Path) -> anyhow::Result<Self> {
        let (config, checkpoints, path, c) = newest_checkpoint(dir)?;
        let section = |name: &str| c.get(name).with_context(|| format!("{}", path.display()));
        let student = Student::restore(section("weights")?, section("optimizer")?, config.pilot_teaches())
            .with_context(|| format!("{}", path.display()))?;
        let data = DistillDataset::from_bytes(section("dataset")?).with_context(|| format!("{}", path.display()))?;
        let mut progress: Progress =
            serde_json::from_slice(section("distiller")?).with_context(|| format!("{}: distiller section", path.display()))?;
        let tasks = LocalTasks::new(TaskController::from_snapshot_bytes(section("taskctl")?, &path)?, None);
        let env = with_images(VecEnv::from_envs(std::mem::take(&mut progress.envs)), &config);
        let teacher = match config.pilot_teaches() {
            false => {
                let bytes = section("teacher")?.to_vec();
                Teacher::Policy(Box::new(Policy::from_blob(&WeightsBlob::from_bytes(&bytes)?)?), bytes)
            }
            true => {
                ensure!(
                    progress.pilots.len() == env.len(),
                    "{}: {} pilots for {} environments",
                    path.display(),
                    progress.pilots.len(),
                    env.len()
                );
                let pilots = std::mem::take(&mut progress.pilots).into_iter().zip(env.envs()).map(|(memory, e)| match memory {
                    Some(memory) => ReferencePilot::recall(PilotParams::default(), e.track(), memory),
                    None => ReferencePilot::new(PilotParams::default()),
                });
                Teacher::Pilot(pilots.collect())
            }
        };
        let (metrics, validator) = Self::around(&config, dir)?;
        let dir = dir.to_path_buf();
        Ok(Self { config, dir, teacher, student, data, env, tasks, progress, checkpoints, metrics, validator })
    }

    /// What start and resume build alike from the config: the metrics files and the validator.
    fn around(config: &DistillConfig, dir: &Path) -> anyhow::Result<(MetricsWriter, Option<Validator>)> {
        let metrics = MetricsWriter::open_with_columns(dir, &COLUMNS).with_context(|| format!("opening metrics in {}", dir.display()))?;
        Ok((metrics, Validator::new(&config.eval)?))
    }

    /// The run's configuration.
    pub fn config(&self) -> &DistillConfig {
        &self.config
    }

    /// Rounds done.
    pub fn round(&self) -> u64 {
        self.progress.round
    }

    /// True once every round is done.
    pub fn finished(&self) -> bool {
        self.progress.round >= self.config.rounds
    }

    /// The student now.
    pub fn student(&self) -> WeightsBlob {
        self.student.weights()
    }

    /// The run directory.
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// Seconds the run took so far, over every sitting.
    pub fn wall_seconds(&self) -> f64 {
        self.progress.wall_seconds
    }

    /// One round: fly and label, switch tracks, regress; validate, log and checkpoint when due.
    pub fn round_step(&mut self) -> anyhow::Result<RoundSummary> {
        let started = Instant::now();
        let flight = self.fly()?;
        let fly_seconds = started.elapsed().as_secs_f64();
        let fit_started = Instant::now();
        let loss = self.regress();
        let fit_seconds = fit_started.elapsed().as_secs_f64();
        self.progress.round += 1;
        let round = self.progress.round;
        let validation = match &self.validator {
            Some(v) if v.due(round) || round == self.config.rounds => Some(v.evaluate(&self.student.weights())?),
            _ => None,
        };
        if let Some(v) = &validation {
            append_validation(&self.dir, round, self.data.seen(), &v.report)?;
            if self.progress.best_validation.is_none_or(|best| v.report.s_pw > best) {
                self.progress.best_validation = Some(v.report.s_pw);
                let mut best = Checkpoint::default();
                best.put("weights", self.student.weights().to_bytes());
                best.write(&self.checkpoints.best())?;
            }
        }
        self.progress.wall_seconds += started.elapsed().as_secs_f64();
        let steps = self.env.len() * self.config.steps_per_round;
        let per_episode = |count: f64| if flight.episodes > 0 { count / flight.episodes as f64 } else { f64::NAN };
        let summary = RoundSummary {
            round,
            teacher_share: flight.teacher_steps as f64 / steps as f64,
            samples_seen: self.data.seen(),
            dataset: self.data.len(),
            loss,
            episodes: flight.episodes,
            laps_per_episode: per_episode(flight.laps as f64),
            crash_rate: per_episode(flight.crashes as f64),
            fly_seconds,
            fit_seconds,
            validation: validation.as_ref().map(|v| (v.report.s_pw, v.report.success_rate)),
        };
        let eval = |f: &dyn Fn(&runtime::Validation) -> f64| validation.as_ref().map_or(f64::NAN, f);
        let values = [
            summary.loss,
            summary.teacher_share,
            summary.dataset as f64,
            summary.laps_per_episode,
            summary.crash_rate,
            eval(&|v| v.report.s_pw),
            eval(&|v| v.report.success_rate),
            eval(&|v| v.report.mean_lap.unwrap_or(f64::NAN)),
            eval(&|v| v.seconds),
        ];
        let row: Vec<(&str, f64)> = COLUMNS.iter().copied().zip(values).collect();
        self.metrics.write_columns(round, summary.samples_seen, self.progress.wall_seconds, &row)?;
        if round.is_multiple_of(self.config.checkpoint_every.max(1)) && round < self.config.rounds {
            self.checkpoint()?;
        }
        Ok(summary)
    }

    /// Flies every environment `steps_per_round` steps — each step by the teacher with
    /// probability β = decay^round, else by the student unless `takeover` hands it back to
    /// the teacher — offering every visited state with the teacher's label to the data set;
    /// then reports the round's rewards to the task controller and applies its switches.
    fn fly(&mut self) -> anyhow::Result<Flight> {
        let beta = self.config.teacher_decay.powi(self.progress.round.min(i32::MAX as u64) as i32);
        // Round 0 is the teacher's alone: the student's actions would not be used.
        let student = if beta < 1.0 { Some(ActingPolicy::from_blob(&self.student.weights())?) } else { None };
        let n = self.env.len();
        let dim = self.env.observation_dim();
        let mut rewards = vec![0.0f64; n];
        let mut flight = Flight::default();
        for _ in 0..self.config.steps_per_round {
            let labels = self.teacher.labels(&self.env);
            let student_actions = student.as_ref().map(|s| s.deterministic_actions(&self.env.observations, &self.env.images));
            self.student.observe(&self.env.observations);
            let mut actions = labels.clone();
            for i in 0..n {
                let state = &self.env.observations[i * dim..(i + 1) * dim];
                let rows = i * ACTION_DIM..(i + 1) * ACTION_DIM;
                self.data.offer(&self.env.envs()[i], state, &labels[rows.clone()], &mut self.progress.rng);
                let student_flies = student_actions.as_ref().is_some_and(|s| {
                    self.progress.rng.random::<f64>() >= beta
                        && self
                            .config
                            .takeover
                            .is_none_or(|t| s[rows.clone()].iter().zip(&labels[rows.clone()]).all(|(a, b)| (a - b).abs() <= t as f32))
                });
                match &student_actions {
                    Some(s) if student_flies => actions[rows.clone()].copy_from_slice(&s[rows]),
                    _ => flight.teacher_steps += 1,
                }
            }
            self.env.step(&actions);
            for (total, r) in rewards.iter_mut().zip(&self.env.rewards) {
                *total += f64::from(*r);
            }
            for f in &self.env.finished {
                self.teacher.episode_started(f.env, &self.env);
                flight.episodes += 1;
                flight.laps += u64::from(f.stats.laps);
                flight.crashes += usize::from(f.stats.crash.is_some());
            }
        }
        for (env, track) in self.tasks.report(ACTOR, self.progress.rollout, &rewards)? {
            self.env.set_track(env, track);
            self.teacher.episode_started(env, &self.env);
        }
        self.progress.rollout += 1;
        Ok(flight)
    }

    /// The round's regression steps on minibatches drawn from the whole data set; their mean
    /// loss (NaN when there are none).
    fn regress(&mut self) -> f64 {
        let batch = self.config.minibatch.min(self.data.len());
        let mut loss = 0.0;
        for _ in 0..self.config.updates_per_round {
            let rows = rand::seq::index::sample(&mut self.progress.rng, self.data.len(), batch).into_vec();
            loss += self.student.train_step(&self.data, &rows, self.config.learning_rate);
        }
        if self.config.updates_per_round > 0 { loss / self.config.updates_per_round as f64 } else { f64::NAN }
    }

    /// Distils until every round is done, `rounds` more are done, or `stop` rises, reporting
    /// each round to the run's `train.log`; then checkpoints, and returns where.
    pub fn run(&mut self, dir: &Path, rounds: Option<u64>, stop: &std::sync::atomic::AtomicBool) -> anyhow::Result<PathBuf> {
        let mut log = runtime::progress::ProgressLog::open(dir)?;
        let first = self.round();
        log.report(&format!("distilling in {} (from round {first})", dir.display()))?;
        while !self.finished() && !stop.load(std::sync::atomic::Ordering::SeqCst) && rounds.is_none_or(|n| self.round() - first < n) {
            let s = self.round_step()?;
            log.report(&progress_line(&s, self.config().rounds))?;
        }
        self.checkpoint()
    }

    /// Writes a periodic checkpoint of everything.
    #[allow(clippy::expect_used, reason = "environments and counters serialise")]
    pub fn checkpoint(&mut self) -> anyhow::Result<PathBuf> {
        let mut c = Checkpoint::default();
        match &self.teacher {
            Teacher::Policy(_, bytes) => c.put("teacher", bytes.clone()),
            Teacher::Pilot(pilots) => self.progress.pilots = pilots.iter().map(ReferencePilot::memory).collect(),
        }
        c.put("weights", self.student.weights().to_bytes());
        c.put("optimizer", self.student.optimizer_state());
        c.put("dataset", self.data.to_bytes());
        c.put("taskctl", self.tasks.read(TaskController::to_snapshot_bytes));
        self.progress.envs = self.env.envs().to_vec();
        c.put("distiller", serde_json::to_vec(&self.progress).expect("environments and counters serialise"));
        self.progress.envs.clear();
        self.progress.pilots.clear();
        Ok(self.checkpoints.save(&c, self.progress.round)?)
    }
}

/// The config of the distillation run in `dir`, its checkpoint directory, and the path and
/// contents of its newest checkpoint.
fn newest_checkpoint(dir: &Path) -> anyhow::Result<(DistillConfig, CheckpointDir, PathBuf, Checkpoint)> {
    let config = DistillConfig::read(&dir.join("config.toml"))?;
    let checkpoints = CheckpointDir::new(dir.join("checkpoints"), config.keep_checkpoints)?;
    let path = checkpoints.latest().with_context(|| format!("{} has no checkpoint to resume from", dir.display()))?;
    let checkpoint = Checkpoint::read(&path)?;
    Ok((config, checkpoints, path, checkpoint))
}

/// `env`, rendering the camera images when the student sees them.
fn with_images(env: VecEnv, config: &DistillConfig) -> VecEnv {
    match config.student {
        Agent::Vision => env.with_images(),
        Agent::State => env,
    }
}

/// The progress line of one round.
pub fn progress_line(s: &RoundSummary, rounds: u64) -> String {
    let validation =
        s.validation.map_or(String::new(), |(s_pw, success)| format!(" | validation S_pw {s_pw:.4}, success {:.0} %", 100.0 * success));
    let episodes = match s.episodes {
        0 => "no episode ended".to_string(),
        n => format!("{n} episodes: laps/ep {:.2}, crashed {:.0} %", s.laps_per_episode, 100.0 * s.crash_rate),
    };
    format!(
        "round {:>4}/{rounds} | {:>9} samples (kept {:>8}) | teacher {:>3.0} % | loss {:.4} | {episodes} | fly {:.1} s, fit {:.1} s{validation}",
        s.round,
        s.samples_seen,
        s.dataset,
        100.0 * s.teacher_share,
        s.loss,
        s.fly_seconds,
        s.fit_seconds,
    )
}
