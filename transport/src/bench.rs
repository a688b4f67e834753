//! The transports measured (`dronerace bench transport`): rollout throughput (MB/s) and
//! weight-broadcast latency of iceoryx2 and gRPC, and the learner's capacity as actors grow —
//! N concurrent actor connections (threads of this process, each with its own link: the same
//! shared-memory segments or loopback sockets N processes would use) sending to one learner
//! end, with the CPU time of the learner's threads alone.

use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Barrier};
use std::time::{Duration, Instant};

use crate::grpc_link::{GrpcActorLink, LearnerService};
use crate::shm::{ShmActorLink, ShmConfig, ShmLearnerLink};
use crate::{ActorLink, Admission, LearnerLink, LinkError, Received, Security, SecurityError, Transport, WeightsUpdate};

/// What to measure.
#[derive(Clone, Debug)]
pub struct TransportBench {
    /// Transport to measure.
    pub transport: Transport,
    /// Environments per rollout chunk.
    pub envs: usize,
    /// Steps per rollout chunk.
    pub steps: usize,
    /// Chunks sent in all (spread over the actors; at least 2: the first starts the clock).
    pub chunks: usize,
    /// Concurrent actor connections, each sending and watching weights.
    pub actors: usize,
    /// Weights blob size in bytes.
    pub weights_bytes: usize,
    /// Weight broadcasts timed.
    pub broadcasts: usize,
    /// Bytes of rollouts the gRPC learner end holds at most (the learner's `rollout_memory_mib`).
    pub rollout_memory_bytes: usize,
}

/// What one measurement found.
#[derive(Clone, Debug)]
pub struct TransportTiming {
    /// Bytes of one encoded chunk.
    pub chunk_bytes: usize,
    /// Rollout throughput (encode + send + decode), MB/s.
    pub megabytes_per_second: f64,
    /// Chunks per second.
    pub chunks_per_second: f64,
    /// CPU seconds of the learner's threads per GB received.
    pub learner_cpu_seconds_per_gb: f64,
    /// Broadcast latency until the last actor holds the weights: median, seconds.
    pub broadcast_p50: f64,
    /// The same, 99th percentile.
    pub broadcast_p99: f64,
}

/// Why a measurement could not be made.
#[derive(Debug, thiserror::Error)]
pub enum BenchError {
    /// A bad setting.
    #[error("{0}")]
    Setting(&'static str),
    /// A transport failed.
    #[error(transparent)]
    Link(#[from] LinkError),
    /// TLS or token settings.
    #[error(transparent)]
    Security(#[from] SecurityError),
    /// A socket, thread or runtime could not be had.
    #[error(transparent)]
    Io(#[from] std::io::Error),
    /// Something sent never arrived within 20 s.
    #[error("{0} never arrived")]
    Lost(&'static str),
    /// The learner's end refused a benchmark chunk.
    #[error("the learner's end refused a benchmark chunk: {0}")]
    Refused(String),
    /// An actor thread panicked.
    #[error("an actor thread panicked")]
    Panicked,
}

/// Name prefix of the threads that do the learner's side of a transport (besides the thread
/// that receives), so that their CPU time can be told from the simulated actors'.
const LEARNER_THREADS: &str = "learner-rpc";

/// A benchmark chunk of `envs` × `steps` transitions.
fn chunk(envs: usize, steps: usize) -> rollout::RolloutChunk {
    let mut chunk = rollout::RolloutChunk::zeroed(0, 0, envs, steps, sim::STATE_OBS_DIM, sim::ACTION_DIM);
    // Varied values, so nothing compresses or short-cuts a run of zeros.
    chunk.observations.iter_mut().enumerate().for_each(|(i, x)| *x = (i % 97) as f32 * 0.01);
    chunk
}

/// CPU seconds (user + system) of this process's threads whose name starts with `prefix`, plus
/// the calling thread's.
fn learner_cpu_seconds(prefix: &str) -> f64 {
    // SAFETY: sysconf and gettid have no preconditions.
    let (ticks, me) = unsafe { (libc::sysconf(libc::_SC_CLK_TCK) as f64, libc::gettid()) };
    let Ok(tasks) = std::fs::read_dir("/proc/self/task") else { return f64::NAN };
    let mut total = 0.0;
    for task in tasks.flatten() {
        let path = task.path();
        let name = std::fs::read_to_string(path.join("comm")).unwrap_or_default();
        let mine = task.file_name().to_str().and_then(|t| t.parse::<i32>().ok()) == Some(me);
        if !mine && !name.starts_with(prefix) {
            continue;
        }
        // Fields after the parenthesised name: state is field 3, utime 14, stime 15.
        let stat = std::fs::read_to_string(path.join("stat")).unwrap_or_default();
        let fields: Vec<&str> = stat.rsplit_once(')').map(|(_, rest)| rest.split_whitespace().collect()).unwrap_or_default();
        let field = |i: usize| fields.get(i - 3).and_then(|f| f.parse::<f64>().ok()).unwrap_or(0.0);
        total += (field(14) + field(15)) / ticks;
    }
    total
}

/// The learner end runs on this thread; each of `args.actors` actor ends on a thread of its own,
/// opened there by `make_actor`: first every broadcast is timed until the last actor holds it,
/// then the actors send `args.chunks` rollout chunks between them.
fn measure<L: LearnerLink>(
    args: &TransportBench,
    mut learner: L,
    make_actor: impl Fn() -> Result<Box<dyn ActorLink>, BenchError> + Send + Sync + 'static,
) -> Result<TransportTiming, BenchError> {
    let payload = Arc::new(chunk(args.envs, args.steps));
    let bytes = payload.to_bytes().len();
    let (actors, chunks, broadcasts) = (args.actors, args.chunks, args.broadcasts as u64);
    // The version every actor waits for; each reports when its link holds it.
    let wanted = Arc::new(AtomicU64::new(0));
    let (arrived_tx, arrived_rx) = std::sync::mpsc::channel::<Instant>();
    let connected = Arc::new(Barrier::new(actors + 1));
    let done = Arc::new(AtomicBool::new(false));
    let make_actor = Arc::new(make_actor);
    // Waiting actors poll; all of them together about 20,000 times a second, whatever their
    // number (64 threads each polling every 50 µs took the two cores from the learner).
    let poll = Duration::from_micros(50 * actors as u64);
    let mut threads = Vec::new();
    for a in 0..actors {
        let (payload, wanted, arrived_tx, connected, done, make_actor) =
            (payload.clone(), wanted.clone(), arrived_tx.clone(), connected.clone(), done.clone(), make_actor.clone());
        let share = chunks / actors + usize::from(a < chunks % actors);
        let thread = std::thread::Builder::new().name(format!("actor-{a}")).spawn(move || -> Result<(), BenchError> {
            let link = make_actor();
            connected.wait();
            let mut link = link?;
            for version in 1..=broadcasts {
                while wanted.load(Ordering::SeqCst) < version {
                    std::thread::sleep(poll);
                }
                loop {
                    if let Some(w) = link.newest_weights()?
                        && w.version == version
                    {
                        arrived_tx.send(Instant::now()).ok();
                        break;
                    }
                    std::thread::sleep(poll);
                }
            }
            let name = format!("bench-{a}");
            for _ in 0..share {
                link.send_rollout(&name, 0, &payload)?;
            }
            while !done.load(Ordering::SeqCst) {
                std::thread::sleep(Duration::from_millis(5));
            }
            Ok(())
        })?;
        threads.push(thread);
    }
    connected.wait();
    // Let the actors' ends connect before timing.
    std::thread::sleep(Duration::from_millis(500));
    let blob = vec![7u8; args.weights_bytes];
    let mut latencies = Vec::new();
    for version in 1..=broadcasts {
        let sent = Instant::now();
        learner.publish(&WeightsUpdate { learner_epoch: 0, version, max_policy_lag: 0, blob: blob.clone() })?;
        wanted.store(version, Ordering::SeqCst);
        let mut last = sent;
        for _ in 0..actors {
            last = last.max(arrived_rx.recv_timeout(Duration::from_secs(20)).map_err(|_| BenchError::Lost("a weights broadcast"))?);
        }
        latencies.push(last - sent);
    }
    let (observation_dim, action_dim) = (sim::STATE_OBS_DIM, sim::ACTION_DIM);
    learner.admit(Admission {
        learner_epoch: 0,
        version: 0,
        max_policy_lag: 0,
        observation_dim,
        action_dim,
        images: false,
        total_envs: args.envs,
        rollout_steps: args.steps,
    });
    let mut received = 0;
    let mut started = None;
    while received < chunks {
        let received_now = learner.receive(Duration::from_secs(20))?.ok_or(BenchError::Lost("a rollout chunk"))?;
        started.get_or_insert_with(|| (Instant::now(), learner_cpu_seconds(LEARNER_THREADS)));
        match received_now {
            Received::Rollout(d) => received += usize::from(d.chunk.transitions() == args.envs * args.steps),
            Received::Refused { refusal, .. } => return Err(BenchError::Refused(refusal.to_string())),
        }
    }
    // The first arrival starts the clock, so `chunks - 1` transfers are timed.
    let (seconds, cpu) =
        started.map_or((f64::NAN, f64::NAN), |(t, cpu)| (t.elapsed().as_secs_f64(), learner_cpu_seconds(LEARNER_THREADS) - cpu));
    done.store(true, Ordering::SeqCst);
    for thread in threads {
        thread.join().map_err(|_| BenchError::Panicked)??;
    }
    latencies.sort();
    let megabytes = (chunks - 1) as f64 * bytes as f64 / 1e6;
    Ok(TransportTiming {
        chunk_bytes: bytes,
        megabytes_per_second: megabytes / seconds,
        chunks_per_second: (chunks - 1) as f64 / seconds,
        learner_cpu_seconds_per_gb: cpu / megabytes * 1e3,
        broadcast_p50: latencies[latencies.len() / 2].as_secs_f64(),
        broadcast_p99: latencies[(latencies.len() * 99 / 100).min(latencies.len() - 1)].as_secs_f64(),
    })
}

/// Measures one transport.
pub fn measure_transport(args: &TransportBench) -> Result<TransportTiming, BenchError> {
    if args.chunks < 2 || args.broadcasts < 1 || args.actors < 1 {
        return Err(BenchError::Setting("--chunks must be ≥ 2, --broadcasts ≥ 1 and --actors ≥ 1"));
    }
    match args.transport {
        Transport::Shm => {
            let config = ShmConfig { run: format!("bench-{}", std::process::id()), max_actors: args.actors };
            let learner = ShmLearnerLink::open(&config)?;
            measure(args, learner, move || Ok(Box::new(ShmActorLink::open(&config)?) as Box<dyn ActorLink>))
        }
        Transport::Grpc => {
            // The learner's server and the actors' clients on runtimes of their own, so that the
            // learner's CPU time can be read off its threads.
            let rt = tokio::runtime::Builder::new_multi_thread().worker_threads(2).thread_name(LEARNER_THREADS).enable_all().build()?;
            let actors_rt = tokio::runtime::Builder::new_multi_thread().worker_threads(2).thread_name("actors-rpc").enable_all().build()?;
            let listener = std::net::TcpListener::bind("127.0.0.1:0")?;
            let addr = listener.local_addr()?;
            listener.set_nonblocking(true)?;
            let board = Arc::new(crate::board::LearnerBoard::default());
            let (service, link) = LearnerService::with_rollouts(board.clone(), args.rollout_memory_bytes);
            board.set_admission(Admission {
                learner_epoch: 0,
                version: 0,
                max_policy_lag: 0,
                observation_dim: sim::STATE_OBS_DIM,
                action_dim: sim::ACTION_DIM,
                images: false,
                total_envs: args.envs,
                rollout_steps: args.steps,
            });
            let security = Security::default();
            let router = security.server()?.add_service(service.into_server());
            let incoming = {
                let _guard = rt.enter();
                crate::listener::incoming(tokio::net::TcpListener::from_std(listener)?)
            };
            rt.spawn(router.serve_with_incoming(incoming));
            let handle = actors_rt.handle().clone();
            let url = format!("http://{addr}");
            measure(args, link, move || {
                Ok(Box::new(GrpcActorLink::connect(handle.clone(), &url, &Security::default())?) as Box<dyn ActorLink>)
            })
        }
    }
}
