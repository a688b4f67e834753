//! Experiments as files: a base run config plus named variants (each a set of config
//! overrides) × seeds. Every run trains in its own run directory `<out>/<variant>/seed-<s>/`;
//! when its budget is spent, its final policy and its `best.bin` (the average of its last
//! validated policies) fly the test set and `test.json` marks the run done. Running the file
//! again skips done runs and resumes interrupted ones from their newest checkpoint, so a grid
//! can outlive a sitting.
//!
//! ```toml
//! description = "observation frame"
//! seeds = [0, 1]
//! [base]                      # any run-config fields (TrainConfig)
//! total_env_steps = 30_000_000
//! [[variant]]
//! name = "world"
//! [[variant]]
//! name = "heading"
//! set = { env.observation.frame = "heading" }
//! ```

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};

use policy::{Policy, PolicyController};
use serde::{Deserialize, Serialize};
use sim::eval::{EvalConfig, EvalReport, OutcomeCounts, evaluate};

use crate::config::TrainConfig;
use crate::error::TrainError;
use crate::overrides::merge;
use crate::progress::IterationSummary;
use crate::run_lock::{LockError, RunLock};
use crate::trainer::Trainer;
use learner::checkpoint::CheckpointDir;

/// One variant: a name and the overrides that make it.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Variant {
    /// Name (its runs live in `<out>/<name>/`).
    pub name: String,
    /// Run-config overrides, merged into `base` key by key.
    #[serde(default)]
    pub set: toml::Table,
}

/// How the finished runs are tested (SPEC §9).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct TestSettings {
    /// Seed of the test set's generated tracks. Default 9,000,000.
    pub track_seed: u64,
    /// Deployments per track. Default 25.
    pub runs: usize,
    /// Steps per deployment. Default 1000.
    pub steps: u32,
    /// Fresh validation tracks `best.bin` also flies, 10 deployments each: the score variants
    /// are chosen by. They are the validation range's tracks after those the run validated on
    /// while training, so no checkpoint was kept for them. Tracks are flown nearly all or
    /// nothing, so at ~70 % success a score over n of them has a standard error of ~46/√n points:
    /// ~7 for the test set's 40, ~4.6 for training-time validation's 100, ~2.6 for 300 — below the
    /// 3–5 points that separate one seed of the defaults from another. Default 300; 0 skips it.
    pub validation_tracks: usize,
}

impl Default for TestSettings {
    fn default() -> Self {
        Self { track_seed: racetracks::track_sets::TEST_SEED, runs: 25, steps: 1000, validation_tracks: 300 }
    }
}

/// Deployments per track of `best.bin`'s fresh validation ([`TestSettings::validation_tracks`]).
const FRESH_VALIDATION_RUNS: usize = 10;

/// An experiment file.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Experiment {
    /// What the experiment asks.
    #[serde(default)]
    pub description: String,
    /// Seeds every variant runs with.
    pub seeds: Vec<u64>,
    /// Run-config fields shared by every variant.
    #[serde(default)]
    pub base: toml::Table,
    /// The variants, in the order the report lists them.
    #[serde(rename = "variant")]
    pub variants: Vec<Variant>,
    /// Test-set evaluation of the finished runs.
    #[serde(default)]
    pub test: TestSettings,
    /// Run the variants one after another for each seed, each starting from the policy the
    /// previous one ended with: a sequential curriculum (thesis §3.4.1). Default false.
    #[serde(default)]
    pub sequential: bool,
}

/// Why an experiment cannot run or be reported.
#[derive(Debug, thiserror::Error)]
pub enum ExperimentError {
    /// The file is unreadable or invalid; the message names the file and the field.
    #[error("{0}")]
    Invalid(String),
    /// Training one of the runs failed.
    #[error("{run}: {source}")]
    Run {
        /// The run directory.
        run: String,
        /// What failed (boxed: a training error is large, and this one is rare).
        source: Box<TrainError>,
    },
    /// Reading or writing a result file.
    #[error("{0}")]
    Io(String),
}

impl Experiment {
    /// Reads and checks an experiment file: every variant's config must resolve.
    pub fn read(path: &Path) -> Result<Self, ExperimentError> {
        let text = durable::read_text_limited(path, durable::MAX_TEXT_FILE_BYTES)
            .map_err(|e| ExperimentError::Invalid(format!("{}: {e}", path.display())))?;
        let experiment: Self = toml::from_str(&text).map_err(|e| ExperimentError::Invalid(format!("{}: {e}", path.display())))?;
        experiment.check().map_err(|e| ExperimentError::Invalid(format!("{}: {e}", path.display())))?;
        Ok(experiment)
    }

    fn check(&self) -> Result<(), ExperimentError> {
        let invalid = |message: String| Err(ExperimentError::Invalid(message));
        if self.seeds.is_empty() || self.variants.is_empty() {
            return invalid("name at least one seed and one [[variant]]".into());
        }
        let mut names = std::collections::BTreeSet::new();
        for v in &self.variants {
            let safe = !v.name.is_empty() && v.name.chars().all(|c| c.is_ascii_alphanumeric() || c == '-' || c == '_');
            if !safe {
                return invalid(format!("variant name {:?}: use letters, digits, '-' and '_'", v.name));
            }
            if !names.insert(&v.name) {
                return invalid(format!("variant name {:?} appears twice", v.name));
            }
            self.config(v, self.seeds[0])?;
        }
        Ok(())
    }

    /// Narrows the experiment to the named variants and seeds (empty: all of them), so one
    /// sitting can run part of a grid; the rest stays in the file for a later run. Names and
    /// seeds the file does not have are refused, as is a variant subset of a sequential
    /// experiment (its stages start from one another).
    pub fn select(&mut self, variants: &[String], seeds: &[u64]) -> Result<(), ExperimentError> {
        if let Some(name) = variants.iter().find(|n| !self.variants.iter().any(|v| &v.name == *n)) {
            let known: Vec<&str> = self.variants.iter().map(|v| v.name.as_str()).collect();
            return Err(ExperimentError::Invalid(format!("no variant {name:?} (the file has {})", known.join(", "))));
        }
        if let Some(seed) = seeds.iter().find(|s| !self.seeds.contains(s)) {
            return Err(ExperimentError::Invalid(format!("no seed {seed} (the file has {:?})", self.seeds)));
        }
        if self.sequential && !variants.is_empty() {
            return Err(ExperimentError::Invalid("a sequential experiment runs its stages in order: select seeds only".into()));
        }
        if !variants.is_empty() {
            self.variants.retain(|v| variants.contains(&v.name));
        }
        if !seeds.is_empty() {
            self.seeds.retain(|s| seeds.contains(s));
        }
        Ok(())
    }

    /// The run config of `variant` with `seed`: the defaults, then `base`, then the variant's
    /// overrides. Unknown keys are refused, named with the variant.
    pub fn config(&self, variant: &Variant, seed: u64) -> Result<TrainConfig, ExperimentError> {
        let invalid = |e: String| ExperimentError::Invalid(format!("variant {:?}: {e}", variant.name));
        let mut table = self.base.clone();
        merge(&mut table, &variant.set);
        table.insert("seed".into(), toml::Value::Integer(seed as i64));
        table.insert("name".into(), toml::Value::String(format!("{}-seed-{seed}", variant.name)));
        // Through text, so that toml's error shows the offending line and key.
        let text = toml::to_string(&table).map_err(|e| invalid(e.to_string()))?;
        let config = TrainConfig::from_toml(&text).map_err(|e| invalid(e.to_string()))?;
        config.clone().resolve().map_err(|e| invalid(e.to_string()))?;
        Ok(config)
    }

    /// The run directory of `variant` with `seed` under `out`.
    pub fn run_dir(out: &Path, variant: &str, seed: u64) -> PathBuf {
        out.join(variant).join(format!("seed-{seed}"))
    }
}

/// The test-set results of one finished run (`test.json`).
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct RunResult {
    /// Variant.
    pub variant: String,
    /// Seed.
    pub seed: u64,
    /// Environment steps trained.
    pub env_steps: u64,
    /// Iterations trained.
    pub iterations: u64,
    /// Wall seconds of training (validation included, test evaluation not).
    pub wall_seconds: f64,
    /// Highest validation S_pw seen (the thesis' "max S_pw").
    pub best_validation_s_pw: Option<f64>,
    /// Policy version in `best.bin` (the newest of those it averages).
    pub best_version: u64,
    /// The final policy on the test set, every deployment included.
    pub final_policy: EvalReport,
    /// `best.bin` on the test set, every deployment included.
    pub best_policy: EvalReport,
    /// `best.bin` on [`TestSettings::validation_tracks`] fresh validation tracks (none when
    /// switched off, or in results written before the change of 2026-12-05, whose `final_validation` flew
    /// the final policy on the run's own validation tracks).
    #[serde(default)]
    pub fresh_validation: Option<EvalReport>,
}

/// What one call of [`run_experiment`] did.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct RunLog {
    /// Runs already done before this call.
    pub skipped: Vec<PathBuf>,
    /// Runs continued from a checkpoint.
    pub resumed: Vec<PathBuf>,
    /// Runs started from scratch.
    pub started: Vec<PathBuf>,
    /// Runs finished (and tested) in this call.
    pub finished: Vec<PathBuf>,
    /// Runs left alone because another runner holds them ([`RunLock`]).
    pub busy: Vec<PathBuf>,
    /// True when `stop` ended the call before every run was done.
    pub interrupted: bool,
}

/// Runs every seed × variant of `experiment` under `out` (seed-major, so an interrupted grid
/// has compared every variant on the first seeds), until all are done or
/// `stop` is raised (then the current run checkpoints and the call returns). `on_iteration`
/// sees every iteration's summary (for a progress line). Each run is claimed with a
/// [`RunLock`] while it trains, so runners started on the same `out` split the grid; a
/// sequential experiment's later stages wait for a runner that reaches them after the earlier
/// ones are done.
pub fn run_experiment(
    experiment: &Experiment,
    out: &Path,
    stop: &AtomicBool,
    on_iteration: &mut dyn FnMut(&Path, &IterationSummary),
) -> Result<RunLog, ExperimentError> {
    let mut log = RunLog::default();
    for &seed in &experiment.seeds {
        for (stage, variant) in experiment.variants.iter().enumerate() {
            let dir = Experiment::run_dir(out, &variant.name, seed);
            if dir.join("test.json").exists() {
                log.skipped.push(dir);
                continue;
            }
            if stop.load(Ordering::SeqCst) {
                log.interrupted = true;
                return Ok(log);
            }
            if experiment.sequential
                && stage > 0
                && !Experiment::run_dir(out, &experiment.variants[stage - 1].name, seed).join("test.json").exists()
            {
                // The previous stage is another runner's and not done: so is the rest of this seed.
                log.busy.push(dir);
                break;
            }
            std::fs::create_dir_all(&dir).map_err(|e| ExperimentError::Io(format!("{}: {e}", dir.display())))?;
            let _claim = match RunLock::acquire(&dir) {
                Ok(claim) => claim,
                Err(LockError::Held { .. }) => {
                    log.busy.push(dir);
                    if experiment.sequential {
                        break;
                    }
                    continue;
                }
                Err(e) => return Err(ExperimentError::Io(e.to_string())),
            };
            if dir.join("test.json").exists() {
                // Finished by another runner between the first look and the claim.
                log.skipped.push(dir);
                continue;
            }
            let mut config = experiment.config(variant, seed)?;
            if experiment.sequential && stage > 0 {
                // The previous stage is done (stages run in order): start from where it ended.
                let previous = Experiment::run_dir(out, &experiment.variants[stage - 1].name, seed);
                let checkpoints = CheckpointDir::new(previous.join("checkpoints"), config.keep_checkpoints)
                    .map_err(|e| ExperimentError::Run { run: previous.display().to_string(), source: Box::new(e.into()) })?;
                config.init_from = checkpoints.latest();
            }
            // The validation range's tracks the run reads while training; the fresh ones follow.
            let validated = config.eval.range_tracks();
            let failed = |source: TrainError| ExperimentError::Run { run: dir.display().to_string(), source: Box::new(source) };
            let has_checkpoint =
                CheckpointDir::new(dir.join("checkpoints"), config.keep_checkpoints).map_err(|e| failed(e.into()))?.latest().is_some();
            let mut trainer = if has_checkpoint {
                log.resumed.push(dir.clone());
                Trainer::resume(&dir).map_err(failed)?
            } else {
                log.started.push(dir.clone());
                Trainer::start(config.resolve().map_err(|e| failed(e.into()))?, &dir).map_err(failed)?
            };
            while !trainer.finished() {
                if stop.load(Ordering::SeqCst) {
                    trainer.checkpoint().map_err(failed)?;
                    log.interrupted = true;
                    return Ok(log);
                }
                let summary = trainer.iteration_step().map_err(failed)?;
                on_iteration(&dir, &summary);
            }
            trainer.checkpoint().map_err(failed)?;
            let result = test_run(&trainer, &variant.name, seed, &experiment.test, validated).map_err(failed)?;
            let json = serde_json::to_vec_pretty(&result).map_err(|e| ExperimentError::Io(e.to_string()))?;
            durable::write_atomic(&dir.join("test.json"), &json).map_err(|e| ExperimentError::Io(format!("{}: {e}", dir.display())))?;
            log.finished.push(dir);
        }
    }
    Ok(log)
}

/// Flies the final policy and `best.bin` of a finished run on the test set, and `best.bin` on
/// the validation range's tracks after the first `validated` (those the run validated on).
fn test_run(trainer: &Trainer, variant: &str, seed: u64, test: &TestSettings, validated: usize) -> Result<RunResult, TrainError> {
    let tracks: Vec<Arc<sim::Track>> = racetracks::test_set(test.track_seed)?.into_iter().map(Arc::new).collect();
    let config = EvalConfig { runs: test.runs, steps: test.steps, ..EvalConfig::default() };
    let fly_on =
        |tracks: &[Arc<sim::Track>], config: &EvalConfig, blob: &policy::WeightsBlob, name: &str| -> Result<EvalReport, TrainError> {
            let policy = Arc::new(Policy::from_blob(blob)?);
            // Deployments stay in: where each one ended is what failure analyses read
            // (docs/python/crash_offsets.py), and re-flying a run's policies costs minutes.
            Ok(evaluate(name, tracks, &|| Box::new(PolicyController::new(policy.clone())), config))
        };
    let fly = |blob: &policy::WeightsBlob, name: &str| fly_on(&tracks, &config, blob, name);
    let final_blob = trainer.learner().weights();
    let best_path = trainer.dir().join("checkpoints").join("best.bin");
    let best_blob = if best_path.exists() { learner::checkpoint::read_policy(&best_path)? } else { final_blob.clone() };
    Ok(RunResult {
        variant: variant.to_owned(),
        seed,
        env_steps: trainer.learner().env_steps(),
        iterations: trainer.iteration(),
        wall_seconds: trainer.wall_seconds(),
        best_validation_s_pw: trainer.best_validation(),
        best_version: best_blob.version,
        final_policy: fly(&final_blob, "final")?,
        best_policy: fly(&best_blob, "best")?,
        fresh_validation: if test.validation_tracks == 0 {
            None
        } else {
            let tracks = racetracks::validation_tracks(validated, test.validation_tracks)?;
            let config = EvalConfig { runs: FRESH_VALIDATION_RUNS, steps: test.steps, ..EvalConfig::default() };
            Some(fly_on(&tracks.into_iter().map(Arc::new).collect::<Vec<_>>(), &config, &best_blob, "best")?)
        },
    })
}

/// Success on one validation track against environment steps since the first stage.
#[derive(Clone, Debug, PartialEq)]
pub struct TrackCurve {
    /// Track name.
    pub track: String,
    /// `(env steps since the first stage, success rate)`, in order.
    pub points: Vec<(u64, f64)>,
}

/// Per-track validation success of a sequential experiment's stages for `seed`, the stages laid
/// end to end; also the env steps at which each later stage began.
pub fn sequential_track_curves(experiment: &Experiment, out: &Path, seed: u64) -> Result<(Vec<TrackCurve>, Vec<u64>), ExperimentError> {
    let mut curves: Vec<TrackCurve> = Vec::new();
    let mut boundaries = Vec::new();
    let mut offset = 0u64;
    for (stage, variant) in experiment.variants.iter().enumerate() {
        let run = Experiment::run_dir(out, &variant.name, seed);
        let path = run.join("validation.csv");
        let Ok(text) = std::fs::read_to_string(&path) else { break };
        if stage > 0 {
            boundaries.push(offset);
        }
        // A resumed run repeats rows after its last checkpoint: the later row wins.
        let mut rows: std::collections::BTreeMap<(String, u64), f64> = Default::default();
        let mut last_steps = 0;
        for line in text.lines().skip(1) {
            let f: Vec<&str> = line.split(',').collect();
            let (Some(steps), Some(track), Some(success)) = (f.get(1), f.get(2), f.get(3)) else { continue };
            let (Ok(steps), Ok(success)) = (steps.parse::<u64>(), success.parse::<f64>()) else {
                return Err(ExperimentError::Io(format!("{}: malformed row {line:?}", path.display())));
            };
            last_steps = last_steps.max(steps);
            rows.insert((track.to_string(), steps), success);
        }
        for ((track, steps), success) in rows {
            let at = offset + steps;
            match curves.iter_mut().find(|c| c.track == track) {
                Some(c) => c.points.push((at, success)),
                None => curves.push(TrackCurve { track, points: vec![(at, success)] }),
            }
        }
        // The stage ends where its training did, which is past its last validation unless its
        // length is a multiple of the validation interval.
        offset += last_steps.max(trained_env_steps(&run.join("metrics.csv")));
    }
    for c in &mut curves {
        c.points.sort_by_key(|p| p.0);
    }
    Ok((curves, boundaries))
}

/// One point of a validation curve.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CurvePoint {
    /// Environment steps at the evaluation.
    pub env_steps: u64,
    /// Validation S_pw.
    pub s_pw: f64,
}

/// Everything the report shows of one variant.
#[derive(Clone, Debug)]
pub struct VariantSummary {
    /// Variant name.
    pub name: String,
    /// Finished runs' results, by seed.
    pub results: Vec<RunResult>,
    /// Validation curve of every run that has one (finished or not), by seed.
    pub curves: Vec<(u64, Vec<CurvePoint>)>,
    /// Task switches each run with a metrics file made so far, by seed.
    pub switches: Vec<(u64, u64)>,
    /// Runs not finished yet.
    pub unfinished: Vec<u64>,
}

/// Reads every run of `experiment` under `out`.
pub fn summarise(experiment: &Experiment, out: &Path) -> Result<Vec<VariantSummary>, ExperimentError> {
    let mut summaries = Vec::new();
    for variant in &experiment.variants {
        let mut summary = VariantSummary {
            name: variant.name.clone(),
            results: Vec::new(),
            curves: Vec::new(),
            switches: Vec::new(),
            unfinished: Vec::new(),
        };
        for &seed in &experiment.seeds {
            let dir = Experiment::run_dir(out, &variant.name, seed);
            let curve = validation_curve(&dir.join("metrics.csv"))?;
            if !curve.is_empty() {
                summary.curves.push((seed, curve));
            }
            if let Some(switches) = column_max(&dir.join("metrics.csv"), "tasks/switches") {
                summary.switches.push((seed, switches));
            }
            let path = dir.join("test.json");
            match std::fs::read(&path) {
                Ok(bytes) => {
                    let invalid = |e: serde_json::Error| ExperimentError::Io(format!("{}: {e}", path.display()));
                    let mut result: serde_json::Value = serde_json::from_slice(&bytes).map_err(invalid)?;
                    crate::overrides::retire_in_results(&mut result);
                    summary.results.push(serde_json::from_value(result).map_err(invalid)?);
                }
                Err(_) => summary.unfinished.push(seed),
            }
        }
        summaries.push(summary);
    }
    Ok(summaries)
}

/// A metrics file's text and the index of each of `names` in its header; `None` without the
/// file or with a column missing.
fn metrics_columns<const N: usize>(metrics: &Path, names: [&str; N]) -> Option<(String, [usize; N])> {
    let text = std::fs::read_to_string(metrics).ok()?;
    let header: Vec<&str> = text.lines().next().unwrap_or_default().split(',').collect();
    let mut columns = [0; N];
    for (column, name) in columns.iter_mut().zip(names) {
        *column = header.iter().position(|h| *h == name)?;
    }
    Some((text, columns))
}

/// The most env steps any row of a metrics file records (0 without the file or the column).
fn trained_env_steps(metrics: &Path) -> u64 {
    column_max(metrics, "env_steps").unwrap_or(0)
}

/// The largest whole number in a metrics file's column; `None` without the file, the column or
/// a row.
fn column_max(metrics: &Path, name: &str) -> Option<u64> {
    let (text, [column]) = metrics_columns(metrics, [name])?;
    text.lines().skip(1).filter_map(|line| line.split(',').nth(column)?.parse::<u64>().ok()).max()
}

/// Env steps at which a validation curve first reaches half its maximum: the thesis' "time to
/// 50 % of max" (Table 3.2), in samples rather than hours so machines compare; `None` for an
/// empty curve or one that never rises above 0.
pub fn steps_to_half_max(curve: &[CurvePoint]) -> Option<u64> {
    let max = curve.iter().map(|p| p.s_pw).fold(f64::NEG_INFINITY, f64::max);
    (max > 0.0).then(|| curve.iter().find(|p| p.s_pw >= 0.5 * max).map(|p| p.env_steps)).flatten()
}

/// `(env_steps, eval/S_pw)` of every evaluated iteration in a metrics file (empty if none).
/// A resumed run repeats iterations after its last checkpoint; the later row wins.
pub fn validation_curve(metrics: &Path) -> Result<Vec<CurvePoint>, ExperimentError> {
    let Some((text, [steps, s_pw])) = metrics_columns(metrics, ["env_steps", "eval/S_pw"]) else { return Ok(Vec::new()) };
    let mut points: std::collections::BTreeMap<u64, f64> = Default::default();
    for line in text.lines().skip(1) {
        let cells: Vec<&str> = line.split(',').collect();
        let (Some(x), Some(y)) = (cells.get(steps), cells.get(s_pw)) else { continue };
        if let (Ok(x), Ok(y)) = (x.parse::<u64>(), y.parse::<f64>()) {
            points.insert(x, y);
        }
    }
    Ok(points.into_iter().map(|(env_steps, s_pw)| CurvePoint { env_steps, s_pw }).collect())
}

/// Mean and sample standard deviation (0 for one value).
fn mean_std(values: &[f64]) -> (f64, f64) {
    let n = values.len() as f64;
    let mean = values.iter().sum::<f64>() / n;
    let var = if values.len() > 1 { values.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / (n - 1.0) } else { 0.0 };
    (mean, var.sqrt())
}

/// A column cell: mean ± sample standard deviation over seeds, then each seed's value (as a
/// percentage with `percent`); one seed's value alone, "–" for none.
fn spread(values: Vec<f64>, percent: bool) -> String {
    if values.is_empty() {
        return "–".into();
    }
    let scale = if percent { 100.0 } else { 1.0 };
    let (m, s) = mean_std(&values);
    let each: Vec<String> = values.iter().map(|v| if percent { format!("{:.0}", v * scale) } else { format!("{v:.4}") }).collect();
    // One seed has no spread to show: "± 0" would claim one.
    if values.len() == 1 {
        return if percent { format!("{} %", each[0]) } else { each[0].clone() };
    }
    if percent {
        format!("{:.0} ± {:.0} % ({})", m * scale, s * scale, each.join(", "))
    } else {
        format!("{m:.4} ± {s:.4} ({})", each.join(", "))
    }
}

/// `report.md`: per variant, the seeds, budget, wall time, best validation S_pw and the test
/// set's success and S_pw (mean ± sample standard deviation over seeds, then each seed's), with
/// the crash breakdown of the chosen (`best.bin`) policies.
pub fn markdown_report(experiment: &Experiment, summaries: &[VariantSummary]) -> String {
    let mut out = format!("# Experiment report\n\n{}\n\n", experiment.description.trim());
    out.push_str(&format!(
        "Seeds {:?}; test set: library + generated from seed {}, {} deployments × {} steps per track. \
         `best` is the run's `best.bin` (runs before 2026-12-05: the checkpoint with the highest validation S_pw; since: \
         the weight average of the last validated policies); mean ± sample standard deviation over seeds, \
         then each seed's value. `best` also flies {} fresh validation tracks × {FRESH_VALIDATION_RUNS} deployments, tracks of \
         the validation range after those the run validated on (\"best, fresh validation\"): choose variants by that, not \
         by the test set. Runs tested before 2026-12-05's change have none (they flew their final policy on their own \
         validation tracks).\n\n",
        experiment.seeds, experiment.test.track_seed, experiment.test.runs, experiment.test.steps, experiment.test.validation_tracks
    ));
    out.push_str("| variant | runs done | env steps | wall time (min) | best validation S_pw | test success (best) | test S_pw (best) | test success (final) | test S_pw (final) | success (best, fresh validation) | S_pw (best, fresh validation) |\n");
    out.push_str("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|\n");
    for v in summaries {
        let r = &v.results;
        let steps: Vec<String> = r.iter().map(|x| format!("{:.1}M", x.env_steps as f64 / 1e6)).collect();
        let minutes: Vec<String> = r.iter().map(|x| format!("{:.0}", x.wall_seconds / 60.0)).collect();
        let validation: Vec<&EvalReport> = r.iter().filter_map(|x| x.fresh_validation.as_ref()).collect();
        out.push_str(&format!(
            "| {} | {} of {} | {} | {} | {} | {} | {} | {} | {} | {} | {} |\n",
            v.name,
            r.len(),
            r.len() + v.unfinished.len(),
            if steps.is_empty() { "–".into() } else { steps.join(", ") },
            if minutes.is_empty() { "–".into() } else { minutes.join(", ") },
            spread(r.iter().filter_map(|x| x.best_validation_s_pw).collect(), false),
            spread(r.iter().map(|x| x.best_policy.success_rate).collect(), true),
            spread(r.iter().map(|x| x.best_policy.s_pw).collect(), false),
            spread(r.iter().map(|x| x.final_policy.success_rate).collect(), true),
            spread(r.iter().map(|x| x.final_policy.s_pw).collect(), false),
            spread(validation.iter().map(|x| x.success_rate).collect(), true),
            spread(validation.iter().map(|x| x.s_pw).collect(), false),
        ));
    }
    out.push_str(
        "\n## The thesis' columns (Table 3.2)\n\nPer run: the maximum validation S_pw, the env steps at which validation first \
         reached half of it, and the task switches made; mean ± sample standard deviation over the runs with a curve, then each \
         run's.\n\n| variant | runs | max validation S_pw | env steps to 50 % of max (M) | switches |\n|---|---:|---:|---:|---:|\n",
    );
    for v in summaries {
        let max: Vec<f64> = v.curves.iter().map(|(_, c)| c.iter().map(|p| p.s_pw).fold(f64::NEG_INFINITY, f64::max)).collect();
        let half: Vec<f64> = v.curves.iter().filter_map(|(_, c)| steps_to_half_max(c)).map(|s| s as f64 / 1e6).collect();
        let switches: Vec<f64> = v.switches.iter().map(|&(_, s)| s as f64).collect();
        let whole = |values: Vec<f64>| {
            if values.len() > 1 {
                let (m, s) = mean_std(&values);
                let each: Vec<String> = values.iter().map(|v| format!("{v:.1}")).collect();
                format!("{m:.1} ± {s:.1} ({})", each.join(", "))
            } else {
                values.first().map_or_else(|| "–".into(), |v| format!("{v:.1}"))
            }
        };
        out.push_str(&format!("| {} | {} | {} | {} | {} |\n", v.name, v.curves.len(), spread(max, false), whole(half), whole(switches)));
    }
    out.push_str("\n## How the test deployments of `best` ended (all seeds together)\n\n");
    out.push_str("| variant | deployments | success | ground | ceiling | wall | gate frame | of it not the target | no lap | mean lap (s) |\n|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|\n");
    for v in summaries {
        let mut total = OutcomeCounts::default();
        for x in &v.results {
            total.merge(&x.best_policy.outcomes);
        }
        let pct = |n: usize| format!("{:.0} %", 100.0 * total.fraction(n));
        let laps: Vec<f64> = v.results.iter().filter_map(|x| x.best_policy.mean_lap).collect();
        out.push_str(&format!(
            "| {} | {} | {} | {} | {} | {} | {} | {} | {} | {} |\n",
            v.name,
            total.deployments,
            pct(total.success),
            pct(total.ground),
            pct(total.ceiling),
            pct(total.wall),
            pct(total.gate_total()),
            pct(total.gate_not_target),
            pct(total.no_lap),
            if laps.is_empty() { "–".into() } else { format!("{:.2}", mean_std(&laps).0) }
        ));
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    const FILE: &str = r#"
        description = "frames"
        seeds = [0, 1]
        [base]
        total_env_steps = 1000
        [base.ppo]
        n_epochs = 3
        mirror_coef = 0.0   # the body frame has no mirror
        [[variant]]
        name = "world"
        [[variant]]
        name = "body"
        set = { env.observation.frame = "body", ppo.batch_size = 64 }
    "#;

    #[test]
    fn report_cells_show_a_spread_only_over_several_seeds() {
        assert_eq!(spread(vec![0.6, 0.34, 0.46], true), "47 ± 13 % (60, 34, 46)");
        assert_eq!(spread(vec![0.1042, 0.0529], false), "0.0786 ± 0.0363 (0.1042, 0.0529)");
        assert_eq!(spread(vec![0.586], true), "59 %");
        assert_eq!(spread(vec![0.0933], false), "0.0933");
        assert_eq!(spread(vec![], true), "–");
    }

    #[test]
    fn a_selection_keeps_the_named_variants_and_seeds_and_refuses_unknown_ones() {
        let mut e: Experiment = toml::from_str(FILE).unwrap();
        e.select(&["body".into()], &[1]).unwrap();
        assert_eq!(e.variants.iter().map(|v| v.name.as_str()).collect::<Vec<_>>(), ["body"]);
        assert_eq!(e.seeds, [1]);
        let mut e: Experiment = toml::from_str(FILE).unwrap();
        let err = e.select(&["heading".into()], &[]).unwrap_err().to_string();
        assert!(err.contains("\"heading\"") && err.contains("world, body"), "{err}");
        let err = e.select(&[], &[7]).unwrap_err().to_string();
        assert!(err.contains("no seed 7"), "{err}");
        e.sequential = true;
        assert!(e.select(&["world".into()], &[]).is_err());
        e.select(&[], &[0]).unwrap();
        assert_eq!((e.variants.len(), e.seeds.as_slice()), (2, [0].as_slice()));
    }

    #[test]
    fn variants_merge_over_the_base_key_by_key() {
        let e: Experiment = toml::from_str(FILE).unwrap();
        e.check().unwrap();
        let world = e.config(&e.variants[0], 1).unwrap();
        let body = e.config(&e.variants[1], 0).unwrap();
        assert_eq!((world.seed, world.total_env_steps, world.ppo.unwrap().n_epochs), (1, 1000, 3));
        assert_eq!(world.env.observation.frame, sim::EnvConfig::default().observation.frame, "no override: the default");
        assert_eq!(body.env.observation.frame, sim::ObservationFrame::Body);
        // The nested override kept the base's sibling key.
        assert_eq!((body.ppo.unwrap().n_epochs, body.ppo.unwrap().batch_size), (3, 64));
        assert_eq!(body.name, "body-seed-0");
    }

    #[test]
    fn unknown_override_keys_are_refused_by_name() {
        let mut e: Experiment = toml::from_str(FILE).unwrap();
        e.variants[1].set = toml::from_str("env = { observation_fram = \"heading\" }").unwrap();
        let error = e.check().unwrap_err().to_string();
        assert!(error.contains("observation_fram") && error.contains("body"), "{error}");
        e.variants[1].set = toml::from_str("learning_rate = 0.1").unwrap();
        let error = e.check().unwrap_err().to_string();
        assert!(error.contains("learning_rate"), "{error}");
        e.variants[1].set = toml::from_str("profile = \"gpu\"").unwrap();
        assert!(e.check().unwrap_err().to_string().contains("gpu"));
    }

    #[test]
    fn a_later_stage_starts_where_the_earlier_one_stopped_training_not_where_it_last_validated() {
        let out = tempfile::tempdir().unwrap();
        let e: Experiment = toml::from_str("seeds = [0]\nsequential = true\n[[variant]]\nname = \"a\"\n[[variant]]\nname = \"b\"").unwrap();
        for (stage, last_iteration) in [("a", "3,300"), ("b", "2,200")] {
            let run = Experiment::run_dir(out.path(), stage, 0);
            std::fs::create_dir_all(&run).unwrap();
            // Validated at 200 steps, trained on to the last row's.
            std::fs::write(run.join("validation.csv"), "iteration,env_steps,track,success\n2,200,Figure8,1\n").unwrap();
            std::fs::write(run.join("metrics.csv"), format!("iteration,env_steps,eval/S_pw\n2,200,0.5\n{last_iteration},\n")).unwrap();
        }
        let (curves, boundaries) = sequential_track_curves(&e, out.path(), 0).unwrap();
        assert_eq!(boundaries, vec![300]);
        assert_eq!(curves[0].points, vec![(200, 1.0), (500, 1.0)]);
    }

    #[test]
    fn time_to_half_max_is_the_first_validation_at_half_the_runs_best() {
        let curve =
            |s: &[f64]| s.iter().enumerate().map(|(i, &s_pw)| CurvePoint { env_steps: (i as u64 + 1) * 100, s_pw }).collect::<Vec<_>>();
        assert_eq!(steps_to_half_max(&curve(&[0.0, 0.02, 0.06, 0.04, 0.1])), Some(300));
        assert_eq!(steps_to_half_max(&curve(&[0.08, 0.1])), Some(100));
        assert_eq!(steps_to_half_max(&curve(&[0.0, 0.0])), None);
        assert_eq!(steps_to_half_max(&[]), None);
    }

    #[test]
    fn validation_curves_keep_the_latest_row_of_repeated_iterations() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("metrics.csv");
        std::fs::write(&path, "iteration,env_steps,eval/S_pw\n1,100,\n2,200,0.5\n3,300,\n2,200,0.25\n4,400,0.75\n").unwrap();
        let curve = validation_curve(&path).unwrap();
        assert_eq!(curve, vec![CurvePoint { env_steps: 200, s_pw: 0.25 }, CurvePoint { env_steps: 400, s_pw: 0.75 }]);
        assert!(validation_curve(&dir.path().join("missing.csv")).unwrap().is_empty());
    }
}
