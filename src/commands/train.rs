//! `dronerace train`: the task controller, the learner and the actors as supervised processes
//! on this machine (the default), or all in this process (`--in-process`, for debugging).

use std::path::{Path, PathBuf};

use anyhow::Context;
use clap::Args;

use crate::signal::stop_flag;
use learner::checkpoint::CheckpointDir;
use runtime::{ResolvedRun, Run, TrainConfig, TrainFlags, Trainer};

use runtime::supervisor::{self, ClusterPlan};

/// Arguments of `dronerace train`.
#[derive(Args)]
pub struct TrainArgs {
    /// TOML configuration (every field optional; see runtime::TrainConfig).
    #[arg(long)]
    config: Option<PathBuf>,
    /// Run directory (default `runs/<name>`).
    #[arg(long)]
    out: Option<PathBuf>,
    /// Continue the run in this directory from its newest checkpoint.
    #[arg(long, conflicts_with_all = ["config", "out", "profile", "track", "total_env_steps", "seed", "init_from"])]
    resume: Option<PathBuf>,
    #[command(flatten)]
    flags: TrainFlags,
    /// Stop after this many iterations (a checkpoint is written on the way out).
    #[arg(long)]
    iterations: Option<u64>,
    /// Actor processes (default: one per core).
    #[arg(long)]
    actors: Option<usize>,
    /// How rollouts travel between the actor processes and the learner.
    #[arg(long, default_value = "shm")]
    transport: transport::Transport,
    /// Run everything in this one process (no services; for debugging and tests).
    #[arg(long, conflicts_with_all = ["actors"])]
    in_process: bool,
    /// The agent of a new run, with its defaults [default: state] (a config file names its
    /// agent itself, `agent = "vision"`).
    #[arg(long, conflicts_with_all = ["config", "resume"])]
    agent: Option<policy::Agent>,
}

/// The run directory and its resolved config: a new one, or the one being resumed.
fn prepare(args: &TrainArgs) -> anyhow::Result<(PathBuf, ResolvedRun, bool)> {
    if let Some(dir) = &args.resume {
        return Ok((dir.clone(), ResolvedRun::read(&dir.join("config.toml"))?, true));
    }
    let config = match (&args.config, &args.agent) {
        (Some(path), _) => TrainConfig::read(path)?,
        (None, Some(agent)) => TrainConfig::defaults_for(*agent),
        (None, None) => TrainConfig::default(),
    };
    let resolved = config.with_flags(&args.flags)?.resolve()?;
    let dir = args.out.clone().unwrap_or_else(|| PathBuf::from("runs").join(&resolved.config().name));
    Ok((dir, resolved, false))
}

/// Runs `dronerace train` in the mode the flags choose.
pub fn run(args: TrainArgs) -> anyhow::Result<()> {
    let (dir, config, resume) = prepare(&args)?;
    std::fs::create_dir_all(&dir).with_context(|| format!("creating {}", dir.display()))?;
    // One trainer per run directory at a time, as experiment runners claim theirs: two would
    // write the same checkpoints and metrics.
    let _claim = runtime::run_lock::RunLock::acquire(&dir)?;
    if args.in_process {
        return in_process(&dir, config, resume, args.iterations);
    }
    let actors = args.actors.unwrap_or_else(|| std::thread::available_parallelism().map_or(1, |n| n.get()));
    with_processes(&dir, config, resume, actors, args.transport, args.iterations)
}

/// Trains with supervised processes until the budget is spent, `iterations` are done, or
/// Ctrl-C. A new run needs a directory without checkpoints (its config is written there); a
/// resumed one needs a checkpoint to resume from.
fn with_processes(
    dir: &Path,
    resolved: ResolvedRun,
    resume: bool,
    actors: usize,
    transport: transport::Transport,
    iterations: Option<u64>,
) -> anyhow::Result<()> {
    if resume {
        let checkpoints = CheckpointDir::new(dir.join("checkpoints"), resolved.config().keep_checkpoints)?;
        anyhow::ensure!(checkpoints.latest().is_some(), "{} has no checkpoint to resume from", dir.display());
    } else {
        Run::prepare(&resolved, dir)?;
        let _ = std::fs::remove_file(dir.join("taskctl.snapshot"));
    }
    let plan = ClusterPlan { dir: dir.to_path_buf(), actors, envs: resolved.envs(), transport, iterations };
    let stop = stop_flag()?;
    Ok(supervisor::run(plan, &stop)?)
}

/// Trains in this process, by turns of the actor's and the learner's loops, until the budget is
/// spent, `iterations` are done, or Ctrl-C; then checkpoints.
fn in_process(dir: &Path, resolved: ResolvedRun, resume: bool, iterations: Option<u64>) -> anyhow::Result<()> {
    let mut trainer = if resume { Trainer::resume(dir)? } else { Trainer::start(resolved, dir)? };
    let stop = stop_flag()?;
    let path = trainer.train(iterations, &stop)?;
    eprintln!("checkpoint written to {}", path.display());
    Ok(())
}
