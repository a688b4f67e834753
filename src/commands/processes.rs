//! The three processes of the distributed runtime and their servers' wiring: `dronerace
//! taskctl`, `dronerace learner`, `dronerace actor` (their arguments are parsed by the binary
//! with the `Args` structs here). Each reads the run config (TOML, as for `train`) plus flags naming
//! addresses; SIGINT or SIGTERM stops each cleanly (the learner checkpoints first).

#![allow(clippy::print_stderr, reason = "the process commands' own terminal output: what started, where it serves, what it restarted")]

use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;

use crate::signal::stop_flag;
use anyhow::Context;
use clap::{Args, ValueEnum};
use proto::board::LearnerBoard;
use proto::grpc_link::{GrpcActorLink, LearnerService};
use proto::shm::{ShmActorLink, ShmConfig, ShmLearnerLink};
use proto::task_client::TaskClient;
use proto::{LearnerLink, Security};
use runtime::learner_process::{LearnerProcess, learner_only};
use runtime::progress::{ProgressLog, progress_line};
use runtime::{Run, TrainConfig};
use taskctl::TaskService;

/// How rollouts and weights travel between actors and the learner.
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub enum Transport {
    /// iceoryx2 shared memory (actors on the learner's machine).
    Shm,
    /// gRPC streams (actors anywhere).
    Grpc,
}

/// The run configuration at `path`, or the defaults.
pub fn read_config(path: &Option<PathBuf>) -> anyhow::Result<TrainConfig> {
    Ok(match path {
        Some(p) => TrainConfig::read(p)?,
        None => TrainConfig::default(),
    })
}

/// A multi-threaded tokio runtime with `threads` workers.
pub fn async_runtime(threads: usize) -> anyhow::Result<tokio::runtime::Runtime> {
    tokio::runtime::Builder::new_multi_thread().worker_threads(threads).enable_all().build().context("starting the async runtime")
}

/// Snapshot writes failed in a row before the task controller stops.
const MAX_FAILED_SNAPSHOTS: u32 = 3;

/// Starts the plaintext health server for probes on `addr` (`--health-listen`), if given,
/// reporting `serving` SERVING until `stop`.
pub fn spawn_health(
    rt: &tokio::runtime::Runtime,
    addr: Option<SocketAddr>,
    serving: &'static [&'static str],
    stop: Arc<AtomicBool>,
) -> anyhow::Result<()> {
    let Some(addr) = addr else { return Ok(()) };
    let listener = rt.block_on(tokio::net::TcpListener::bind(addr)).with_context(|| format!("health: binding {addr}"))?;
    eprintln!("health (plaintext, for probes): serving on {addr}");
    rt.spawn(async move {
        if let Err(e) = proto::serve_health(listener, serving, until(stop)).await {
            tracing::error!("health server on {addr}: {e}");
        }
    });
    Ok(())
}

/// Resolves once `stop` is set (polled every 100 ms).
pub(crate) async fn until(stop: Arc<AtomicBool>) {
    while !stop.load(Ordering::SeqCst) {
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
}

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
    let config = read_config(&args.config)?;
    let security = Security::load(&config.network)?;
    let envs = config.resolved_profile()?.envs; // also checks the config's values, the timeout among them
    // A write cut off by a kill leaves its temporary file; the snapshot itself is whole.
    if let Some(stale) = racetracks::files::remove_stale_temporary(&args.snapshot)? {
        eprintln!("taskctl: removed {}, left by a write that was cut off", stale.display());
    }
    let controller = if args.snapshot.exists() {
        let c = taskctl::TaskController::restore(&args.snapshot)?;
        eprintln!("taskctl: restored {} environments and {} switches from {}", c.len(), c.history().len(), args.snapshot.display());
        c
    } else {
        let c = config.task_controller(envs)?;
        c.snapshot(&args.snapshot)?;
        c
    };
    let stop = stop_flag()?;
    let tasks = Arc::new(
        taskctl::LocalTasks::new(controller, Some(args.snapshot.clone()))
            .release_after(Duration::from_secs_f64(config.learner.actor_timeout_seconds)),
    );
    let service = proto::task_grpc::TaskControllerService::new(tasks.clone());
    // Snapshots that keep failing (a full disk) refuse every report: stop rather than leave the
    // actors retrying forever; the supervisor then stops the run (exit code 3).
    let failing = Arc::new(std::sync::Mutex::new(None));
    let watcher = {
        let (stop, failing) = (stop.clone(), failing.clone());
        std::thread::spawn(move || {
            while !stop.load(Ordering::SeqCst) {
                let (count, last) = tasks.failed_snapshots();
                if count >= MAX_FAILED_SNAPSHOTS {
                    *failing.lock().unwrap_or_else(|e| e.into_inner()) = Some(runtime::TrainError::CheckpointsFailing { count, last });
                    stop.store(true, Ordering::SeqCst);
                }
                std::thread::sleep(Duration::from_millis(200));
            }
        })
    };
    eprintln!("taskctl: serving on {}", args.listen);
    let rt = async_runtime(1)?;
    spawn_health(&rt, args.health_listen, &["dronerace.v1.TaskController"], stop.clone())?;
    let served = rt.block_on(proto::task_grpc::serve(args.listen, &security, service, until(stop.clone())));
    stop.store(true, Ordering::SeqCst);
    let _ = watcher.join();
    if let Some(fatal) = failing.lock().unwrap_or_else(|e| e.into_inner()).take() {
        return Err(fatal.into());
    }
    served.map_err(|e| anyhow::anyhow!("taskctl on {}: {e}", args.listen))
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
    #[arg(long, value_enum, default_value_t = Transport::Shm)]
    transport: Transport,
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
    let config = read_config(&args.config)?;
    let (run, checkpoint) = Run::open_or_create(config, &args.out)?;
    let security = Security::load(&run.config().network)?;
    security.check_listen(&args.listen)?;
    let mut settings = run.config().learner;
    settings.expected_actors = args.actors.max(1);
    let stop = stop_flag()?;
    let rt = async_runtime(1)?;
    let tasks = match &args.taskctl {
        Some(url) => Some(TaskClient::new(rt.handle().clone(), url, &security)?),
        None => None,
    };
    let resumed = checkpoint.is_some();
    match args.transport {
        Transport::Grpc => {
            let shared = Arc::new(LearnerBoard::default());
            let (service, link) = LearnerService::with_rollouts(shared.clone(), settings.rollout_memory_mib << 20);
            let process = LearnerProcess::start(run, checkpoint.as_ref(), link, shared, settings)?;
            let server = serve_learner(&rt, args.listen, args.health_listen, &security, service, stop.clone())?;
            drive(process, resumed, &args, &stop, tasks.as_ref())?;
            finish_server(&rt, server, &stop);
        }
        Transport::Shm => {
            let shm = ShmConfig { run: args.shm_run.clone(), max_actors: args.actors.max(1) };
            let link = ShmLearnerLink::open(&shm)?;
            let shared = Arc::new(LearnerBoard::default());
            let service = LearnerService::status_only(shared.clone());
            let process = LearnerProcess::start(run, checkpoint.as_ref(), link, shared, settings)?;
            let server = serve_learner(&rt, args.listen, args.health_listen, &security, service, stop.clone())?;
            drive(process, resumed, &args, &stop, tasks.as_ref())?;
            finish_server(&rt, server, &stop);
        }
    }
    Ok(())
}

type ServerTask = tokio::task::JoinHandle<Result<(), tonic::transport::Error>>;

/// Serves the learner's gRPC services. Call it only once the learner process holds its
/// restored state: a Status answered earlier would report iteration 0 for a resumed run.
fn serve_learner(
    rt: &tokio::runtime::Runtime,
    addr: SocketAddr,
    health: Option<SocketAddr>,
    security: &Security,
    service: LearnerService,
    stop: Arc<AtomicBool>,
) -> anyhow::Result<ServerTask> {
    // Bind now, so a taken port is an error at start rather than a silent background failure.
    let listener = rt.block_on(tokio::net::TcpListener::bind(addr)).with_context(|| format!("learner: binding {addr}"))?;
    let router = rt
        .block_on(proto::with_discovery(security.server()?, &["dronerace.v1.Learner"], security.token_check()))
        .add_service(tonic::service::interceptor::InterceptedService::new(service.into_server(), security.token_check()));
    let incoming = {
        let _runtime = rt.enter();
        proto::listener::incoming(listener)
    };
    spawn_health(rt, health, &["dronerace.v1.Learner"], stop.clone())?;
    eprintln!("learner: serving on {addr}");
    Ok(rt.spawn(router.serve_with_incoming_shutdown(incoming, until(stop))))
}

fn finish_server(rt: &tokio::runtime::Runtime, server: ServerTask, stop: &AtomicBool) {
    stop.store(true, Ordering::SeqCst);
    let _ = rt.block_on(async { tokio::time::timeout(Duration::from_secs(5), server).await });
}

fn drive<L: LearnerLink>(
    mut process: LearnerProcess<L>,
    resumed: bool,
    args: &LearnerArgs,
    stop: &AtomicBool,
    tasks: Option<&TaskClient>,
) -> anyhow::Result<()> {
    let dir = process.run().dir().to_path_buf();
    let mut log = ProgressLog::open(&dir)?;
    eprintln!(
        "learner: {} run in {} at iteration {} ({} transport)",
        if resumed { "resuming the" } else { "starting a new" },
        dir.display(),
        process.run().iteration(),
        match args.transport {
            Transport::Shm => "iceoryx2",
            Transport::Grpc => "gRPC",
        }
    );
    let mut done = 0;
    while !process.finished() && !stop.load(Ordering::SeqCst) && args.iterations.is_none_or(|n| done < n) {
        let Some(s) = process.iteration_step(stop, tasks.map(|t| t as &dyn TaskService), &learner_only)? else { break };
        done += 1;
        super::report(&mut log, &progress_line(&s, process.eta_seconds()))?;
    }
    let path = process.checkpoint(&learner_only)?;
    eprintln!("learner: checkpoint written to {}", path.display());
    Ok(())
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
    #[arg(long, value_enum, default_value_t = Transport::Shm)]
    transport: Transport,
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
    let config = read_config(&args.config)?;
    anyhow::ensure!(args.envs > 0, "--envs must be at least 1");
    proto::transport::check_actor_name(&args.name).context("--name")?;
    let profile = config.resolved_profile()?;
    let security = Security::load(&config.network)?;
    if let Some(owner) = security.token_actor().filter(|owner| *owner != args.name) {
        anyhow::bail!(
            "network.token_file holds actor {owner:?}'s token, and this actor runs as {:?}: run it with --name {owner}, \
             or give it its own token (dronerace token --actor {})",
            args.name,
            args.name
        );
    }
    let rt = async_runtime(1)?;
    let tasks = TaskClient::new(rt.handle().clone(), &args.taskctl, &security)?;
    let settings = runtime::actor_process::ActorSettings {
        name: args.name.clone(),
        envs: args.envs,
        seed: config.seed,
        env: config.env,
        n_steps: profile.ppo.n_steps,
        weights_timeout: Duration::from_secs_f64(config.learner.actor_timeout_seconds.max(0.1)),
        max_rollouts: args.rollouts,
    };
    let stop = stop_flag()?;
    match args.transport {
        Transport::Grpc => {
            let mut link = GrpcActorLink::connect(rt.handle().clone(), &args.learner, &security)?;
            runtime::actor_process::run_actor(&settings, &mut link, &tasks, &stop)?;
        }
        Transport::Shm => {
            let mut link = ShmActorLink::open(&ShmConfig { run: args.shm_run.clone(), max_actors: args.max_actors.max(1) })?;
            runtime::actor_process::run_actor(&settings, &mut link, &tasks, &stop)?;
        }
    }
    Ok(())
}
