//! `dronerace bench …`: every speed measurement under one group.

use anyhow::Context;
use clap::{Args, Subcommand};

/// What `dronerace bench` measures.
#[derive(Subcommand)]
pub enum BenchCommand {
    /// Time one PPO gradient step (forward, backward, optimiser) on this machine.
    Learner(LearnerBenchArgs),
    /// Measure rollout throughput and weight-broadcast latency of a transport.
    Transport(super::transport_bench::TransportBenchArgs),
    /// Measure the simulator's environment steps per second.
    Sim(super::sim::SimBenchArgs),
    /// Measure track generation (speed, acceptance) and one task-controller update.
    Tracks(super::tracks::TracksBenchArgs),
}

/// Runs one benchmark.
pub fn run(command: BenchCommand) -> anyhow::Result<()> {
    match command {
        BenchCommand::Learner(a) => learner_step(a),
        BenchCommand::Transport(a) => super::transport_bench::run(a),
        BenchCommand::Sim(a) => super::sim::bench(a),
        BenchCommand::Tracks(a) => super::tracks::bench(a),
    }
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
    #[arg(long, default_value = "state")]
    agent: policy::Agent,
}

/// Times forward, backward and the optimiser step of one PPO gradient step.
fn learner_step(args: LearnerBenchArgs) -> anyhow::Result<()> {
    let profile = learner::Profile::named(&args.profile).with_context(|| format!("--profile: unknown profile {:?}", args.profile))?;
    let mut learner = profile.default_learner();
    anyhow::ensure!(args.samples > 0 && args.repeats > 0, "--samples and --repeats must be at least 1");
    if let Some(hidden) = args.hidden {
        anyhow::ensure!(!hidden.is_empty() && !hidden.contains(&0), "--hidden: widths must be at least 1, e.g. 128,128");
        learner.architecture.hidden = hidden;
    }
    let device = learner::bench::device(&args.backend).context("--backend")?;
    let t = match args.agent {
        policy::Agent::State => learner::bench::time_gradient_step(&learner, args.samples, args.repeats, &device),
        policy::Agent::Vision => learner::bench::time_vision_gradient_step(&learner, args.samples, args.repeats, &device),
    };
    println!(
        "{} {} profile {:?}, {} samples, {} backend, {} threads: forward {:.1} ms, backward {:.1} ms, optimiser {:.1} ms, {:.1} GFLOP/s (forward+backward)",
        args.agent,
        profile.name,
        learner.architecture.hidden,
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
