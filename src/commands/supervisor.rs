//! `dronerace train` on one machine: starts the task controller, the learner and N actor
//! processes (iceoryx2 between actors and learner), supervises them — a crashed process is
//! restarted and picks up where it was (actors re-register, the learner resumes from its
//! checkpoint, the task controller from its snapshot) — and on Ctrl-C or SIGTERM (to it alone
//! or to its whole process group) stops them in order (actors, then the learner, which
//! checkpoints, then the task controller). Children run in process groups of their own, so
//! only the supervisor hears a terminal's Ctrl-C.

#![allow(clippy::print_stderr, reason = "the process commands' own terminal output: what started, where it serves, what it restarted")]

use std::net::{SocketAddr, TcpListener, TcpStream};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, ExitStatus, Stdio};
use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};

use anyhow::Context;

use super::processes::Transport;
use crate::signal::stop_flag;

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
/// diverging run, a disk that takes no checkpoints or snapshots:
/// [`runtime::TrainError::is_fatal`]): the supervisor stops the run instead of restarting it.
pub const EXIT_FATAL: u8 = 3;

/// A process that dies sooner than this after starting is failing at start (a bad config, a
/// taken port), not being killed at work.
const QUICK_FAILURE: Duration = Duration::from_secs(10);
/// Failures at start in a row before the supervisor gives up on a process.
const MAX_QUICK_FAILURES: u32 = 5;

fn spawn(args: &[String], envs: &[(String, String)]) -> anyhow::Result<Child> {
    let exe = std::env::current_exe().context("locating the dronerace executable")?;
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
    command.spawn().with_context(|| format!("starting dronerace {}", args.join(" ")))
}

impl Supervised {
    fn start(name: &str, args: Vec<String>, envs: Vec<(String, String)>) -> anyhow::Result<Self> {
        let child = spawn(&args, &envs)?;
        Ok(Self { name: name.into(), args, envs, child, quick_failures: 0, started: Instant::now() })
    }

    /// Starts the process again after it exited with `status`, at most once every 2 s (a
    /// process that fails at start must not be restarted in a busy loop). Gives up after
    /// [`MAX_QUICK_FAILURES`] failures at start in a row; a process killed after working for a
    /// while is restarted however often that happens.
    fn restart(&mut self, status: ExitStatus) -> anyhow::Result<()> {
        let lived = self.started.elapsed();
        self.quick_failures = if lived < QUICK_FAILURE { self.quick_failures + 1 } else { 0 };
        anyhow::ensure!(
            self.quick_failures < MAX_QUICK_FAILURES,
            "{} failed {MAX_QUICK_FAILURES} times in a row within {QUICK_FAILURE:?} of starting (last: {status}); see its messages above",
            self.name
        );
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
fn two_free_ports() -> anyhow::Result<(SocketAddr, SocketAddr)> {
    let bind = || TcpListener::bind("127.0.0.1:0").context("finding a free local port");
    let (first, second) = (bind()?, bind()?);
    Ok((first.local_addr()?, second.local_addr()?))
}

fn wait_for_port(addr: SocketAddr, process: &mut Supervised) -> anyhow::Result<()> {
    let deadline = Instant::now() + Duration::from_secs(60);
    while TcpStream::connect_timeout(&addr, Duration::from_millis(200)).is_err() {
        if let Some(status) = process.exited() {
            anyhow::bail!("{} exited ({status}) before serving on {addr}", process.name);
        }
        anyhow::ensure!(Instant::now() < deadline, "{} did not serve on {addr} within 60 s", process.name);
        std::thread::sleep(Duration::from_millis(50));
    }
    Ok(())
}

fn shm_run_id(dir: &Path) -> String {
    let base: String = dir
        .file_name()
        .map(|n| n.to_string_lossy().chars().map(|c| if c.is_ascii_alphanumeric() { c } else { '_' }).collect())
        .unwrap_or_else(|| "run".into());
    format!("{base}-{}", std::process::id())
}

/// Starts and supervises the processes until the learner finishes or Ctrl-C.
pub fn run(plan: ClusterPlan) -> anyhow::Result<()> {
    anyhow::ensure!(plan.actors >= 1, "--actors must be at least 1");
    anyhow::ensure!(plan.actors <= plan.envs, "--actors {} exceeds the {} environments of the run", plan.actors, plan.envs);
    let stop = stop_flag()?;
    let config = plan.dir.join("config.toml").display().to_string();
    let (taskctl_addr, learner_addr) = two_free_ports()?;
    let shm_run = shm_run_id(&plan.dir);
    let transport = match plan.transport {
        Transport::Shm => "shm",
        Transport::Grpc => "grpc",
    };
    let s = |x: &str| x.to_string();

    let mut taskctl = Supervised::start(
        "taskctl",
        vec![
            s("taskctl"),
            s("--config"),
            config.clone(),
            s("--listen"),
            taskctl_addr.to_string(),
            s("--snapshot"),
            plan.dir.join("taskctl.snapshot").display().to_string(),
        ],
        vec![],
    )?;
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
    let mut learner = Supervised::start("learner", learner_args, vec![])?;
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
        if plan.transport == Transport::Shm { "iceoryx2" } else { "gRPC" }
    );

    let mut outcome = Ok(());
    // An exit seen after a stop was requested is part of the stop, never a crash.
    let stopping = || stop.load(Ordering::SeqCst);
    while !stopping() {
        std::thread::sleep(Duration::from_millis(100));
        if stopping() {
            break;
        }
        if let Some(status) = learner.exited() {
            if status.success() {
                break;
            }
            if status.code() == Some(i32::from(EXIT_FATAL)) {
                outcome =
                    Err(anyhow::anyhow!("the learner stopped for a reason a restart would repeat (its message is above); the run stops"));
                break;
            }
            eprintln!("train: the learner exited ({status}); restarting it from its checkpoint");
            if let Err(e) = learner.restart(status) {
                outcome = Err(e);
                break;
            }
        }
        if let Some(status) = taskctl.exited() {
            if status.code() == Some(i32::from(EXIT_FATAL)) {
                outcome = Err(anyhow::anyhow!(
                    "the task controller stopped for a reason a restart would repeat (its message is above); the run stops"
                ));
                break;
            }
            eprintln!("train: the task controller exited ({status}); restarting it from its snapshot");
            if let Err(e) = taskctl.restart(status) {
                outcome = Err(e);
                break;
            }
        }
        for actor in &mut actors {
            if let Some(status) = actor.exited() {
                eprintln!("train: {} exited ({status}); restarting it", actor.name);
                if let Err(e) = actor.restart(status) {
                    outcome = Err(e);
                    break;
                }
            }
        }
        if outcome.is_err() {
            break;
        }
    }
    for actor in &mut actors {
        actor.stop(Duration::from_secs(10));
    }
    learner.stop(Duration::from_secs(120));
    taskctl.stop(Duration::from_secs(10));
    if let Err(e) = proto::shm::cleanup_dead_nodes() {
        eprintln!("train: shared-memory cleanup: {e}");
    }
    outcome
}
