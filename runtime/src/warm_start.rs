//! `[warm_start]`: before PPO, the run's actor imitates the reference pilot by DAgger
//! (`distill` with a state-based student), and PPO starts from that student instead of a
//! random network — a policy that already flies half the tracks and has to get faster and
//! surer, rather than one that must first discover gates by crashing on 96 tracks at once. The
//! student's critic is fresh, so the first PPO iterations train the critic alone
//! (`critic_iterations`, which sets `ppo.critic_warmup_iterations`); after them PPO's loss
//! keeps an imitation term on the warm start's data set (`imitation_weight`, annealed to 0),
//! without which PPO drifts off the imitation faster than it improves on it.
//!
//! The imitation runs in `RUN/warm-start/` with its own checkpoints, metrics and progress
//! line; started again after an interruption, it resumes there. Its student is written to
//! `RUN/warm-start/student.bin` and becomes the run's `init_from`.

use std::path::{Path, PathBuf};
use std::sync::atomic::Ordering;

use anyhow::{Context, bail, ensure};
use learner::checkpoint::{Checkpoint, CheckpointDir};
use learner::distill::DistillDataset;
use learner::ppo::ImitationSet;
use policy::Agent;
use serde::{Deserialize, Serialize};
use taskctl::SwitchParams;

use crate::TrainConfig;
use crate::distill::{DistillConfig, PILOT_TEACHER};

/// The imitation phase of a run (`[warm_start]` in the run config); every field optional.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct WarmStart {
    /// The teacher: `pilot` (default) or a state-based policy file.
    pub teacher: PathBuf,
    /// DAgger rounds. Default 40.
    pub rounds: u64,
    /// Steps every environment flies per round. Default 100.
    pub steps_per_round: usize,
    /// β of round r is `teacher_decay`^r: the share of steps the teacher flies. Default 0.8.
    pub teacher_decay: f64,
    /// Regression steps per round. Default 200.
    pub updates_per_round: usize,
    /// Samples per regression step. Default 512.
    pub minibatch: usize,
    /// Adam's learning rate of the regression. Default 1e-3.
    pub learning_rate: f64,
    /// Rounds between track switches (adaptive, with the run's α). Default 5.
    pub switch_window: usize,
    /// Log standard deviation the student (and so PPO's exploration) starts with. Default −2
    /// (σ = 0.14): SPEC's −0.5 (σ = 0.61) shakes the imitation off every track — its first
    /// rollouts average 0 laps and a return of ~0 against 0.8 laps and ~60 at −2
    /// (docs/notebook/generalist-rejected.md, "Starting from the reference pilot").
    pub initial_log_std: f64,
    /// Weight of the imitation term in PPO's loss at the start of the run — the squared error
    /// between the policy's means and the teacher's labels on the warm start's data set,
    /// annealed linearly to 0 at the end (0: PPO alone). Default 10, chosen on validation
    /// (`experiments/warm-start.toml`: 0 lets PPO drift off the imitation, 1 holds it weakly).
    pub imitation_weight: f64,
    /// PPO iterations that then train the fresh critic alone (`ppo.critic_warmup_iterations`).
    /// Default 10.
    pub critic_iterations: u64,
}

impl Default for WarmStart {
    fn default() -> Self {
        Self {
            teacher: PILOT_TEACHER.into(),
            rounds: 40,
            steps_per_round: 100,
            teacher_decay: 0.8,
            updates_per_round: 200,
            minibatch: 512,
            learning_rate: 1e-3,
            switch_window: 5,
            initial_log_std: -2.0,
            imitation_weight: 10.0,
            critic_iterations: 10,
        }
    }
}

impl WarmStart {
    /// The distillation this warm start runs for `run`: the run's environments, tracks,
    /// generator, switching sensitivity, network widths and seed.
    pub fn distill_config(&self, run: &TrainConfig) -> anyhow::Result<DistillConfig> {
        ensure!(
            run.agent == Agent::State,
            "warm_start: imitation warm-starts state-based runs; distil a vision student with `dronerace distill`"
        );
        let profile = run.resolved_profile()?;
        let defaults = DistillConfig::defaults_for(Agent::State);
        Ok(DistillConfig {
            teacher: self.teacher.clone(),
            student: Agent::State,
            hidden: (self.teacher.as_os_str() == PILOT_TEACHER).then(|| profile.architecture.hidden.clone()),
            seed: run.seed,
            envs: profile.envs,
            steps_per_round: self.steps_per_round,
            rounds: self.rounds,
            teacher_decay: self.teacher_decay,
            takeover: None,
            updates_per_round: self.updates_per_round,
            minibatch: self.minibatch,
            learning_rate: self.learning_rate,
            initial_log_std: self.initial_log_std,
            init_from: None,
            tracks: run.tracks.clone(),
            generator: run.generator,
            switching: SwitchParams { window: self.switch_window, ..run.switching },
            env: run.env,
            // Each checkpoint holds the whole data set (~100 MB at the defaults): few, and one kept.
            checkpoint_every: 10,
            keep_checkpoints: 1,
            // One validation, of the finished student (how well the imitation flies), unless the
            // run validates nothing.
            eval: crate::EvalSettings { every: if run.eval.every == 0 { 0 } else { self.rounds.max(1) }, ..run.eval.clone() },
            ..defaults
        })
    }
}

/// Where a run's warm start lives.
pub fn warm_start_dir(run_dir: &Path) -> PathBuf {
    run_dir.join("warm-start")
}

/// Runs (or finishes) the warm start of a new run in `run_dir` when its config asks for one,
/// and points the config's `init_from` at the student. Nothing to do without `[warm_start]`.
#[allow(clippy::print_stderr, reason = "the command's own terminal output")]
pub fn prepare(config: &mut TrainConfig, run_dir: &Path) -> anyhow::Result<()> {
    let Some(warm_start) = &config.warm_start else { return Ok(()) };
    if let Some(path) = &config.init_from {
        bail!("init_from ({}) and [warm_start] both say where training starts: keep one", path.display());
    }
    let dir = warm_start_dir(run_dir);
    let student_path = dir.join("student.bin");
    if !student_path.exists() {
        let distill = warm_start.distill_config(config)?;
        let rounds = distill.rounds;
        let resume = CheckpointDir::new(dir.join("checkpoints"), distill.keep_checkpoints)?.latest().is_some();
        let stop = crate::signal::stop_flag()?;
        eprintln!("warm start: imitating {} for {rounds} rounds in {}", warm_start.teacher.display(), dir.display());
        let outcome = crate::distill::run(&dir, (!resume).then_some(distill), None, &stop)?;
        if !outcome.finished || stop.load(Ordering::SeqCst) {
            bail!("stopped during the warm start in {}: start the run again to continue it", dir.display());
        }
        racetracks::files::write_atomic(&student_path, &outcome.student.to_bytes())
            .with_context(|| format!("writing {}", student_path.display()))?;
    }
    config.init_from = Some(student_path);
    Ok(())
}

/// The warm start's labelled states for PPO's imitation term, when the run's `[warm_start]`
/// asks for the term: the data set of the warm start's newest checkpoint in `run_dir`.
pub fn imitation_set(config: &TrainConfig, run_dir: &Path) -> anyhow::Result<Option<(ImitationSet, f64)>> {
    let Some(warm_start) = config.warm_start.as_ref().filter(|w| w.imitation_weight > 0.0) else { return Ok(None) };
    let dir = warm_start_dir(run_dir).join("checkpoints");
    let path = CheckpointDir::new(dir.clone(), 1)?
        .latest()
        .with_context(|| format!("{}: no warm-start checkpoint holds the data set the imitation term needs", dir.display()))?;
    let checkpoint = Checkpoint::read(&path)?;
    let data = DistillDataset::from_bytes(checkpoint.get("dataset")?).with_context(|| format!("{}", path.display()))?;
    let rows: Vec<usize> = (0..data.len()).collect();
    let set = ImitationSet::new(data.states(&rows), data.labels(&rows), data.state_dim(), sim::ACTION_DIM)
        .map_err(|e| anyhow::anyhow!("{}: {e}", path.display()))?;
    Ok(Some((set, warm_start.imitation_weight)))
}
