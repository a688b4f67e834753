//! Starting and watching dronerace processes from tests.

#![allow(dead_code)]

pub mod certificates;
pub mod prerequisites;

use std::fs::File;
use std::net::TcpListener;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::{Mutex, MutexGuard};
use std::time::{Duration, Instant};

use proto::v1;
use transport::Security;

/// Tests that start processes or touch /dev/shm run one at a time.
pub fn serial() -> MutexGuard<'static, ()> {
    static LOCK: Mutex<()> = Mutex::new(());
    LOCK.lock().unwrap_or_else(|e| e.into_inner())
}

/// A free local TCP port.
pub fn free_port() -> u16 {
    TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port()
}

/// Two distinct free local ports, both held until both are known (one dropped before the next
/// bind lets the kernel hand the same port out twice).
pub fn two_free_ports() -> (std::net::SocketAddr, std::net::SocketAddr) {
    let (first, second) = (TcpListener::bind("127.0.0.1:0").unwrap(), TcpListener::bind("127.0.0.1:0").unwrap());
    (first.local_addr().unwrap(), second.local_addr().unwrap())
}

/// A tiny run: 8 environments, 32-step rollouts, 1 epoch, a checkpoint every iteration, a
/// 3 s actor timeout; `extra` is appended to the TOML.
pub fn write_config(dir: &Path, extra: &str) -> PathBuf {
    let path = dir.join("cluster.toml");
    let text = format!(
        r#"name = "cluster"
profile = "cpu"
total_env_steps = 10000000
seed = 5
envs = 8
checkpoint_every = 1

[ppo]
n_steps = 32
batch_size = 64
n_epochs = 1

[switching]
window = 3

[learner]
actor_timeout_seconds = 3.0
{extra}"#
    );
    std::fs::write(&path, text).unwrap();
    path
}

/// A dronerace process whose stderr goes to `<dir>/<name>.log`; killed when dropped.
pub struct Proc {
    pub name: String,
    pub child: Child,
    pub log: PathBuf,
}

impl Proc {
    /// Starts `dronerace args…` (prefixed by `wrapper`, e.g. `ip netns exec ns`).
    pub fn start_wrapped(dir: &Path, name: &str, wrapper: &[&str], args: &[String]) -> Self {
        let log = dir.join(format!("{name}.log"));
        let err = File::options().create(true).append(true).open(&log).unwrap();
        let exe = env!("CARGO_BIN_EXE_dronerace");
        let mut command = if wrapper.is_empty() {
            Command::new(exe)
        } else {
            let mut c = Command::new(wrapper[0]);
            c.args(&wrapper[1..]).arg(exe);
            c
        };
        // A process group of its own, as a shell gives a foreground job: tests can signal the
        // group as a terminal's Ctrl-C does, without signalling the test harness.
        std::os::unix::process::CommandExt::process_group(&mut command, 0);
        let child = command.args(args).stdin(Stdio::null()).stdout(Stdio::null()).stderr(err).spawn().unwrap();
        Self { name: name.into(), child, log }
    }

    /// Starts `dronerace args…`.
    pub fn start(dir: &Path, name: &str, args: &[String]) -> Self {
        Self::start_wrapped(dir, name, &[], args)
    }

    /// kill -9.
    pub fn kill9(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }

    /// SIGINT, then waits for the exit status.
    pub fn interrupt(&mut self) -> std::process::ExitStatus {
        // SAFETY: kill(2) on our own child.
        unsafe { libc::kill(self.child.id() as libc::pid_t, libc::SIGINT) };
        self.child.wait().unwrap()
    }

    /// Sends `signal` to the process alone, or to its whole process group (a terminal's
    /// Ctrl-C), then waits for the exit status.
    pub fn signal(&mut self, signal: libc::c_int, whole_group: bool) -> std::process::ExitStatus {
        let pid = self.child.id() as libc::pid_t;
        // SAFETY: kill(2) on our own child or on the process group it leads.
        unsafe { libc::kill(if whole_group { -pid } else { pid }, signal) };
        self.child.wait().unwrap()
    }

    /// Waits up to `limit` for the exit, panicking with the log otherwise.
    pub fn wait_exit(&mut self, limit: Duration) -> std::process::ExitStatus {
        let deadline = Instant::now() + limit;
        loop {
            if let Some(status) = self.child.try_wait().unwrap() {
                return status;
            }
            assert!(Instant::now() < deadline, "{} did not exit within {limit:?}:\n{}", self.name, self.output());
            std::thread::sleep(Duration::from_millis(100));
        }
    }

    /// Still running?
    pub fn running(&mut self) -> bool {
        self.child.try_wait().unwrap().is_none()
    }

    /// What it wrote to stderr so far.
    pub fn output(&self) -> String {
        std::fs::read_to_string(&self.log).unwrap_or_default()
    }
}

impl Drop for Proc {
    /// SIGINT and a moment to shut down cleanly (releasing shared memory), then SIGKILL.
    fn drop(&mut self) {
        if self.running() {
            // SAFETY: kill(2) on our own child.
            unsafe { libc::kill(self.child.id() as libc::pid_t, libc::SIGINT) };
            let deadline = Instant::now() + Duration::from_secs(10);
            while self.running() && Instant::now() < deadline {
                std::thread::sleep(Duration::from_millis(20));
            }
        }
        let _ = self.child.kill();
        let _ = self.child.wait();
        // Whatever a killed process left behind.
        let _ = transport::shm::cleanup_dead_nodes();
    }
}

/// Waits up to `limit` for `ready`, panicking with `what` and the logs otherwise.
pub fn wait_until(limit: Duration, what: &str, procs: &[&Proc], mut ready: impl FnMut() -> bool) {
    let deadline = Instant::now() + limit;
    while Instant::now() < deadline {
        if ready() {
            return;
        }
        std::thread::sleep(Duration::from_millis(100));
    }
    let logs: Vec<String> = procs.iter().map(|p| format!("--- {} ---\n{}", p.name, p.output())).collect();
    panic!("timed out waiting for {what}\n{}", logs.join("\n"));
}

/// gRPC clients of a learner and a task controller.
pub struct Clients {
    pub rt: tokio::runtime::Runtime,
    pub security: Security,
}

impl Clients {
    pub fn new(security: Security) -> Self {
        let rt = tokio::runtime::Builder::new_multi_thread().worker_threads(1).enable_all().build().unwrap();
        Self { rt, security }
    }

    /// The learner's status, if it answers.
    pub fn status(&self, url: &str) -> Option<v1::StatusResponse> {
        let _guard = self.rt.enter();
        let mut client = transport::grpc_link::learner_client(url, &self.security).ok()?;
        let call = tokio::time::timeout(Duration::from_secs(2), client.status(v1::StatusRequest {}));
        self.rt.block_on(call).ok()?.ok().map(|r| r.into_inner())
    }

    /// A task-controller client.
    pub fn tasks(&self, url: &str) -> transport::task_client::TaskClient {
        transport::task_client::TaskClient::new(self.rt.handle().clone(), url, &self.security).unwrap()
    }
}

/// iceoryx2 files in shared memory.
pub fn shm_files() -> Vec<String> {
    let mut names: Vec<String> = std::fs::read_dir("/dev/shm")
        .map(|d| d.filter_map(|e| e.ok()).map(|e| e.file_name().to_string_lossy().into_owned()).filter(|n| n.starts_with("iox2")).collect())
        .unwrap_or_default();
    names.sort();
    names
}

/// Rows of a run's metrics.csv as (iteration, env_steps). The learner may be appending while
/// this reads: a last line without its newline is not a row yet.
pub fn metrics_rows(dir: &Path) -> Vec<(u64, u64)> {
    let text = std::fs::read_to_string(dir.join("metrics.csv")).unwrap_or_default();
    let complete = &text[..text.rfind('\n').map_or(0, |end| end + 1)];
    complete
        .lines()
        .skip(1)
        .map(|l| {
            let mut f = l.split(',');
            (f.next().unwrap().parse().unwrap(), f.next().unwrap().parse().unwrap())
        })
        .collect()
}

/// Command-line arguments from string slices.
pub fn args(a: &[&str]) -> Vec<String> {
    a.iter().map(|s| s.to_string()).collect()
}
