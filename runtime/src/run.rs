//! A training run: its directory (the resolved config, checkpoints, `metrics.csv`, TensorBoard
//! events) and the bookkeeping every iteration adds to it, shared by the in-process trainer and
//! the learner process. The configuration itself is `crate::config`.

use std::path::{Path, PathBuf};

use policy::{Agent, WeightsBlob};
use rollout::RolloutChunk;
use serde::{Deserialize, Serialize};

use crate::config::{ResolvedRun, TrainConfig};
use crate::error::TrainError;
use crate::metrics::{MetricsRow, MetricsWriter};
use crate::progress::{Eta, IterationSummary};
use crate::validation::Validation;
use learner::checkpoint::{Checkpoint, CheckpointDir};
use learner::learner::IterationReport;

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
    resolved: ResolvedRun,
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
    /// Makes `dir` a new run's directory, refusing one that holds checkpoints, and writes the
    /// resolved config into it as `config.toml` — once: a file that already says the same is
    /// left as it is (the supervisor writes it before the learner process starts).
    pub fn prepare(resolved: &ResolvedRun, dir: &Path) -> Result<CheckpointDir, TrainError> {
        std::fs::create_dir_all(dir).map_err(|source| TrainError::Io { file: dir.to_path_buf(), source })?;
        let checkpoints = CheckpointDir::new(dir.join("checkpoints"), resolved.config().keep_checkpoints)?;
        if checkpoints.latest().is_some() {
            let message = "already holds checkpoints: resume it (--resume), or choose another run directory".into();
            return Err(TrainError::RunDirectory { dir: dir.to_path_buf(), message });
        }
        let (path, text) = (dir.join("config.toml"), resolved.to_toml());
        if std::fs::read_to_string(&path).ok().as_deref() != Some(text.as_str()) {
            durable::write_atomic(&path, text.as_bytes()).map_err(|source| TrainError::Io { file: path, source })?;
        }
        Ok(checkpoints)
    }

    /// Starts a new run in `dir` (which must not hold checkpoints already) with the resolved
    /// config written into it.
    pub fn create(resolved: ResolvedRun, dir: &Path) -> Result<Self, TrainError> {
        let checkpoints = Self::prepare(&resolved, dir)?;
        let metrics = MetricsWriter::open(dir).map_err(|source| TrainError::Io { file: dir.to_path_buf(), source })?;
        let progress = Progress { iteration: 0, wall_seconds: 0.0, best_return: None, best_validation: None };
        Ok(Self { resolved, dir: dir.to_path_buf(), checkpoints, metrics, progress, pending_validation_seconds: 0.0, eta: Eta::default() })
    }

    /// Opens the run in `dir` with its newest readable checkpoint: one that is cut off or
    /// corrupt (a disk fault, a copy gone wrong) is skipped with a warning naming it, and the
    /// one before it is used. Removes the temporary files of checkpoint writes cut off by a
    /// kill (the caller is the run's one writer).
    pub fn open(dir: &Path) -> Result<(Self, Checkpoint), TrainError> {
        let resolved = ResolvedRun::read(&dir.join("config.toml"))?;
        let checkpoints = CheckpointDir::new(dir.join("checkpoints"), resolved.config().keep_checkpoints)?;
        for stale in durable::remove_stale_temporaries(checkpoints.dir())
            .map_err(|source| TrainError::Io { file: checkpoints.dir().to_path_buf(), source })?
        {
            tracing::warn!("removed {}, left by a checkpoint write that was cut off", stale.display());
        }
        let candidates = checkpoints.periodic();
        if candidates.is_empty() {
            return Err(TrainError::RunDirectory { dir: dir.to_path_buf(), message: "has no checkpoint to resume from".into() });
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
            let message = format!("no checkpoint is readable: {}", skipped.join("; "));
            return Err(TrainError::RunDirectory { dir: dir.to_path_buf(), message });
        };
        if !skipped.is_empty() {
            tracing::warn!("resuming from iteration {} after skipping {} unreadable checkpoint(s)", progress.iteration, skipped.len());
        }
        let metrics = MetricsWriter::open(dir).map_err(|source| TrainError::Io { file: dir.to_path_buf(), source })?;
        Ok((
            Self { resolved, dir: dir.to_path_buf(), checkpoints, metrics, progress, pending_validation_seconds: 0.0, eta: Eta::default() },
            ckpt,
        ))
    }

    /// Opens the run in `dir` if it has a checkpoint, else starts it with `resolved`.
    pub fn open_or_create(resolved: ResolvedRun, dir: &Path) -> Result<(Self, Option<Checkpoint>), TrainError> {
        let has_checkpoint = CheckpointDir::new(dir.join("checkpoints"), resolved.config().keep_checkpoints)?.latest().is_some();
        if has_checkpoint {
            let (run, ckpt) = Self::open(dir)?;
            Ok((run, Some(ckpt)))
        } else {
            Ok((Self::create(resolved, dir)?, None))
        }
    }

    /// The run's configuration.
    pub fn config(&self) -> &TrainConfig {
        self.resolved.config()
    }

    /// The run's resolved configuration, with the learner it trains.
    pub fn resolved(&self) -> &ResolvedRun {
        &self.resolved
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
        let episodes: Vec<&rollout::EpisodeRecord> = chunks.iter().flat_map(|c| &c.episodes).collect();
        let mean = |f: &dyn Fn(&rollout::EpisodeRecord) -> f64| {
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
        let best = if self.config().eval.every > 0 {
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
        let every = self.config().eval.every;
        self.progress.iteration.is_multiple_of(self.config().checkpoint_every.max(1))
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
        let best = if self.config().eval.every > 0 {
            let keep = if policy.architecture.agent == Agent::Vision { 1 } else { self.config().eval.average };
            let kept = self.checkpoints.save_validated(&policy, self.progress.iteration, keep)?;
            let policies = kept.iter().map(|p| learner::checkpoint::read_policy(p)).collect::<Result<Vec<_>, _>>()?;
            policyfile::averaging::average(&policies)?
        } else {
            policy
        };
        let path = self.checkpoints.best();
        durable::write_atomic(&path, &best.to_bytes()).map_err(|source| TrainError::Io { file: path.clone(), source })
    }

    /// Estimated seconds to the end of the run after `env_steps`, from the smoothed training
    /// rate and the validations still due.
    pub fn eta_seconds(&self, env_steps: u64) -> f64 {
        let steps_left = self.config().total_env_steps.saturating_sub(env_steps);
        let every = self.config().eval.every;
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
