//! `dronerace taskctl`, `dronerace learner`, `dronerace actor`: the three processes of the
//! distributed runtime (`runtime::services`). Each reads the run config (TOML, as for `train`)
//! plus flags naming addresses; SIGINT or SIGTERM stops each cleanly (the learner checkpoints
//! first).

use std::net::SocketAddr;
use std::path::PathBuf;

use clap::Args;
use runtime::services::{self, ActorOptions, LearnerOptions, TaskctlOptions, read_config};

use super::TransportArg;
use crate::signal::stop_flag;

/// Arguments of `dronerace taskctl`.
#[derive(Args)]
pub struct TaskctlArgs {
    /// Run configuration (TOML; tracks, generator, switching, environment count, network).
    #[arg(long)]
    config: Option<PathBuf>,
    /// Address to serve gRPC on.
    #[arg(long, default_value = "127.0.0.1:50051")]
    listen: SocketAddr,
    /// Snapshot file: restored at start when present, rewritten after every change.
    #[arg(long)]
    snapshot: PathBuf,
    /// Also serve gRPC health alone, in plaintext, here: for probes that cannot speak TLS.
    #[arg(long)]
    health_listen: Option<SocketAddr>,
}

/// Serves the task controller until SIGINT/SIGTERM.
pub fn taskctl(args: TaskctlArgs) -> anyhow::Result<()> {
    let config = read_config(args.config.as_deref())?;
    let options = TaskctlOptions { config, listen: args.listen, snapshot: args.snapshot, health_listen: args.health_listen };
    Ok(services::taskctl(options, stop_flag()?)?)
}

/// Arguments of `dronerace learner`.
#[derive(Args)]
pub struct LearnerArgs {
    /// Run configuration (TOML); ignored when the run directory already holds a run.
    #[arg(long)]
    config: Option<PathBuf>,
    /// Run directory: a new run starts there, or the run there resumes from its newest checkpoint.
    #[arg(long)]
    out: PathBuf,
    /// Address to serve gRPC on (status, weights, and rollouts with `--transport grpc`).
    #[arg(long, default_value = "127.0.0.1:50052")]
    listen: SocketAddr,
    /// Also serve gRPC health alone, in plaintext, here (once the checkpoint is restored): for
    /// probes that cannot speak TLS.
    #[arg(long)]
    health_listen: Option<SocketAddr>,
    /// How rollouts arrive.
    #[arg(long, value_enum, default_value_t = TransportArg::Shm)]
    transport: TransportArg,
    /// iceoryx2 run identifier (with `--transport shm`).
    #[arg(long, default_value = "main")]
    shm_run: String,
    /// Actors the first iteration waits for.
    #[arg(long, default_value_t = 1)]
    actors: usize,
    /// Task controller address (for the switch count in the progress line).
    #[arg(long)]
    taskctl: Option<String>,
    /// Stop after this many iterations (a checkpoint is written on the way out).
    #[arg(long)]
    iterations: Option<u64>,
}

/// Runs the learner process until the budget is spent, `--iterations` are done, or SIGINT.
pub fn learner(args: LearnerArgs) -> anyhow::Result<()> {
    let options = LearnerOptions {
        config: read_config(args.config.as_deref())?,
        out: args.out,
        listen: args.listen,
        health_listen: args.health_listen,
        transport: args.transport.into(),
        shm_run: args.shm_run,
        actors: args.actors,
        taskctl: args.taskctl,
        iterations: args.iterations,
    };
    Ok(services::learner(options, stop_flag()?)?)
}

/// Arguments of `dronerace actor`.
#[derive(Args)]
pub struct ActorArgs {
    /// Run configuration (TOML; environment, seed, n_steps of the profile, network).
    #[arg(long)]
    config: Option<PathBuf>,
    /// Actor name (stable across restarts: it takes back its environments).
    #[arg(long)]
    name: String,
    /// Environments this actor runs.
    #[arg(long)]
    envs: usize,
    /// Task controller address.
    #[arg(long, default_value = "http://127.0.0.1:50051")]
    taskctl: String,
    /// How rollouts travel.
    #[arg(long, value_enum, default_value_t = TransportArg::Shm)]
    transport: TransportArg,
    /// Learner address (with `--transport grpc`).
    #[arg(long, default_value = "http://127.0.0.1:50052")]
    learner: String,
    /// iceoryx2 run identifier (with `--transport shm`).
    #[arg(long, default_value = "main")]
    shm_run: String,
    /// Most actors of the run on this machine (sizes the iceoryx2 services; same on all).
    #[arg(long, default_value_t = 1)]
    max_actors: usize,
    /// Stop after this many rollouts.
    #[arg(long)]
    rollouts: Option<u64>,
}

/// Runs one actor until SIGINT/SIGTERM.
pub fn actor(args: ActorArgs) -> anyhow::Result<()> {
    let options = ActorOptions {
        config: read_config(args.config.as_deref())?,
        name: args.name,
        envs: args.envs,
        taskctl: args.taskctl,
        transport: args.transport.into(),
        learner: args.learner,
        shm_run: args.shm_run,
        max_actors: args.max_actors,
        rollouts: args.rollouts,
    };
    Ok(services::actor(options, stop_flag()?)?)
}
