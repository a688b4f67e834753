//! `dronerace train`: the task controller, the learner and the actors as supervised processes
//! on this machine (the default), or all in this process (`--in-process`, for debugging).

use std::path::{Path, PathBuf};

use anyhow::Context;
use clap::Args;
use std::sync::atomic::Ordering;

use crate::signal::stop_flag;
use learner::checkpoint::CheckpointDir;
use runtime::progress::{ProgressLog, progress_line};
use runtime::{TrackSource, TrainConfig, Trainer};

use runtime::supervisor::{self, ClusterPlan};

use super::TransportArg;

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
    /// Profile (overrides the config): cpu (256×256, 96 environments) or paper (SPEC §10).
    #[arg(long, value_parser = ["cpu", "paper"])]
    profile: Option<String>,
    /// Train on this one track instead of generated tracks: a library track's name (e.g.
    /// Figure8) or a track file (e.g. my-track.toml); validation then flies it too.
    #[arg(long)]
    track: Option<String>,
    /// Environment steps of the run (overrides the config).
    #[arg(long)]
    total_env_steps: Option<u64>,
    /// Seed (overrides the config).
    #[arg(long)]
    seed: Option<u64>,
    /// Start from this trained policy (checkpoint or weights blob): fine-tuning. Pair it with
    /// a lower learning rate in the config's [ppo] section.
    #[arg(long)]
    init_from: Option<PathBuf>,
    /// Stop after this many iterations (a checkpoint is written on the way out).
    #[arg(long)]
    iterations: Option<u64>,
    /// Actor processes (default: one per core).
    #[arg(long)]
    actors: Option<usize>,
    /// How rollouts travel between the actor processes and the learner.
    #[arg(long, value_enum, default_value_t = TransportArg::Shm)]
    transport: TransportArg,
    /// Run everything in this one process (no services; for debugging and tests).
    #[arg(long, conflicts_with_all = ["actors"])]
    in_process: bool,
    /// The agent of a new run, with its defaults [default: state] (a config file names its
    /// agent itself, `agent = "vision"`).
    #[arg(long, conflicts_with_all = ["config", "resume"], value_parser = ["state", "vision"])]
    agent: Option<String>,
}

/// The agent a command-line flag names.
pub(crate) fn parse_agent(name: &str) -> anyhow::Result<policy::Agent> {
    match name {
        "state" => Ok(policy::Agent::State),
        "vision" => Ok(policy::Agent::Vision),
        other => anyhow::bail!("{other:?} is neither state nor vision"),
    }
}

/// The run directory and its config: a new one (written to `<dir>/config.toml`), or the one
/// being resumed.
fn prepare(args: &TrainArgs) -> anyhow::Result<(PathBuf, TrainConfig, bool)> {
    if let Some(dir) = &args.resume {
        let config = TrainConfig::read(&dir.join("config.toml"))?;
        return Ok((dir.clone(), config, true));
    }
    let mut config = match (&args.config, &args.agent) {
        (Some(path), _) => TrainConfig::read(path)?,
        (None, Some(agent)) => TrainConfig::defaults_for(parse_agent(agent)?),
        (None, None) => TrainConfig::default(),
    };
    if let Some(p) = &args.profile {
        config.profile = p.clone();
    }
    if let Some(t) = &args.track {
        // A path (a file that exists, or anything ending in .toml) is a track file; otherwise
        // a library name. Either way the validation flies the same track.
        let is_file = t.ends_with(".toml") || Path::new(t).is_file();
        // Absolute, so that the run's config.toml still finds the file from elsewhere (resume).
        let file = || std::fs::canonicalize(t).with_context(|| format!("--track {t}"));
        let (names, files) = if is_file { (Vec::new(), vec![file()?]) } else { (vec![t.clone()], Vec::new()) };
        racetracks::chosen_tracks(["--track"; 2], &names, &files)?;
        config.eval.library = names.clone();
        config.eval.files = files.clone();
        config.tracks = TrackSource::Chosen { names, files };
        config.switching.policy = taskctl::SwitchPolicy::None;
    }
    if let Some(n) = args.total_env_steps {
        config.total_env_steps = n;
    }
    if let Some(s) = args.seed {
        config.seed = s;
    }
    if let Some(p) = &args.init_from {
        config.init_from = Some(p.clone());
    }
    config.resolved_profile()?;
    let dir = args.out.clone().unwrap_or_else(|| PathBuf::from("runs").join(&config.name));
    Ok((dir, config, false))
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
    config: TrainConfig,
    resume: bool,
    actors: usize,
    transport: TransportArg,
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
        let text = toml::to_string(&config).context("serialising the config")?;
        let path = dir.join("config.toml");
        durable::write_atomic(&path, text.as_bytes()).with_context(|| format!("writing {}", path.display()))?;
    }
    let envs = config.resolved_profile()?.envs;
    let stop = stop_flag()?;
    Ok(supervisor::run(ClusterPlan { dir: dir.to_path_buf(), actors, envs, transport: transport.into(), iterations }, &stop)?)
}

/// Trains in this process, by turns of the actor's and the learner's loops, until the budget is
/// spent, `iterations` are done, or Ctrl-C; then checkpoints.
fn in_process(dir: &Path, config: TrainConfig, resume: bool, iterations: Option<u64>) -> anyhow::Result<()> {
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
        log.report(&progress_line(&s, trainer.eta_seconds()))?;
    }
    let path = trainer.checkpoint()?;
    eprintln!("checkpoint written to {}", path.display());
    Ok(())
}
