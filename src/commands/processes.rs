//! `dronerace taskctl`, `dronerace learner`, `dronerace actor`: the three processes of the
//! distributed runtime (`runtime::services`, which defines their flags). Each reads the run
//! config (TOML, as for `train`); SIGINT or SIGTERM stops each cleanly (the learner checkpoints
//! first).

use std::path::PathBuf;

use clap::Args;
use runtime::services::{self, ActorOptions, LearnerOptions, TaskctlOptions, read_config};

use crate::signal::stop_flag;

/// Arguments of `dronerace taskctl`.
#[derive(Args)]
pub struct TaskctlArgs {
    /// Run configuration (TOML; tracks, generator, switching, environment count, network).
    #[arg(long)]
    config: Option<PathBuf>,
    #[command(flatten)]
    options: TaskctlOptions,
}

/// Serves the task controller until SIGINT/SIGTERM.
pub fn taskctl(args: TaskctlArgs) -> anyhow::Result<()> {
    Ok(services::taskctl(read_config(args.config.as_deref())?, args.options, stop_flag()?)?)
}

/// Arguments of `dronerace learner`.
#[derive(Args)]
pub struct LearnerArgs {
    /// Run configuration (TOML); ignored when the run directory already holds a run.
    #[arg(long)]
    config: Option<PathBuf>,
    #[command(flatten)]
    options: LearnerOptions,
}

/// Runs the learner process until the budget is spent, `--iterations` are done, or SIGINT.
pub fn learner(args: LearnerArgs) -> anyhow::Result<()> {
    Ok(services::learner(read_config(args.config.as_deref())?, args.options, stop_flag()?)?)
}

/// Arguments of `dronerace actor`.
#[derive(Args)]
pub struct ActorArgs {
    /// Run configuration (TOML; environment, seed, n_steps of the profile, network).
    #[arg(long)]
    config: Option<PathBuf>,
    #[command(flatten)]
    options: ActorOptions,
}

/// Runs one actor until SIGINT/SIGTERM.
pub fn actor(args: ActorArgs) -> anyhow::Result<()> {
    Ok(services::actor(read_config(args.config.as_deref())?, args.options, stop_flag()?)?)
}
