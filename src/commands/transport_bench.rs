//! `dronerace transport-bench`: rollout throughput (MB/s) and weight-broadcast latency of the
//! iceoryx2 and gRPC transports, sender and receiver on separate threads of this process
//! (the same shared-memory segments or loopback sockets two processes would use).

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use anyhow::Context;
use clap::Args;
use proto::grpc_link::{GrpcActorLink, LearnerService};
use proto::shm::{ShmActorLink, ShmConfig, ShmLearnerLink};
use proto::{ActorLink, Admission, LearnerLink, Received, Security, WeightsUpdate};

use super::services::Transport;

/// Arguments of `dronerace transport-bench`.
#[derive(Args)]
pub struct TransportBenchArgs {
    /// Transport to measure.
    #[arg(long, value_enum, default_value_t = Transport::Shm)]
    transport: Transport,
    /// Environments per rollout chunk.
    #[arg(long, default_value_t = 48)]
    envs: usize,
    /// Steps per rollout chunk.
    #[arg(long, default_value_t = 250)]
    steps: usize,
    /// Chunks sent.
    #[arg(long, default_value_t = 40)]
    chunks: usize,
    /// Weights blob size in bytes (cpu profile ≈ 90 kB, paper ≈ 1.2 MB).
    #[arg(long, default_value_t = 1_200_000)]
    weights_bytes: usize,
    /// Weight broadcasts timed.
    #[arg(long, default_value_t = 50)]
    broadcasts: usize,
}

fn chunk(envs: usize, steps: usize) -> policy::RolloutChunk {
    let mut chunk = policy::RolloutChunk::zeroed(0, 0, envs, steps, sim::STATE_OBS_DIM, sim::ACTION_DIM);
    // Varied values, so nothing compresses or short-cuts a run of zeros.
    chunk.observations.iter_mut().enumerate().for_each(|(i, x)| *x = (i % 97) as f32 * 0.01);
    chunk
}

/// The learner end runs on this thread, the actor end on a thread `make_actor` opens it in.
fn measure<L: LearnerLink>(
    args: &TransportBenchArgs,
    mut learner: L,
    make_actor: impl FnOnce() -> anyhow::Result<Box<dyn ActorLink>> + Send + 'static,
) -> anyhow::Result<()> {
    let payload = chunk(args.envs, args.steps);
    let bytes = payload.to_bytes().len();
    let chunks = args.chunks;
    let (weights_tx, weights_rx) = std::sync::mpsc::channel::<(u64, Instant)>();
    let (latency_tx, latency_rx) = std::sync::mpsc::channel::<Duration>();
    let done = Arc::new(AtomicBool::new(false));
    let done_actor = done.clone();
    let broadcasts = args.broadcasts;
    let actor = std::thread::spawn(move || -> anyhow::Result<()> {
        let mut link = make_actor()?;
        // Weights first: wait for each version, report when it arrived.
        for _ in 0..broadcasts {
            let (version, sent) = weights_rx.recv().context("weights schedule")?;
            loop {
                if let Some(w) = link.newest_weights()?
                    && w.version == version
                {
                    latency_tx.send(sent.elapsed()).ok();
                    break;
                }
                std::hint::spin_loop();
            }
        }
        for _ in 0..chunks {
            link.send_rollout("bench", 0, &payload)?;
        }
        while !done_actor.load(Ordering::SeqCst) {
            std::thread::sleep(Duration::from_millis(5));
        }
        Ok(())
    });
    // Let the actor's end connect before timing.
    std::thread::sleep(Duration::from_millis(500));
    let blob = vec![7u8; args.weights_bytes];
    let mut latencies = Vec::new();
    for version in 1..=args.broadcasts as u64 {
        let sent = Instant::now();
        learner.publish(&WeightsUpdate { learner_epoch: 0, version, max_policy_lag: 0, blob: blob.clone() })?;
        weights_tx.send((version, sent))?;
        latencies.push(latency_rx.recv_timeout(Duration::from_secs(10)).context("a weights broadcast never arrived")?);
    }
    let mut received = 0;
    let mut started = None;
    let (observation_dim, action_dim) = (sim::STATE_OBS_DIM, sim::ACTION_DIM);
    learner.admit(Admission { learner_epoch: 0, version: 0, max_policy_lag: 0, observation_dim, action_dim, total_envs: args.envs });
    while received < chunks {
        let received_now = learner.receive(Duration::from_secs(20))?.context("a rollout chunk never arrived")?;
        started.get_or_insert_with(Instant::now);
        match received_now {
            Received::Rollout(d) => received += usize::from(d.chunk.transitions() == args.envs * args.steps),
            Received::Refused { refusal, .. } => anyhow::bail!("the learner's end refused a benchmark chunk: {refusal}"),
        }
    }
    // The first arrival starts the clock, so `chunks - 1` transfers are timed.
    let seconds = started.map_or(f64::NAN, |s| s.elapsed().as_secs_f64());
    done.store(true, Ordering::SeqCst);
    actor.join().map_err(|_| anyhow::anyhow!("the actor thread panicked"))??;
    latencies.sort();
    let ms = |d: Duration| d.as_secs_f64() * 1e3;
    println!(
        "{:?}: rollouts {} × {:.2} MB: {:.0} MB/s ({:.1} chunks/s, encode + send + decode); weights {:.2} MB: latency p50 {:.3} ms, p99 {:.3} ms",
        args.transport,
        chunks,
        bytes as f64 / 1e6,
        (chunks - 1) as f64 * bytes as f64 / 1e6 / seconds,
        (chunks - 1) as f64 / seconds,
        args.weights_bytes as f64 / 1e6,
        ms(latencies[latencies.len() / 2]),
        ms(latencies[(latencies.len() * 99 / 100).min(latencies.len() - 1)])
    );
    Ok(())
}

/// Measures one transport.
pub fn run(args: TransportBenchArgs) -> anyhow::Result<()> {
    anyhow::ensure!(args.chunks >= 2 && args.broadcasts >= 1, "--chunks must be ≥ 2 and --broadcasts ≥ 1");
    match args.transport {
        Transport::Shm => {
            let config = ShmConfig { run: format!("bench-{}", std::process::id()), max_actors: 1 };
            let learner = ShmLearnerLink::open(&config)?;
            measure(&args, learner, move || Ok(Box::new(ShmActorLink::open(&config)?) as Box<dyn ActorLink>))
        }
        Transport::Grpc => {
            let rt = tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build()?;
            let listener = std::net::TcpListener::bind("127.0.0.1:0")?;
            let addr = listener.local_addr()?;
            listener.set_nonblocking(true)?;
            let board = Arc::new(proto::board::LearnerBoard::default());
            let (service, link) = LearnerService::with_rollouts(board.clone());
            board.set_admission(proto::Admission {
                learner_epoch: 0,
                version: 0,
                max_policy_lag: 0,
                observation_dim: sim::STATE_OBS_DIM,
                action_dim: sim::ACTION_DIM,
                total_envs: args.envs,
            });
            let security = Security::default();
            let router = security.server()?.add_service(service.into_server());
            let incoming = {
                let _guard = rt.enter();
                proto::security::incoming(tokio::net::TcpListener::from_std(listener)?)
            };
            rt.spawn(router.serve_with_incoming(incoming));
            let handle = rt.handle().clone();
            let url = format!("http://{addr}");
            measure(&args, link, move || Ok(Box::new(GrpcActorLink::connect(handle, &url, &Security::default())?) as Box<dyn ActorLink>))
        }
    }
}
