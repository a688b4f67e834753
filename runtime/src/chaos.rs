//! Faults under sustained load (`dronerace chaos`): runs `dronerace train` and kills (-9) one
//! of its processes — an actor, the learner or the task controller, chosen at random — every
//! few seconds for minutes; then stops the run as a user would (SIGINT) and audits it: faults
//! injected, iterations completed, rollouts refused by reason, task reports acknowledged and
//! lost, checkpoints readable, resident memory of each process at start and end, shared memory
//! left behind.

#![allow(clippy::print_stderr, reason = "the chaos run's own terminal output: each fault as it is injected")]

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use learner::checkpoint::Checkpoint;
use rand::{Rng, SeedableRng};
use serde::Serialize;
use transport::Transport;

/// What a chaos run does (`dronerace chaos`'s flags).
#[derive(Clone, Debug, clap::Args)]
pub struct ChaosOptions {
    /// Run configuration (TOML; default: the built-in defaults, i.e. the main job).
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Run directory (must not hold checkpoints yet); the audit goes to `<out>/chaos.json`.
    #[arg(long)]
    pub out: PathBuf,
    /// Seconds between two kills.
    #[arg(long, default_value_t = 20.0)]
    pub every: f64,
    /// Minutes of fault injection.
    #[arg(long, default_value_t = 30.0)]
    pub minutes: f64,
    /// Actor processes.
    #[arg(long, default_value_t = 2)]
    pub actors: usize,
    /// How rollouts travel: `shm` (iceoryx2) or `grpc`.
    #[arg(long, default_value = "shm")]
    pub transport: Transport,
    /// Seed of the choice of victims.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
}

/// Why a chaos run could not be run, or what it found broken.
#[derive(Debug, thiserror::Error)]
pub enum ChaosError {
    /// A bad option.
    #[error("{0}")]
    Option(&'static str),
    /// A file, directory or process of the run.
    #[error("{what}: {source}")]
    Io {
        /// What was being done.
        what: String,
        /// What the system said.
        #[source]
        source: std::io::Error,
    },
    /// The run did not get going, or its supervisor died (its log names why).
    #[error("{what}; see {}", log.display())]
    Run {
        /// What happened.
        what: &'static str,
        /// The run's log.
        log: PathBuf,
    },
    /// The task controller's final snapshot.
    #[error(transparent)]
    Snapshot(#[from] taskctl::SnapshotError),
    /// The audit found something lost or left behind.
    #[error("the audit failed: {0}")]
    Audit(String),
}

/// An I/O error with what was being done.
fn io(what: impl Into<String>) -> impl FnOnce(std::io::Error) -> ChaosError {
    let what = what.into();
    move |source| ChaosError::Io { what, source }
}

/// What the chaos run found.
#[derive(Debug, Serialize)]
pub struct ChaosReport {
    /// Seconds of fault injection.
    pub seconds: f64,
    /// Kills per role (`taskctl`, `learner`, `actor`).
    pub faults: BTreeMap<String, u32>,
    /// Iteration the run had reached when the first fault was injected.
    pub iteration_at_start: u64,
    /// Iteration of the last metrics row when the run stopped.
    pub iteration_at_end: u64,
    /// Rollouts the learner refused, per reason.
    pub refused_chunks: BTreeMap<String, u64>,
    /// Task reports the controller acknowledged and kept (sum of every actor's next rollout in
    /// its final snapshot).
    pub reports_acknowledged: u64,
    /// Acknowledged reports the controller no longer had after a restart (must be 0).
    pub reports_lost: u64,
    /// Files of the run's `checkpoints/`: periodic checkpoints, `best.bin` and the validated
    /// policies.
    pub checkpoints: usize,
    /// Those that read back: periodic checkpoints restoring into a learner, the others as
    /// policies.
    pub checkpoints_readable: usize,
    /// Resident memory (MiB) per process when the faults began.
    pub rss_start_mib: BTreeMap<String, f64>,
    /// Resident memory (MiB) per process when they ended.
    pub rss_end_mib: BTreeMap<String, f64>,
    /// The supervisor exited with success after SIGINT.
    pub clean_exit: bool,
    /// /dev/shm entries created during the run and left after it.
    pub shm_left: Vec<String>,
    /// Temporary files of writes cut off by a kill, still in the run directory or its
    /// checkpoints after the stop (every restarted process removes its own).
    pub temporaries_left: Vec<String>,
}

/// A process of the run: its pid and role name (`taskctl`, `learner`, `actor-0`, …).
struct Member {
    pid: i32,
    name: String,
}

/// The supervisor's children, named by their subcommand (and `--name` for actors).
fn members(supervisor: u32) -> Vec<Member> {
    let Ok(entries) = std::fs::read_dir("/proc") else { return Vec::new() };
    let mut found = Vec::new();
    for entry in entries.flatten() {
        let Ok(pid) = entry.file_name().to_string_lossy().parse::<i32>() else { continue };
        let Ok(status) = std::fs::read_to_string(entry.path().join("status")) else { continue };
        let parent = status.lines().find_map(|l| l.strip_prefix("PPid:")).and_then(|p| p.trim().parse::<u32>().ok());
        if parent != Some(supervisor) {
            continue;
        }
        let Ok(cmdline) = std::fs::read(entry.path().join("cmdline")) else { continue };
        let args: Vec<String> = cmdline.split(|&b| b == 0).map(|a| String::from_utf8_lossy(a).into_owned()).collect();
        let name = match args.get(1).map(String::as_str) {
            Some("actor") => {
                args.iter().position(|a| a == "--name").and_then(|i| args.get(i + 1)).cloned().unwrap_or_else(|| "actor".into())
            }
            Some(role) => role.to_string(),
            None => continue,
        };
        found.push(Member { pid, name });
    }
    found.sort_by(|a, b| a.name.cmp(&b.name));
    found
}

/// Resident memory of `pid` in MiB.
fn rss_mib(pid: i32) -> Option<f64> {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).ok()?;
    let kib: f64 = status.lines().find_map(|l| l.strip_prefix("VmRSS:"))?.trim().trim_end_matches("kB").trim().parse().ok()?;
    Some(kib / 1024.0)
}

/// The entries of /dev/shm.
fn shm_entries() -> Vec<String> {
    std::fs::read_dir("/dev/shm").map(|d| d.flatten().map(|e| e.file_name().to_string_lossy().into_owned()).collect()).unwrap_or_default()
}

/// The iteration of the last row of the run's metrics.csv (0 before the first).
fn last_iteration(dir: &Path) -> u64 {
    let text = std::fs::read_to_string(dir.join("metrics.csv")).unwrap_or_default();
    text.lines().skip(1).filter_map(|l| l.split(',').next()?.parse().ok()).max().unwrap_or(0)
}

/// The value of `key=value` in a log line (tracing's field format).
fn field<'a>(line: &'a str, key: &str) -> Option<&'a str> {
    let start = line.find(&format!("{key}="))? + key.len() + 1;
    line[start..].split_whitespace().next().map(|v| v.trim_matches('"'))
}

/// Refusals per reason and lost reports, from the run's log.
fn audit_log(log: &str) -> (BTreeMap<String, u64>, u64) {
    let mut refused = BTreeMap::new();
    let mut lost = 0;
    for line in log.lines() {
        if line.contains("rollout not used") {
            *refused.entry(field(line, "reason").unwrap_or("unknown").to_string()).or_insert(0) += 1;
        }
        if line.contains("acknowledged reports lost") {
            lost += field(line, "lost").and_then(|n| n.parse::<u64>().ok()).unwrap_or(1);
        }
    }
    (refused, lost)
}

impl ChaosReport {
    /// Nothing lost or left behind: every acknowledged report kept, every checkpoint readable,
    /// a clean stop, no shared memory and no temporary files left.
    pub fn verdict(&self) -> Result<(), ChaosError> {
        let failed = |what: String| Err(ChaosError::Audit(what));
        if self.reports_lost > 0 {
            return failed(format!("{} acknowledged task reports were lost", self.reports_lost));
        }
        if self.checkpoints_readable != self.checkpoints {
            return failed(format!("{} of {} checkpoints are unreadable", self.checkpoints - self.checkpoints_readable, self.checkpoints));
        }
        if !self.clean_exit {
            return failed("the run did not stop cleanly after the faults".into());
        }
        if !self.shm_left.is_empty() {
            return failed(format!("shared memory left behind: {:?}", self.shm_left));
        }
        if !self.temporaries_left.is_empty() {
            return failed(format!("temporary files left behind: {:?}", self.temporaries_left));
        }
        Ok(())
    }
}

/// Runs the chaos experiment; its report is also written to `<out>/chaos.json`.
pub fn run(options: &ChaosOptions) -> Result<ChaosReport, ChaosError> {
    if !(options.every > 0.0 && options.minutes > 0.0) {
        return Err(ChaosError::Option("--every and --minutes must be positive"));
    }
    let out = &options.out;
    std::fs::create_dir_all(out).map_err(io(format!("creating {}", out.display())))?;
    let log_path = out.join("chaos-train.log");
    let shm_before = shm_entries();
    let mut train = start_training(options, &log_path)?;
    let supervisor = train.id();
    let expected = options.actors + 2;
    let failed = |what| ChaosError::Run { what, log: log_path.clone() };

    // Faults start once the run trains: every process up and a first iteration done.
    let deadline = Instant::now() + Duration::from_secs(300);
    while members(supervisor).len() < expected || last_iteration(out) < 1 {
        if !running(&mut train)? {
            return Err(failed("dronerace train exited before training"));
        }
        if Instant::now() >= deadline {
            return Err(failed("the run did not complete an iteration within 5 minutes"));
        }
        std::thread::sleep(Duration::from_millis(200));
    }
    let rss = |list: &[Member]| list.iter().filter_map(|m| Some((m.name.clone(), rss_mib(m.pid)?))).collect::<BTreeMap<_, _>>();
    let rss_start_mib = rss(&members(supervisor));
    let iteration_at_start = last_iteration(out);
    eprintln!("chaos: killing one of {expected} processes every {} s for {} min", options.every, options.minutes);
    let started = Instant::now();
    let faults = inject_faults(options, &mut train, &log_path)?;
    let seconds = started.elapsed().as_secs_f64();
    // Let the supervisor bring every process back before measuring and stopping.
    let settle = Instant::now() + Duration::from_secs(60);
    while members(supervisor).len() < expected && Instant::now() < settle {
        std::thread::sleep(Duration::from_millis(200));
    }
    let rss_end_mib = rss(&members(supervisor));
    let clean_exit = stop_training(&mut train)?;

    let log_text = std::fs::read_to_string(&log_path).map_err(io(format!("reading {}", log_path.display())))?;
    let (refused_chunks, reports_lost) = audit_log(&log_text);
    let snapshot = taskctl::TaskController::restore(&out.join("taskctl.snapshot"))?;
    let (checkpoints, checkpoints_readable) = audit_checkpoints(&out.join("checkpoints"));
    let report = ChaosReport {
        seconds,
        faults,
        iteration_at_start,
        iteration_at_end: last_iteration(out),
        refused_chunks,
        reports_acknowledged: snapshot.actors().iter().map(|a| a.next_rollout).sum(),
        reports_lost,
        checkpoints,
        checkpoints_readable,
        rss_start_mib,
        rss_end_mib,
        clean_exit,
        shm_left: shm_entries().into_iter().filter(|e| !shm_before.contains(e)).collect(),
        temporaries_left: temporaries(&[out.clone(), out.join("checkpoints")]),
    };
    let report_path = out.join("chaos.json");
    let json = serde_json::to_string_pretty(&report).map_err(|e| ChaosError::Audit(format!("serialising the report: {e}")))?;
    durable::write_atomic(&report_path, json.as_bytes()).map_err(io(format!("writing {}", report_path.display())))?;
    Ok(report)
}

/// `dronerace train` on the options' run, its messages into `log_path`.
fn start_training(options: &ChaosOptions, log_path: &Path) -> Result<Child, ChaosError> {
    let log = std::fs::File::create(log_path).map_err(io(format!("creating {}", log_path.display())))?;
    let exe = std::env::current_exe().map_err(io("locating the dronerace executable"))?;
    let mut command = Command::new(exe);
    command.arg("train").arg("--out").arg(&options.out).arg("--actors").arg(options.actors.to_string());
    command.arg("--transport").arg(options.transport.flag());
    if let Some(config) = &options.config {
        command.arg("--config").arg(config);
    }
    command.stdin(Stdio::null()).stdout(Stdio::null()).stderr(log).spawn().map_err(io("starting dronerace train"))
}

/// Whether the supervisor is still running.
fn running(train: &mut Child) -> Result<bool, ChaosError> {
    Ok(train.try_wait().map_err(io("waiting for dronerace train"))?.is_none())
}

/// Kills a random process of the run every `options.every` seconds for `options.minutes`;
/// the kills per role, or an error if the supervisor itself exited meanwhile.
fn inject_faults(options: &ChaosOptions, train: &mut Child, log_path: &Path) -> Result<BTreeMap<String, u32>, ChaosError> {
    let supervisor = train.id();
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(options.seed);
    let mut faults: BTreeMap<String, u32> = BTreeMap::new();
    let started = Instant::now();
    let until = started + Duration::from_secs_f64(options.minutes * 60.0);
    let mut next_kill = started + Duration::from_secs_f64(options.every);
    while Instant::now() < until {
        if !running(train)? {
            return Err(ChaosError::Run { what: "the supervisor itself exited during the faults", log: log_path.to_path_buf() });
        }
        if Instant::now() >= next_kill {
            let alive = members(supervisor);
            if !alive.is_empty() {
                let victim = &alive[rng.random_range(0..alive.len())];
                // SAFETY: kill(2) on a process this run started; no memory is involved.
                unsafe { libc::kill(victim.pid, libc::SIGKILL) };
                let role = if victim.name.starts_with("actor") { "actor" } else { victim.name.as_str() };
                *faults.entry(role.to_string()).or_insert(0) += 1;
                eprintln!("chaos: {:>6.1} s: killed {} (pid {})", started.elapsed().as_secs_f64(), victim.name, victim.pid);
            }
            next_kill += Duration::from_secs_f64(options.every);
        }
        std::thread::sleep(Duration::from_millis(100));
    }
    Ok(faults)
}

/// Stops the run as a user would (SIGINT; SIGKILL after 180 s); whether it exited with success.
fn stop_training(train: &mut Child) -> Result<bool, ChaosError> {
    // SAFETY: kill(2) on our own child.
    unsafe { libc::kill(train.id() as i32, libc::SIGINT) };
    let stop_deadline = Instant::now() + Duration::from_secs(180);
    loop {
        if let Some(status) = train.try_wait().map_err(io("waiting for dronerace train"))? {
            return Ok(status.success());
        }
        if Instant::now() > stop_deadline {
            let _ = train.kill();
            let _ = train.wait();
            return Ok(false);
        }
        std::thread::sleep(Duration::from_millis(100));
    }
}

/// The files of a run's `checkpoints/` (periodic checkpoints, `best.bin`, the validated
/// policies), and how many read back: periodic checkpoints restoring into a learner, the
/// others as policies.
fn audit_checkpoints(dir: &Path) -> (usize, usize) {
    let bins = |dir: &Path| -> Vec<PathBuf> {
        let files = std::fs::read_dir(dir).into_iter().flatten().flatten().map(|e| e.path());
        files.filter(|p| p.extension().is_some_and(|e| e == "bin")).collect()
    };
    let (periodic, policies): (Vec<PathBuf>, Vec<PathBuf>) = bins(dir)
        .into_iter()
        .chain(bins(&dir.join("validated")))
        .partition(|p| p.file_name().and_then(|n| n.to_str()).is_some_and(|n| n.starts_with("ckpt-")));
    let restores = |p: &PathBuf| Checkpoint::read(p).ok().is_some_and(|c| learner::Learner::from_checkpoint(&c).is_ok());
    let readable =
        periodic.iter().filter(|p| restores(p)).count() + policies.iter().filter(|p| learner::checkpoint::read_policy(p).is_ok()).count();
    (periodic.len() + policies.len(), readable)
}

/// Temporary files of cut-off writes in `dirs`.
fn temporaries(dirs: &[PathBuf]) -> Vec<String> {
    dirs.iter()
        .flat_map(|dir| std::fs::read_dir(dir).into_iter().flatten().flatten())
        .map(|e| e.path())
        .filter(|p| p.extension().is_some_and(|e| e == "tmp"))
        .map(|p| p.display().to_string())
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_log_audit_counts_refusals_by_reason_and_lost_reports() {
        let log = "\
2026 INFO runtime::learner_process: rollout not used: rollout of policy version 3 actor=a0 reason=wrong_version
2026 INFO runtime::learner_process: rollout not used: malformed rollout: x actor=a1 reason=malformed
2026 INFO runtime::learner_process: rollout not used: rollout of policy version 4 actor=a1 reason=wrong_version
2026 ERROR taskctl::controller: acknowledged reports lost actor=a0 lost=3
iter 5 | ...";
        let (refused, lost) = audit_log(log);
        assert_eq!(refused.get("wrong_version"), Some(&2));
        assert_eq!(refused.get("malformed"), Some(&1));
        assert_eq!(lost, 3);
    }
}
