//! The progress line of an iteration, printed and appended to the run's `train.log` (by the
//! learner process and by training in one process alike).

use std::fs::File;
use std::io::Write;
use std::path::{Path, PathBuf};

use anyhow::Context;

use crate::run::IterationSummary;

/// `train.log` of a run directory, opened for appending.
pub struct ProgressLog {
    path: PathBuf,
    file: File,
}

impl ProgressLog {
    /// Opens (or creates) `dir/train.log`.
    pub fn open(dir: &Path) -> anyhow::Result<Self> {
        let path = dir.join("train.log");
        let file =
            std::fs::OpenOptions::new().create(true).append(true).open(&path).with_context(|| format!("opening {}", path.display()))?;
        Ok(Self { path, file })
    }

    /// Prints `line` on stderr and appends it to the log.
    #[allow(clippy::print_stderr, reason = "the progress line is the command's terminal output")]
    pub fn line(&mut self, line: &str) -> anyhow::Result<()> {
        eprintln!("{line}");
        writeln!(self.file, "{line}").with_context(|| format!("writing {}", self.path.display()))
    }
}

/// The live progress line of one iteration.
pub fn progress_line(s: &IterationSummary, eta_seconds: f64) -> String {
    let validation =
        s.validation.map_or(String::new(), |(s_pw, success)| format!(" | validation S_pw {s_pw:.4}, success {:.0} %", 100.0 * success));
    format!(
        "iter {:>5} | {:>11} steps | {:>6.0} SPS (collect {:.1} s, update {:.1} s) | return {:>8.2} | laps/ep {:>5.2} | switches {:>5} | kl {:.4} | ETA {}{validation}",
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
