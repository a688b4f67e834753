//! The progress line of an iteration, printed and appended to the run's `train.log` (by the
//! learner process and by training in one process alike).

use std::fs::File;
use std::io::Write;
use std::path::{Path, PathBuf};

use learner::learner::IterationReport;

/// What one iteration produced, for the progress line.
#[derive(Clone, Debug)]
pub struct IterationSummary {
    /// Iteration number (1-based, equals the new policy version).
    pub iteration: u64,
    /// Learner report.
    pub report: IterationReport,
    /// Environment steps per second of this iteration's collection and update (the validation
    /// that ran in its interval left out).
    pub sps: f64,
    /// Seconds spent collecting the rollout (simulation and inference).
    pub collect_seconds: f64,
    /// Seconds of the previous iteration's validation, which ran in this iteration's interval
    /// (0 when there was none).
    pub validation_seconds: f64,
    /// Seconds spent in the PPO update.
    pub update_seconds: f64,
    /// Mean return of the episodes that ended.
    pub mean_return: f64,
    /// Mean laps per ended episode.
    pub laps_per_episode: f64,
    /// Task switches so far.
    pub switches: usize,
    /// Validation S_pw and success rate, when this iteration was evaluated.
    pub validation: Option<(f64, f64)>,
}

/// `train.log` could not be opened or written.
#[derive(Debug, thiserror::Error)]
#[error("{}: {source}", file.display())]
pub struct LogError {
    /// The log file.
    pub file: PathBuf,
    /// What the system said.
    #[source]
    pub source: std::io::Error,
}

/// `train.log` of a run directory, opened for appending.
pub struct ProgressLog {
    path: PathBuf,
    file: File,
}

impl ProgressLog {
    /// Shows `line` on the terminal and appends it to the log.
    #[allow(clippy::print_stderr, reason = "the progress line is the training's own terminal output")]
    pub fn report(&mut self, line: &str) -> Result<(), LogError> {
        eprintln!("{line}");
        self.append(line)
    }

    /// Opens (or creates) `dir/train.log`.
    pub fn open(dir: &Path) -> Result<Self, LogError> {
        let path = dir.join("train.log");
        match std::fs::OpenOptions::new().create(true).append(true).open(&path) {
            Ok(file) => Ok(Self { path, file }),
            Err(source) => Err(LogError { file: path, source }),
        }
    }

    /// Appends `line` to the log (the command shows it on its terminal too).
    pub fn append(&mut self, line: &str) -> Result<(), LogError> {
        writeln!(self.file, "{line}").map_err(|source| LogError { file: self.path.clone(), source })
    }
}

/// The time left in a run, from a smoothed training rate plus the validations still due: an
/// iteration's own rate swings with the machine's load, and the one after each validation
/// used to count the validation as collection.
#[derive(Clone, Debug, Default)]
pub struct Eta {
    /// Exponential moving average of the training env-steps/s (validation excluded).
    steps_per_second: Option<f64>,
    /// Seconds the latest validation took.
    pub validation_seconds: Option<f64>,
}

impl Eta {
    /// Weight of the newest iteration in the average: ~20 iterations of memory.
    const SMOOTHING: f64 = 0.05;

    /// Folds one iteration's training rate into the average.
    pub fn observe(&mut self, steps_per_second: f64) {
        if !(steps_per_second.is_finite() && steps_per_second > 0.0) {
            return;
        }
        self.steps_per_second =
            Some(self.steps_per_second.map_or(steps_per_second, |avg| avg + Self::SMOOTHING * (steps_per_second - avg)));
    }

    /// Seconds to train `steps_left` more env steps and run `validations_left` validations
    /// (NaN before the first iteration).
    pub fn seconds_left(&self, steps_left: u64, validations_left: u64) -> f64 {
        let training = self.steps_per_second.map_or(f64::NAN, |rate| steps_left as f64 / rate);
        training + validations_left as f64 * self.validation_seconds.unwrap_or(0.0)
    }
}

/// The live progress line of one iteration.
pub fn progress_line(s: &IterationSummary, eta_seconds: f64) -> String {
    let validation =
        s.validation.map_or(String::new(), |(s_pw, success)| format!(" | validation S_pw {s_pw:.4}, success {:.0} %", 100.0 * success));
    let validated = if s.validation_seconds > 0.0 { format!(", previous validation {:.1} s", s.validation_seconds) } else { String::new() };
    format!(
        "iter {:>5} | {:>11} steps | {:>6.0} SPS (collect {:.1} s, update {:.1} s{validated}) | return {:>8.2} | laps/ep {:>5.2} | switches {:>5} | kl {:.4} | ETA {}{validation}",
        s.iteration,
        s.report.env_steps,
        s.sps,
        s.collect_seconds,
        s.update_seconds,
        s.mean_return,
        s.laps_per_episode,
        s.switches,
        s.report.stats.approx_kl,
        format_duration(eta_seconds)
    )
}

fn format_duration(seconds: f64) -> String {
    if !seconds.is_finite() {
        return "–".into();
    }
    let s = seconds as u64;
    format!("{}h{:02}m{:02}s", s / 3600, s % 3600 / 60, s % 60)
}

#[cfg(test)]
mod tests {
    use super::Eta;

    #[test]
    fn the_estimate_follows_the_smoothed_rate_and_adds_the_validations_due() {
        let mut eta = Eta::default();
        assert!(eta.seconds_left(1000, 0).is_nan(), "no rate before the first iteration");
        eta.observe(1000.0);
        assert_eq!(eta.seconds_left(10_000, 3), 10.0, "no validation measured yet");
        // One slow iteration moves the average by a twentieth of the difference, not to it.
        eta.observe(100.0);
        assert!((eta.seconds_left(9550, 0) - 10.0).abs() < 1e-9);
        eta.observe(f64::INFINITY);
        eta.observe(0.0);
        assert!((eta.seconds_left(9550, 0) - 10.0).abs() < 1e-9, "non-finite and zero rates are ignored");
        eta.validation_seconds = Some(12.0);
        assert!((eta.seconds_left(9550, 2) - 34.0).abs() < 1e-9);
    }
}
