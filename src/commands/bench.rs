//! `dronerace bench …`: every speed measurement under one group.

use clap::Subcommand;

/// What `dronerace bench` measures.
#[derive(Subcommand)]
pub enum BenchCommand {
    /// Time one PPO gradient step (forward, backward, optimiser) on this machine.
    Learner(super::train::LearnerBenchArgs),
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
        BenchCommand::Learner(a) => super::train::bench(a),
        BenchCommand::Transport(a) => super::transport_bench::run(a),
        BenchCommand::Sim(a) => super::sim::bench(a),
        BenchCommand::Tracks(a) => super::tracks::bench(a),
    }
}
