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

use super::processes::Transport;
use super::supervisor::{self, ClusterPlan};

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
    #[arg(long, value_enum, default_value_t = Transport::Shm)]
    transport: Transport,
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
    if args.in_process {
        return in_process(&dir, config, resume, args.iterations);
    }
    let actors = args.actors.unwrap_or_else(|| std::thread::available_parallelism().map_or(1, |n| n.get()));
    with_processes(&dir, config, resume, actors, args.transport, args.iterations)
}

/// Arguments of `dronerace bench learner`.
#[derive(Args)]
pub struct LearnerBenchArgs {
    /// Profile whose network and PPO settings are timed.
    #[arg(long, default_value = "paper", value_parser = ["cpu", "paper"])]
    profile: String,
    /// Samples per gradient step.
    #[arg(long, default_value_t = 4096)]
    samples: usize,
    /// Timed steps (after one warm-up).
    #[arg(long, default_value_t = 5)]
    repeats: usize,
    /// burn backend: flex, or ndarray in a build with `--features ndarray` / `openblas`.
    #[arg(long, default_value = "flex")]
    backend: String,
    /// Hidden layer widths instead of the profile's, e.g. `128,128` (to match another
    /// program's network in a side-by-side comparison).
    #[arg(long, value_delimiter = ',')]
    hidden: Option<Vec<usize>>,
    /// `state`: the MLP actor-critic; `vision`: the CNN actor on 84×84 images (SPEC §5) with
    /// the profile's MLP widths.
    #[arg(long, default_value = "state", value_parser = ["state", "vision"])]
    agent: String,
}

/// Times forward, backward and the optimiser step of one PPO gradient step.
pub fn bench(args: LearnerBenchArgs) -> anyhow::Result<()> {
    let mut profile = learner::Profile::named(&args.profile).with_context(|| format!("--profile: unknown profile {:?}", args.profile))?;
    anyhow::ensure!(args.samples > 0 && args.repeats > 0, "--samples and --repeats must be at least 1");
    if let Some(hidden) = args.hidden {
        anyhow::ensure!(!hidden.is_empty() && !hidden.contains(&0), "--hidden: widths must be at least 1, e.g. 128,128");
        profile.architecture.hidden = hidden;
    }
    let device = learner::bench::device(&args.backend).context("--backend")?;
    let t = match parse_agent(&args.agent)? {
        policy::Agent::State => learner::bench::time_gradient_step(&profile, args.samples, args.repeats, &device),
        policy::Agent::Vision => learner::bench::time_vision_gradient_step(&profile, args.samples, args.repeats, &device),
    };
    println!(
        "{} {} profile {:?}, {} samples, {} backend, {} threads: forward {:.1} ms, backward {:.1} ms, optimiser {:.1} ms, {:.1} GFLOP/s (forward+backward)",
        args.agent,
        profile.name,
        profile.architecture.hidden,
        args.samples,
        args.backend,
        rayon::current_num_threads(),
        t.forward * 1e3,
        t.backward * 1e3,
        t.optimizer * 1e3,
        t.gflops
    );
    Ok(())
}

/// Trains with supervised processes until the budget is spent, `iterations` are done, or
/// Ctrl-C. A new run needs a directory without checkpoints (its config is written there); a
/// resumed one needs a checkpoint to resume from.
fn with_processes(
    dir: &Path,
    config: TrainConfig,
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
        let text = toml::to_string(&config).context("serialising the config")?;
        let path = dir.join("config.toml");
        racetracks::files::write_atomic(&path, text.as_bytes()).with_context(|| format!("writing {}", path.display()))?;
    }
    let envs = config.resolved_profile()?.envs;
    supervisor::run(ClusterPlan { dir: dir.to_path_buf(), actors, envs, transport, iterations })
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
        super::report(&mut log, &progress_line(&s, trainer.eta_seconds()))?;
    }
    let path = trainer.checkpoint()?;
    eprintln!("checkpoint written to {}", path.display());
    Ok(())
}
