//! The three processes of the distributed runtime with their servers: the task controller, the
//! learner and an actor, each started from its options and run until its stop flag rises (the
//! binary's `dronerace taskctl`, `learner` and `actor` parse those options; SIGINT or SIGTERM
//! raise the flag, and the learner checkpoints on the way out).

#![allow(clippy::print_stderr, reason = "the processes' own terminal output: what started, where it serves, what it restored")]

use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;

use taskctl::TaskService;
use transport::board::LearnerBoard;
use transport::grpc_link::{GrpcActorLink, LearnerService};
use transport::shm::{ShmActorLink, ShmConfig, ShmLearnerLink};
use transport::task_client::TaskClient;
use transport::{LearnerLink, Security, Transport};

use crate::learner_process::{LearnerProcess, learner_only};
use crate::progress::{ProgressLog, progress_line};
use crate::{ResolvedRun, Run, TrainConfig, TrainError};

/// Why a process of the runtime could not start or stopped on an error.
#[derive(Debug, thiserror::Error)]
pub enum ServiceError {
    /// The run: its config, checkpoints, training or the task controller's state.
    #[error(transparent)]
    Train(#[from] TrainError),
    /// TLS or token settings.
    #[error(transparent)]
    Security(#[from] transport::SecurityError),
    /// A rollout or weights transport.
    #[error(transparent)]
    Link(#[from] transport::LinkError),
    /// The task controller's state.
    #[error(transparent)]
    Task(#[from] taskctl::TaskError),
    /// The task controller's snapshot file.
    #[error(transparent)]
    Snapshot(#[from] taskctl::SnapshotError),
    /// The run's `train.log`.
    #[error(transparent)]
    Log(#[from] crate::progress::LogError),
    /// The actor's loop.
    #[error(transparent)]
    Actor(#[from] crate::actor_process::ActorProcessError),
    /// An option given to the process.
    #[error("{option}: {message}")]
    Option {
        /// The option, as the command line spells it.
        option: &'static str,
        /// What is wrong with it.
        message: String,
    },
    /// A port or file the process needs.
    #[error("{what}: {source}")]
    Io {
        /// What was being done (`binding 127.0.0.1:50051`).
        what: String,
        /// What the system said.
        #[source]
        source: std::io::Error,
    },
    /// A server that stopped on an error.
    #[error("{what}: {message}")]
    Serve {
        /// The server and its address.
        what: String,
        /// The transport's error.
        message: String,
    },
}

impl ServiceError {
    /// Whether a restart would only repeat it ([`TrainError::is_fatal`]): the process then
    /// exits with [`crate::supervisor::EXIT_FATAL`].
    pub fn is_fatal(&self) -> bool {
        matches!(self, ServiceError::Train(e) if e.is_fatal())
    }
}

/// The run configuration at `path`, or the defaults, resolved.
pub fn read_config(path: Option<&Path>) -> Result<ResolvedRun, TrainError> {
    match path {
        Some(p) => ResolvedRun::read(p),
        None => Ok(TrainConfig::default().resolve()?),
    }
}

/// A multi-threaded tokio runtime with `threads` workers.
pub fn async_runtime(threads: usize) -> Result<tokio::runtime::Runtime, ServiceError> {
    tokio::runtime::Builder::new_multi_thread()
        .worker_threads(threads)
        .enable_all()
        .build()
        .map_err(|source| ServiceError::Io { what: "starting the async runtime".into(), source })
}

/// `addr` bound now, so that a taken port is an error at start rather than a silent background
/// failure.
fn bind(rt: &tokio::runtime::Runtime, who: &str, addr: SocketAddr) -> Result<tokio::net::TcpListener, ServiceError> {
    rt.block_on(tokio::net::TcpListener::bind(addr)).map_err(|source| ServiceError::Io { what: format!("{who}: binding {addr}"), source })
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
) -> Result<(), ServiceError> {
    let Some(addr) = addr else { return Ok(()) };
    let listener = bind(rt, "health", addr)?;
    eprintln!("health (plaintext, for probes): serving on {addr}");
    rt.spawn(async move {
        if let Err(e) = transport::serve_health(listener, serving, until(stop)).await {
            tracing::error!("health server on {addr}: {e}");
        }
    });
    Ok(())
}

/// Resolves once `stop` is set (polled every 100 ms).
pub async fn until(stop: Arc<AtomicBool>) {
    while !stop.load(Ordering::SeqCst) {
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
}

/// What the task-controller process serves (`dronerace taskctl`'s flags).
#[derive(Clone, Debug, clap::Args)]
pub struct TaskctlOptions {
    /// Address to serve gRPC on.
    #[arg(long, default_value = "127.0.0.1:50051")]
    pub listen: SocketAddr,
    /// Snapshot file: restored at start when present, rewritten after every change.
    #[arg(long)]
    pub snapshot: PathBuf,
    /// Also serve gRPC health alone, in plaintext, here: for probes that cannot speak TLS.
    #[arg(long)]
    pub health_listen: Option<SocketAddr>,
}

/// Serves the task controller of the run `resolved` describes (tracks, generator, switching,
/// environment count, network) until `stop`.
pub fn taskctl(resolved: ResolvedRun, options: TaskctlOptions, stop: Arc<AtomicBool>) -> Result<(), ServiceError> {
    let TaskctlOptions { listen, snapshot, health_listen } = options;
    let config = resolved.config();
    let security = Security::load(&config.network)?;
    // A write cut off by a kill leaves its temporary file; the snapshot itself is whole.
    let stale = durable::remove_stale_temporary(&snapshot)
        .map_err(|source| ServiceError::Io { what: format!("cleaning up beside {}", snapshot.display()), source })?;
    if let Some(stale) = stale {
        eprintln!("taskctl: removed {}, left by a write that was cut off", stale.display());
    }
    let controller = if snapshot.exists() {
        let c = taskctl::TaskController::restore(&snapshot)?;
        eprintln!("taskctl: restored {} environments and {} switches from {}", c.len(), c.history().len(), snapshot.display());
        c
    } else {
        let c = resolved.task_controller()?;
        c.snapshot(&snapshot)?;
        c
    };
    let tasks = Arc::new(
        taskctl::LocalTasks::new(controller, Some(snapshot.clone()))
            .release_after(Duration::from_secs_f64(config.learner.actor_timeout_seconds)),
    );
    let service = transport::task_grpc::TaskControllerService::new(tasks.clone());
    // Snapshots that keep failing (a full disk) refuse every report: stop rather than leave the
    // actors retrying forever; the supervisor then stops the run (exit code 3).
    let failing = Arc::new(std::sync::Mutex::new(None));
    let watcher = {
        let (stop, failing) = (stop.clone(), failing.clone());
        std::thread::spawn(move || {
            while !stop.load(Ordering::SeqCst) {
                let (count, last) = tasks.failed_snapshots();
                if count >= MAX_FAILED_SNAPSHOTS {
                    *failing.lock().unwrap_or_else(|e| e.into_inner()) = Some(TrainError::CheckpointsFailing { count, last });
                    stop.store(true, Ordering::SeqCst);
                }
                std::thread::sleep(Duration::from_millis(200));
            }
        })
    };
    eprintln!("taskctl: serving on {listen}");
    let rt = async_runtime(1)?;
    spawn_health(&rt, health_listen, &["dronerace.v1.TaskController"], stop.clone())?;
    let served = rt.block_on(transport::task_grpc::serve(listen, &security, service, until(stop.clone())));
    stop.store(true, Ordering::SeqCst);
    let _ = watcher.join();
    if let Some(fatal) = failing.lock().unwrap_or_else(|e| e.into_inner()).take() {
        return Err(fatal.into());
    }
    served.map_err(|e| ServiceError::Serve { what: format!("taskctl on {listen}"), message: e.to_string() })
}

/// What the learner process serves and trains (`dronerace learner`'s flags).
#[derive(Clone, Debug, clap::Args)]
pub struct LearnerOptions {
    /// Run directory: a new run starts there, or the run there resumes from its newest checkpoint.
    #[arg(long)]
    pub out: PathBuf,
    /// Address to serve gRPC on (status, weights, and rollouts with `--transport grpc`).
    #[arg(long, default_value = "127.0.0.1:50052")]
    pub listen: SocketAddr,
    /// Also serve gRPC health alone, in plaintext, here (once the checkpoint is restored): for
    /// probes that cannot speak TLS.
    #[arg(long)]
    pub health_listen: Option<SocketAddr>,
    /// How rollouts arrive: `shm` (iceoryx2) or `grpc`.
    #[arg(long, default_value = "shm")]
    pub transport: Transport,
    /// iceoryx2 run identifier (with `--transport shm`).
    #[arg(long, default_value = "main")]
    pub shm_run: String,
    /// Actors the first iteration waits for.
    #[arg(long, default_value_t = 1)]
    pub actors: usize,
    /// Task controller address (for the switch count in the progress line).
    #[arg(long)]
    pub taskctl: Option<String>,
    /// Stop after this many iterations (a checkpoint is written on the way out).
    #[arg(long)]
    pub iterations: Option<u64>,
}

/// Runs the learner process until the budget is spent, `iterations` are done, or `stop`.
/// A new run starts from `resolved`; a run directory that holds a run keeps its own config.
pub fn learner(resolved: ResolvedRun, options: LearnerOptions, stop: Arc<AtomicBool>) -> Result<(), ServiceError> {
    let (run, checkpoint) = Run::open_or_create(resolved, &options.out)?;
    let security = Security::load(&run.config().network)?;
    security.check_listen(&options.listen)?;
    let mut settings = run.config().learner;
    settings.expected_actors = options.actors.max(1);
    let rt = async_runtime(1)?;
    let tasks = match &options.taskctl {
        Some(url) => Some(TaskClient::new(rt.handle().clone(), url, &security)?),
        None => None,
    };
    let resumed = checkpoint.is_some();
    let shared = Arc::new(LearnerBoard::default());
    match options.transport {
        Transport::Grpc => {
            let (service, link) = LearnerService::with_rollouts(shared.clone(), settings.rollout_memory_mib << 20);
            let process = LearnerProcess::start(run, checkpoint.as_ref(), link, shared, settings)?;
            serve_learner(&rt, &options, &security, service, stop.clone(), || drive(process, resumed, &options, &stop, tasks.as_ref()))
        }
        Transport::Shm => {
            let link = ShmLearnerLink::open(&ShmConfig { run: options.shm_run.clone(), max_actors: options.actors.max(1) })?;
            let service = LearnerService::status_only(shared.clone());
            let process = LearnerProcess::start(run, checkpoint.as_ref(), link, shared, settings)?;
            serve_learner(&rt, &options, &security, service, stop.clone(), || drive(process, resumed, &options, &stop, tasks.as_ref()))
        }
    }
}

/// Serves the learner's gRPC services while `train` runs, then stops them (5 s to finish).
/// Called only once the learner process holds its restored state: a Status answered earlier
/// would report iteration 0 for a resumed run.
fn serve_learner(
    rt: &tokio::runtime::Runtime,
    options: &LearnerOptions,
    security: &Security,
    service: LearnerService,
    stop: Arc<AtomicBool>,
    train: impl FnOnce() -> Result<(), ServiceError>,
) -> Result<(), ServiceError> {
    let listener = bind(rt, "learner", options.listen)?;
    let server = rt.spawn(transport::grpc_link::serve_learner(listener, security.clone(), service, until(stop.clone())));
    spawn_health(rt, options.health_listen, &["dronerace.v1.Learner"], stop.clone())?;
    eprintln!("learner: serving on {}", options.listen);
    let trained = train();
    stop.store(true, Ordering::SeqCst);
    let _ = rt.block_on(async { tokio::time::timeout(Duration::from_secs(5), server).await });
    trained
}

/// The learner's iterations until the budget, `options.iterations` or `stop`, then its checkpoint.
fn drive<L: LearnerLink>(
    mut process: LearnerProcess<L>,
    resumed: bool,
    options: &LearnerOptions,
    stop: &AtomicBool,
    tasks: Option<&TaskClient>,
) -> Result<(), ServiceError> {
    let dir = process.run().dir().to_path_buf();
    let mut log = ProgressLog::open(&dir)?;
    eprintln!(
        "learner: {} run in {} at iteration {} ({} transport)",
        if resumed { "resuming the" } else { "starting a new" },
        dir.display(),
        process.run().iteration(),
        options.transport.label()
    );
    let mut done = 0;
    while !process.finished() && !stop.load(Ordering::SeqCst) && options.iterations.is_none_or(|n| done < n) {
        let Some(s) = process.iteration_step(stop, tasks.map(|t| t as &dyn TaskService), &learner_only)? else { break };
        done += 1;
        log.report(&progress_line(&s, process.eta_seconds()))?;
    }
    let path = process.checkpoint(&learner_only)?;
    eprintln!("learner: checkpoint written to {}", path.display());
    Ok(())
}

/// What an actor process runs and where it sends its rollouts (`dronerace actor`'s flags).
#[derive(Clone, Debug, clap::Args)]
pub struct ActorOptions {
    /// Actor name (stable across restarts: it takes back its environments).
    #[arg(long)]
    pub name: String,
    /// Environments this actor runs.
    #[arg(long)]
    pub envs: usize,
    /// Task controller address.
    #[arg(long, default_value = "http://127.0.0.1:50051")]
    pub taskctl: String,
    /// How rollouts travel: `shm` (iceoryx2) or `grpc`.
    #[arg(long, default_value = "shm")]
    pub transport: Transport,
    /// Learner address (with `--transport grpc`).
    #[arg(long, default_value = "http://127.0.0.1:50052")]
    pub learner: String,
    /// iceoryx2 run identifier (with `--transport shm`).
    #[arg(long, default_value = "main")]
    pub shm_run: String,
    /// Most actors of the run on this machine (sizes the iceoryx2 services; same on all).
    #[arg(long, default_value_t = 1)]
    pub max_actors: usize,
    /// Stop after this many rollouts.
    #[arg(long)]
    pub rollouts: Option<u64>,
}

/// Runs one actor until `stop`.
/// The run `resolved` describes gives the environment, seed, n_steps and network settings.
pub fn actor(resolved: ResolvedRun, options: ActorOptions, stop: Arc<AtomicBool>) -> Result<(), ServiceError> {
    let option = |option, message: String| ServiceError::Option { option, message };
    if options.envs == 0 {
        return Err(option("--envs", "must be at least 1".into()));
    }
    transport::link::check_actor_name(&options.name).map_err(|e| option("--name", e.to_string()))?;
    let config = resolved.config();
    let security = Security::load(&config.network)?;
    if let Some(owner) = security.token_actor().filter(|owner| *owner != options.name) {
        let message = format!(
            "network.token_file holds actor {owner:?}'s token, and this actor runs as {:?}: run it with --name {owner}, \
             or give it its own token (dronerace token --actor {})",
            options.name, options.name
        );
        return Err(option("--name", message));
    }
    let rt = async_runtime(1)?;
    let tasks = TaskClient::new(rt.handle().clone(), &options.taskctl, &security)?;
    let settings =
        crate::actor_process::ActorSettings { max_rollouts: options.rollouts, ..resolved.actor_settings(&options.name, options.envs) };
    match options.transport {
        Transport::Grpc => {
            let mut link = GrpcActorLink::connect(rt.handle().clone(), &options.learner, &security)?;
            crate::actor_process::run_actor(&settings, &mut link, &tasks, &stop)?;
        }
        Transport::Shm => {
            let mut link = ShmActorLink::open(&ShmConfig { run: options.shm_run.clone(), max_actors: options.max_actors.max(1) })?;
            crate::actor_process::run_actor(&settings, &mut link, &tasks, &stop)?;
        }
    }
    Ok(())
}
