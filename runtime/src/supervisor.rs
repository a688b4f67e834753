//! `dronerace train` on one machine: starts the task controller, the learner and N actor
//! processes (this executable's `taskctl`, `learner` and `actor` subcommands; iceoryx2 or gRPC
//! between actors and learner), supervises them — a crashed process is restarted and picks up
//! where it was (actors re-register, the learner resumes from its checkpoint, the task
//! controller from its snapshot) — and on a stop (Ctrl-C or SIGTERM, to it alone or to its
//! whole process group) stops them in order (actors, then the learner, which checkpoints, then
//! the task controller). Children run in process groups of their own, so only the supervisor
//! hears a terminal's Ctrl-C.

#![allow(clippy::print_stderr, reason = "the supervisor's own terminal output: what started, what it restarted")]

use std::net::{SocketAddr, TcpListener, TcpStream};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, ExitStatus, Stdio};
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use transport::Transport;

/// Why the supervisor could not start or keep a run's processes.
#[derive(Debug, thiserror::Error)]
pub enum SupervisorError {
    /// The plan asks for what cannot be run.
    #[error("{0}")]
    Plan(String),
    /// A process could not be started.
    #[error("starting dronerace {command}: {source}")]
    Start {
        /// Its arguments.
        command: String,
        /// What the system said.
        #[source]
        source: std::io::Error,
    },
    /// No local port could be had for the services.
    #[error("finding a free local port: {0}")]
    NoFreePort(#[source] std::io::Error),
    /// A service did not start serving.
    #[error("{process} did not serve on {addr}: {why}")]
    NotServing {
        /// The process.
        process: String,
        /// Its address.
        addr: SocketAddr,
        /// What happened instead.
        why: String,
    },
    /// A process kept failing as soon as it started.
    #[error(
        "{process} failed {MAX_QUICK_FAILURES} times in a row within {QUICK_FAILURE:?} of starting (last: {status}); see its messages above"
    )]
    FailingAtStart {
        /// The process.
        process: String,
        /// Its last exit.
        status: ExitStatus,
    },
    /// A process stopped for a reason a restart would only repeat ([`EXIT_FATAL`]).
    #[error("{0} stopped for a reason a restart would repeat (its message is above); the run stops")]
    Fatal(&'static str),
}

/// What the supervisor starts.
pub struct ClusterPlan {
    /// Run directory (holds config.toml, checkpoints, the task-controller snapshot).
    pub dir: PathBuf,
    /// Actor processes.
    pub actors: usize,
    /// Environments of the run (split over the actors).
    pub envs: usize,
    /// Rollout transport.
    pub transport: Transport,
    /// Stop after this many iterations.
    pub iterations: Option<u64>,
}

/// One supervised process: how to start it again, and the running child.
struct Supervised {
    name: String,
    args: Vec<String>,
    envs: Vec<(String, String)>,
    child: Child,
    /// Failures in a row, each within `QUICK_FAILURE` of its start.
    quick_failures: u32,
    started: Instant,
}

/// Exit code of a process that stopped for a reason its restart would only repeat (a
/// diverging run, a disk that takes no checkpoints or snapshots: [`crate::TrainError::is_fatal`]):
/// the supervisor stops the run instead of restarting it.
pub const EXIT_FATAL: u8 = 3;

/// A process that dies sooner than this after starting is failing at start (a bad config, a
/// taken port), not being killed at work.
const QUICK_FAILURE: Duration = Duration::from_secs(10);
/// Failures at start in a row before the supervisor gives up on a process.
const MAX_QUICK_FAILURES: u32 = 5;

/// Starts this executable again with `args` (a subcommand of `dronerace`) and `envs`.
fn spawn(args: &[String], envs: &[(String, String)]) -> Result<Child, SupervisorError> {
    let start = |source| SupervisorError::Start { command: args.join(" "), source };
    let exe = std::env::current_exe().map_err(start)?;
    let mut command = Command::new(exe);
    // A process group of its own: Ctrl-C in a terminal signals the whole foreground group, and
    // children that stopped on their own would look crashed and be restarted. Only the
    // supervisor hears it, and stops them in order.
    std::os::unix::process::CommandExt::process_group(command.args(args).stdin(Stdio::null()), 0);
    // A supervisor killed with -9 must not leave its children running unsupervised.
    #[cfg(target_os = "linux")]
    {
        use std::os::unix::process::CommandExt;
        // SAFETY: prctl is async-signal-safe; nothing else runs between fork and exec.
        unsafe {
            command.pre_exec(|| {
                if libc::prctl(libc::PR_SET_PDEATHSIG, libc::SIGTERM) != 0 {
                    return Err(std::io::Error::last_os_error());
                }
                Ok(())
            });
        }
    }
    for (k, v) in envs {
        command.env(k, v);
    }
    command.spawn().map_err(start)
}

impl Supervised {
    fn start(name: &str, args: Vec<String>, envs: Vec<(String, String)>) -> Result<Self, SupervisorError> {
        let child = spawn(&args, &envs)?;
        Ok(Self { name: name.into(), args, envs, child, quick_failures: 0, started: Instant::now() })
    }

    /// Starts the process again after it exited with `status`, at most once every 2 s (a
    /// process that fails at start must not be restarted in a busy loop). Gives up after
    /// [`MAX_QUICK_FAILURES`] failures at start in a row; a process killed after working for a
    /// while is restarted however often that happens.
    fn restart(&mut self, status: ExitStatus) -> Result<(), SupervisorError> {
        let lived = self.started.elapsed();
        self.quick_failures = if lived < QUICK_FAILURE { self.quick_failures + 1 } else { 0 };
        if self.quick_failures >= MAX_QUICK_FAILURES {
            return Err(SupervisorError::FailingAtStart { process: self.name.clone(), status });
        }
        std::thread::sleep(Duration::from_secs(2).saturating_sub(lived));
        self.started = Instant::now();
        self.child = spawn(&self.args, &self.envs)?;
        Ok(())
    }

    fn exited(&mut self) -> Option<ExitStatus> {
        self.child.try_wait().ok().flatten()
    }

    /// SIGINT, then SIGKILL if it has not exited within `grace`.
    fn stop(&mut self, grace: Duration) {
        if self.exited().is_some() {
            return;
        }
        // SAFETY: kill(2) on our own child's pid; no memory is involved.
        unsafe { libc::kill(self.child.id() as libc::pid_t, libc::SIGINT) };
        let deadline = Instant::now() + grace;
        while Instant::now() < deadline {
            if self.exited().is_some() {
                return;
            }
            std::thread::sleep(Duration::from_millis(50));
        }
        eprintln!("train: {} did not stop within {grace:?}; killing it", self.name);
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// Two distinct free local ports, for the task controller and the learner. Both listeners are
/// held until both ports are known: one dropped before the next bind lets the kernel hand the
/// same port out twice (seen in CI: the learner could not bind the task controller's port).
fn two_free_ports() -> Result<(SocketAddr, SocketAddr), SupervisorError> {
    let bind = || TcpListener::bind("127.0.0.1:0").map_err(SupervisorError::NoFreePort);
    let (first, second) = (bind()?, bind()?);
    Ok((first.local_addr().map_err(SupervisorError::NoFreePort)?, second.local_addr().map_err(SupervisorError::NoFreePort)?))
}

/// Waits up to 60 s for `process` to serve on `addr`.
fn wait_for_port(addr: SocketAddr, process: &mut Supervised) -> Result<(), SupervisorError> {
    let deadline = Instant::now() + Duration::from_secs(60);
    while TcpStream::connect_timeout(&addr, Duration::from_millis(200)).is_err() {
        let why = match process.exited() {
            Some(status) => format!("it exited ({status})"),
            None if Instant::now() >= deadline => "60 s passed".into(),
            None => {
                std::thread::sleep(Duration::from_millis(50));
                continue;
            }
        };
        return Err(SupervisorError::NotServing { process: process.name.clone(), addr, why });
    }
    Ok(())
}

/// An iceoryx2 run identifier for the run in `dir`, unique to this supervisor.
fn shm_run_id(dir: &Path) -> String {
    let base: String = dir
        .file_name()
        .map(|n| n.to_string_lossy().chars().map(|c| if c.is_ascii_alphanumeric() { c } else { '_' }).collect())
        .unwrap_or_else(|| "run".into());
    format!("{base}-{}", std::process::id())
}

/// The run's processes while they run.
struct Cluster {
    taskctl: Supervised,
    learner: Supervised,
    actors: Vec<Supervised>,
}

/// Starts and supervises the processes until the learner finishes or `stop`; then stops them
/// in order.
pub fn run(plan: ClusterPlan, stop: &AtomicBool) -> Result<(), SupervisorError> {
    if plan.actors == 0 || plan.actors > plan.envs {
        return Err(SupervisorError::Plan(format!("--actors {} must be from 1 to the {} environments of the run", plan.actors, plan.envs)));
    }
    let mut cluster = start(&plan)?;
    let outcome = supervise(&mut cluster, stop);
    for actor in &mut cluster.actors {
        actor.stop(Duration::from_secs(10));
    }
    cluster.learner.stop(Duration::from_secs(120));
    cluster.taskctl.stop(Duration::from_secs(10));
    if let Err(e) = transport::shm::cleanup_dead_nodes() {
        eprintln!("train: shared-memory cleanup: {e}");
    }
    outcome
}

/// Starts the task controller (and waits for it to serve), the learner and the actors.
fn start(plan: &ClusterPlan) -> Result<Cluster, SupervisorError> {
    let config = plan.dir.join("config.toml").display().to_string();
    let (taskctl_addr, learner_addr) = two_free_ports()?;
    let shm_run = shm_run_id(&plan.dir);
    let transport = plan.transport.flag();
    let s = |x: &str| x.to_string();
    let snapshot = plan.dir.join("taskctl.snapshot").display().to_string();
    let taskctl_args =
        vec![s("taskctl"), s("--config"), config.clone(), s("--listen"), taskctl_addr.to_string(), s("--snapshot"), snapshot];
    let mut taskctl = Supervised::start("taskctl", taskctl_args, vec![])?;
    wait_for_port(taskctl_addr, &mut taskctl)?;
    let mut learner_args = vec![
        s("learner"),
        s("--config"),
        config.clone(),
        s("--out"),
        plan.dir.display().to_string(),
        s("--listen"),
        learner_addr.to_string(),
        s("--transport"),
        s(transport),
        s("--shm-run"),
        shm_run.clone(),
        s("--actors"),
        plan.actors.to_string(),
        s("--taskctl"),
        format!("http://{taskctl_addr}"),
    ];
    if let Some(n) = plan.iterations {
        learner_args.extend([s("--iterations"), n.to_string()]);
    }
    let learner = Supervised::start("learner", learner_args, vec![])?;
    // Actors collect one after another with the learner idle, but at the same time as each other.
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    let threads = (cores / plan.actors).max(1).to_string();
    let mut actors = Vec::new();
    for i in 0..plan.actors {
        let envs = plan.envs / plan.actors + usize::from(i < plan.envs % plan.actors);
        let name = format!("actor-{i}");
        let args = vec![
            s("actor"),
            s("--config"),
            config.clone(),
            s("--name"),
            name.clone(),
            s("--envs"),
            envs.to_string(),
            s("--taskctl"),
            format!("http://{taskctl_addr}"),
            s("--transport"),
            s(transport),
            s("--learner"),
            format!("http://{learner_addr}"),
            s("--shm-run"),
            shm_run.clone(),
            s("--max-actors"),
            plan.actors.to_string(),
        ];
        actors.push(Supervised::start(&name, args, vec![(s("RAYON_NUM_THREADS"), threads.clone())])?);
    }
    eprintln!(
        "train: task controller on {taskctl_addr}, learner on {learner_addr}, {} actors over {}; Ctrl-C stops and checkpoints",
        plan.actors,
        plan.transport.label()
    );
    Ok(Cluster { taskctl, learner, actors })
}

/// Restarts whatever exits until the learner finishes, a process fails for good, or `stop`.
fn supervise(cluster: &mut Cluster, stop: &AtomicBool) -> Result<(), SupervisorError> {
    // An exit seen after a stop was requested is part of the stop, never a crash.
    let stopping = || stop.load(Ordering::SeqCst);
    while !stopping() {
        std::thread::sleep(Duration::from_millis(100));
        if stopping() {
            break;
        }
        if let Some(status) = cluster.learner.exited() {
            if status.success() {
                break;
            }
            if status.code() == Some(i32::from(EXIT_FATAL)) {
                return Err(SupervisorError::Fatal("the learner"));
            }
            eprintln!("train: the learner exited ({status}); restarting it from its checkpoint");
            cluster.learner.restart(status)?;
        }
        if let Some(status) = cluster.taskctl.exited() {
            if status.code() == Some(i32::from(EXIT_FATAL)) {
                return Err(SupervisorError::Fatal("the task controller"));
            }
            eprintln!("train: the task controller exited ({status}); restarting it from its snapshot");
            cluster.taskctl.restart(status)?;
        }
        for actor in &mut cluster.actors {
            if let Some(status) = actor.exited() {
                eprintln!("train: {} exited ({status}); restarting it", actor.name);
                actor.restart(status)?;
            }
        }
    }
    Ok(())
}
