//! `dronerace chaos`: faults under sustained load. Runs `dronerace train` and kills (-9) one of
//! its processes — an actor, the learner or the task controller, chosen at random — every
//! `--every` seconds for `--minutes`; then stops the run as a user would (SIGINT) and audits it:
//! faults injected, iterations completed, rollouts refused by reason, task reports acknowledged
//! and lost, checkpoints readable, resident memory of each process at start and end, shared
//! memory left behind. Writes `<out>/chaos.json` and prints a table.

#![allow(clippy::print_stdout, clippy::print_stderr, reason = "a command whose output is its report")]

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use anyhow::Context;
use clap::Args;
use learner::checkpoint::Checkpoint;
use rand::{Rng, SeedableRng};
use serde::Serialize;

use super::processes::Transport;

/// Arguments of `dronerace chaos`.
#[derive(Args)]
pub struct ChaosArgs {
    /// Run configuration (TOML; default: the built-in defaults, i.e. the main job).
    #[arg(long)]
    config: Option<PathBuf>,
    /// Run directory (must not hold checkpoints yet); the audit goes to `<out>/chaos.json`.
    #[arg(long)]
    out: PathBuf,
    /// Seconds between two kills.
    #[arg(long, default_value_t = 20.0)]
    every: f64,
    /// Minutes of fault injection.
    #[arg(long, default_value_t = 30.0)]
    minutes: f64,
    /// Actor processes.
    #[arg(long, default_value_t = 2)]
    actors: usize,
    /// How rollouts travel.
    #[arg(long, value_enum, default_value_t = Transport::Shm)]
    transport: Transport,
    /// Seed of the choice of victims.
    #[arg(long, default_value_t = 0)]
    seed: u64,
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

fn shm_entries() -> Vec<String> {
    std::fs::read_dir("/dev/shm").map(|d| d.flatten().map(|e| e.file_name().to_string_lossy().into_owned()).collect()).unwrap_or_default()
}

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

/// Runs the chaos experiment.
pub fn run(args: ChaosArgs) -> anyhow::Result<()> {
    anyhow::ensure!(args.every > 0.0 && args.minutes > 0.0, "--every and --minutes must be positive");
    std::fs::create_dir_all(&args.out).with_context(|| format!("creating {}", args.out.display()))?;
    let log_path = args.out.join("chaos-train.log");
    let log = std::fs::File::create(&log_path).with_context(|| format!("creating {}", log_path.display()))?;
    let shm_before = shm_entries();
    let exe = std::env::current_exe().context("locating the dronerace executable")?;
    let mut command = Command::new(exe);
    command.arg("train").arg("--out").arg(&args.out).arg("--actors").arg(args.actors.to_string());
    command.arg("--transport").arg(match args.transport {
        Transport::Shm => "shm",
        Transport::Grpc => "grpc",
    });
    if let Some(config) = &args.config {
        command.arg("--config").arg(config);
    }
    let mut train = command.stdin(Stdio::null()).stdout(Stdio::null()).stderr(log).spawn().context("starting dronerace train")?;
    let supervisor = train.id();
    let expected = args.actors + 2;

    // Faults start once the run trains: every process up and a first iteration done.
    let deadline = Instant::now() + Duration::from_secs(300);
    while members(supervisor).len() < expected || last_iteration(&args.out) < 1 {
        anyhow::ensure!(train.try_wait()?.is_none(), "dronerace train exited before training; see {}", log_path.display());
        anyhow::ensure!(Instant::now() < deadline, "the run did not complete an iteration within 5 minutes; see {}", log_path.display());
        std::thread::sleep(Duration::from_millis(200));
    }
    let rss = |list: &[Member]| list.iter().filter_map(|m| Some((m.name.clone(), rss_mib(m.pid)?))).collect::<BTreeMap<_, _>>();
    let rss_start_mib = rss(&members(supervisor));
    let iteration_at_start = last_iteration(&args.out);
    eprintln!("chaos: killing one of {expected} processes every {} s for {} min", args.every, args.minutes);

    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(args.seed);
    let mut faults: BTreeMap<String, u32> = BTreeMap::new();
    let started = Instant::now();
    let until = started + Duration::from_secs_f64(args.minutes * 60.0);
    let mut next_kill = started + Duration::from_secs_f64(args.every);
    while Instant::now() < until {
        anyhow::ensure!(train.try_wait()?.is_none(), "the supervisor itself exited during the faults; see {}", log_path.display());
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
            next_kill += Duration::from_secs_f64(args.every);
        }
        std::thread::sleep(Duration::from_millis(100));
    }
    let seconds = started.elapsed().as_secs_f64();
    // Let the supervisor bring every process back before measuring and stopping.
    let settle = Instant::now() + Duration::from_secs(60);
    while members(supervisor).len() < expected && Instant::now() < settle {
        std::thread::sleep(Duration::from_millis(200));
    }
    let rss_end_mib = rss(&members(supervisor));
    // SAFETY: kill(2) on our own child.
    unsafe { libc::kill(supervisor as i32, libc::SIGINT) };
    let stop_deadline = Instant::now() + Duration::from_secs(180);
    let status = loop {
        if let Some(status) = train.try_wait()? {
            break Some(status);
        }
        if Instant::now() > stop_deadline {
            let _ = train.kill();
            let _ = train.wait();
            break None;
        }
        std::thread::sleep(Duration::from_millis(100));
    };

    let log_text = std::fs::read_to_string(&log_path).with_context(|| format!("reading {}", log_path.display()))?;
    let (refused_chunks, reports_lost) = audit_log(&log_text);
    let snapshot_path = args.out.join("taskctl.snapshot");
    let snapshot = taskctl::TaskController::restore(&snapshot_path)?;
    let reports_acknowledged = snapshot.actors().iter().map(|a| a.next_rollout).sum();
    let checkpoint_dir = args.out.join("checkpoints");
    let bins = |dir: &Path| -> Vec<PathBuf> {
        let files = std::fs::read_dir(dir).into_iter().flatten().flatten().map(|e| e.path());
        files.filter(|p| p.extension().is_some_and(|e| e == "bin")).collect()
    };
    let (periodic, policies): (Vec<PathBuf>, Vec<PathBuf>) = bins(&checkpoint_dir)
        .into_iter()
        .chain(bins(&checkpoint_dir.join("validated")))
        .partition(|p| p.file_name().and_then(|n| n.to_str()).is_some_and(|n| n.starts_with("ckpt-")));
    let restores = |p: &PathBuf| Checkpoint::read(p).ok().is_some_and(|c| learner::Learner::from_checkpoint(&c).is_ok());
    let checkpoints = periodic.len() + policies.len();
    let checkpoints_readable =
        periodic.iter().filter(|p| restores(p)).count() + policies.iter().filter(|p| learner::checkpoint::read_policy(p).is_ok()).count();
    let shm_left = shm_entries().into_iter().filter(|e| !shm_before.contains(e)).collect();
    let temporaries_left = [args.out.clone(), args.out.join("checkpoints")]
        .iter()
        .flat_map(|dir| std::fs::read_dir(dir).into_iter().flatten().flatten())
        .map(|e| e.path())
        .filter(|p| p.extension().is_some_and(|e| e == "tmp"))
        .map(|p| p.display().to_string())
        .collect();
    let report = ChaosReport {
        seconds,
        faults,
        iteration_at_start,
        iteration_at_end: last_iteration(&args.out),
        refused_chunks,
        reports_acknowledged,
        reports_lost,
        checkpoints,
        checkpoints_readable,
        rss_start_mib,
        rss_end_mib,
        clean_exit: status.is_some_and(|s| s.success()),
        shm_left,
        temporaries_left,
    };
    let json = serde_json::to_string_pretty(&report)?;
    let report_path = args.out.join("chaos.json");
    racetracks::files::write_atomic(&report_path, json.as_bytes()).with_context(|| format!("writing {}", report_path.display()))?;
    println!("{json}");
    anyhow::ensure!(report.reports_lost == 0, "{} acknowledged task reports were lost", report.reports_lost);
    anyhow::ensure!(report.checkpoints_readable == report.checkpoints, "unreadable checkpoints in {}", args.out.display());
    anyhow::ensure!(report.clean_exit, "the run did not stop cleanly after the faults; see {}", log_path.display());
    anyhow::ensure!(report.shm_left.is_empty(), "shared memory left behind: {:?}", report.shm_left);
    anyhow::ensure!(report.temporaries_left.is_empty(), "temporary files left behind: {:?}", report.temporaries_left);
    Ok(())
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
