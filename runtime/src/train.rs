//! `dronerace train`'s two modes on a prepared configuration: the task controller, the learner
//! and the actors as supervised processes on this machine, or all of them in this process by
//! turns of the same loops.

#![allow(clippy::print_stderr, reason = "the command's own terminal output: where it trains, where the checkpoint went")]

use std::path::Path;
use std::sync::atomic::Ordering;

use anyhow::Context;
use learner::checkpoint::CheckpointDir;

use crate::progress::{ProgressLog, progress_line};
use crate::services::{Transport, stop_flag};
use crate::supervisor::{self, ClusterPlan};
use crate::{TrainConfig, Trainer};

/// Trains with supervised processes until the budget is spent, `iterations` are done, or
/// Ctrl-C. A new run needs a directory without checkpoints (its config is written there); a
/// resumed one needs a checkpoint to resume from.
pub fn with_processes(
    dir: &Path,
    mut config: TrainConfig,
    resume: bool,
    actors: usize,
    transport: Transport,
    iterations: Option<u64>,
) -> anyhow::Result<()> {
    let checkpoints = CheckpointDir::new(dir.join("checkpoints"), config.keep_checkpoints)?;
    if resume {
        anyhow::ensure!(checkpoints.latest().is_some(), "{} has no checkpoint to resume from", dir.display());
    } else {
        anyhow::ensure!(
            checkpoints.latest().is_none(),
            "{} already holds checkpoints: resume it (--resume), or choose another run directory",
            dir.display()
        );
        let _ = std::fs::remove_file(dir.join("taskctl.snapshot"));
        crate::warm_start::prepare(&mut config, dir)?;
        let text = toml::to_string(&config).context("serialising the config")?;
        let path = dir.join("config.toml");
        racetracks::files::write_atomic(&path, text.as_bytes()).with_context(|| format!("writing {}", path.display()))?;
    }
    let envs = config.resolved_profile()?.envs;
    supervisor::run(ClusterPlan { dir: dir.to_path_buf(), actors, envs, transport, iterations })
}

/// Trains in this process, by turns of the actor's and the learner's loops, until the budget is
/// spent, `iterations` are done, or Ctrl-C; then checkpoints.
pub fn in_process(dir: &Path, config: TrainConfig, resume: bool, iterations: Option<u64>) -> anyhow::Result<()> {
    let mut trainer = if resume {
        Trainer::resume(dir)?
    } else {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
        Trainer::start(config, dir)?
    };
    let stop = stop_flag()?;
    let mut log = ProgressLog::open(trainer.dir())?;
    let first = trainer.iteration();
    eprintln!("training in {} (from iteration {first}, in one process)", trainer.dir().display());
    while !trainer.finished() && !stop.load(Ordering::SeqCst) && iterations.is_none_or(|n| trainer.iteration() - first < n) {
        let s = trainer.iteration_step()?;
        log.line(&progress_line(&s, trainer.eta_seconds()))?;
    }
    let path = trainer.checkpoint()?;
    eprintln!("checkpoint written to {}", path.display());
    Ok(())
}
