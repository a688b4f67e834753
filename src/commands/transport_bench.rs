//! `dronerace bench transport`: rollout throughput (MB/s) and weight-broadcast latency of the
//! iceoryx2 and gRPC transports, and the learner's capacity as actors grow (`transport::bench`).

use clap::Args;

/// Arguments of `dronerace bench transport`.
#[derive(Args)]
pub struct TransportBenchArgs {
    /// Transport to measure.
    #[arg(long, default_value = "shm")]
    transport: transport::Transport,
    /// Environments per rollout chunk.
    #[arg(long, default_value_t = 48)]
    envs: usize,
    /// Steps per rollout chunk.
    #[arg(long, default_value_t = 250)]
    steps: usize,
    /// Chunks sent in all (spread over the actors).
    #[arg(long, default_value_t = 40)]
    chunks: usize,
    /// Concurrent actor connections, each sending and watching weights.
    #[arg(long, default_value_t = 1)]
    actors: usize,
    /// Weights blob size in bytes (cpu profile ≈ 90 kB, paper ≈ 1.2 MB).
    #[arg(long, default_value_t = 1_200_000)]
    weights_bytes: usize,
    /// Weight broadcasts timed.
    #[arg(long, default_value_t = 50)]
    broadcasts: usize,
}

/// Measures one transport and prints what it found.
pub fn run(args: TransportBenchArgs) -> anyhow::Result<()> {
    let bench = transport::bench::TransportBench {
        transport: args.transport,
        envs: args.envs,
        steps: args.steps,
        chunks: args.chunks,
        actors: args.actors,
        weights_bytes: args.weights_bytes,
        broadcasts: args.broadcasts,
        rollout_memory_bytes: runtime::LearnerSettings::default().rollout_memory_mib << 20,
    };
    let t = transport::bench::measure_transport(&bench)?;
    println!(
        "{:?}, {} actor(s): rollouts {} × {:.2} MB: {:.0} MB/s ({:.1} chunks/s, encode + send + decode), learner CPU {:.2} s per GB; weights {:.2} MB to {}: until the last holds them p50 {:.3} ms, p99 {:.3} ms",
        bench.transport,
        bench.actors,
        bench.chunks,
        t.chunk_bytes as f64 / 1e6,
        t.megabytes_per_second,
        t.chunks_per_second,
        t.learner_cpu_seconds_per_gb,
        bench.weights_bytes as f64 / 1e6,
        bench.actors,
        t.broadcast_p50 * 1e3,
        t.broadcast_p99 * 1e3
    );
    Ok(())
}
