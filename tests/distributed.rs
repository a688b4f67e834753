//! The distributed runtime end to end: real taskctl, learner and actor processes over
//! iceoryx2 and gRPC, killed with -9 and restarted, and refusing bad input.

// Test code: a panic is how a failure is reported.
#![allow(clippy::unwrap_used, clippy::expect_used, clippy::print_stdout, clippy::print_stderr)]

mod support;

use std::path::Path;
use std::time::Duration;

use support::*;
use taskctl::TaskService;

const MINUTE: Duration = Duration::from_secs(60);

/// `dronerace train` with 2 actor processes for 3 iterations over `transport`; returns what
/// each iteration learnt (metrics.csv without its timing columns).
fn one_command_run(transport: &str) -> Vec<Vec<String>> {
    let _serial = serial();
    let tmp = tempfile::tempdir().unwrap();
    let config = write_config(tmp.path(), "");
    let out = tmp.path().join("run");
    let shm_before = shm_files();
    let mut train = Proc::start(
        tmp.path(),
        "train",
        &args(&[
            "train",
            "--config",
            config.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
            "--actors",
            "2",
            "--iterations",
            "3",
            "--transport",
            transport,
        ]),
    );
    let status = train.wait_exit(3 * MINUTE);
    let log = train.output();
    assert!(status.success(), "train failed:\n{log}");
    let rows = metrics_rows(&out);
    assert_eq!(rows.iter().map(|r| r.0).collect::<Vec<_>>(), vec![1, 2, 3], "{log}");
    // Both actors' rollouts (4 environments × 32 steps each) went into every update.
    assert_eq!(rows.last().unwrap().1, 3 * 8 * 32, "{log}");
    assert!(out.join("checkpoints").read_dir().unwrap().count() >= 2);
    assert!(out.join("taskctl.snapshot").exists());
    let left: Vec<String> = shm_files().into_iter().filter(|f| !shm_before.contains(f)).collect();
    assert!(left.is_empty(), "shared memory left behind after a clean shutdown: {left:?}");
    learnt(&out)
}

/// metrics.csv's cells but for those read off a clock: `wall_seconds`, `charts/SPS`, and the
/// task controller's `tasks/*` summary, taken when the update ends, while reports still arrive.
fn learnt(run: &Path) -> Vec<Vec<String>> {
    let text = std::fs::read_to_string(run.join("metrics.csv")).unwrap();
    let mut lines = text.lines().map(|l| l.split(',').map(str::to_string).collect::<Vec<_>>());
    let header = lines.next().unwrap();
    let timing = |i: usize| matches!(header[i].as_str(), "wall_seconds" | "charts/SPS") || header[i].starts_with("tasks/");
    lines.map(|row| row.into_iter().enumerate().filter(|(i, _)| !timing(*i)).map(|(_, c)| c).collect()).collect()
}

/// The learner updates on the actors' rollouts in environment order, not in the order they
/// arrive or the actors registered, and the transport only carries bytes: so the same seed
/// learns the same, bit for bit, over either.
#[test]
fn two_actor_processes_learn_the_same_over_iceoryx2_and_grpc() {
    let shm = one_command_run("shm");
    let grpc = one_command_run("grpc");
    assert_eq!(shm, grpc);
}

/// Processes whose command line mentions `needle`.
fn processes_mentioning(needle: &str) -> Vec<String> {
    std::fs::read_dir("/proc")
        .unwrap()
        .filter_map(|e| std::fs::read(e.ok()?.path().join("cmdline")).ok())
        .map(|c| String::from_utf8_lossy(&c).replace('\0', " "))
        .filter(|c| c.contains(needle))
        .collect()
}

/// Starts `dronerace train`, stops it with `signal` (to the supervisor alone or to its whole
/// process group, as a terminal's Ctrl-C does) and checks one clean stop: no restart, one
/// checkpoint of the last iteration, every process gone, no shared memory left.
fn stops_cleanly(signal: libc::c_int, whole_group: bool) {
    let _serial = serial();
    let tmp = tempfile::tempdir().unwrap();
    let config = write_config(tmp.path(), "");
    let out = tmp.path().join("run");
    let shm_before = shm_files();
    let mut train = Proc::start(
        tmp.path(),
        "train",
        &args(&["train", "--config", config.to_str().unwrap(), "--out", out.to_str().unwrap(), "--actors", "2"]),
    );
    wait_until(2 * MINUTE, "two iterations", &[&train], || metrics_rows(&out).len() >= 2);
    // The supervisor, the task controller, the learner and two actors all name the run directory.
    assert_eq!(processes_mentioning(out.to_str().unwrap()).len(), 5, "{:?}", processes_mentioning(out.to_str().unwrap()));
    let status = train.signal(signal, whole_group);
    let log = train.output();
    assert!(status.success(), "{log}");
    assert!(!log.contains("restarting") && !log.contains("exited ("), "a shutdown looked like a crash:\n{log}");
    assert_eq!(log.matches("learner: checkpoint written").count(), 1, "one checkpoint, on the way out:\n{log}");
    let last = metrics_rows(&out).last().unwrap().0;
    assert!(out.join(format!("checkpoints/ckpt-{last:09}.bin")).exists(), "the checkpoint of iteration {last}:\n{log}");
    assert!(processes_mentioning(out.to_str().unwrap()).is_empty(), "processes left running");
    let left: Vec<String> = shm_files().into_iter().filter(|f| !shm_before.contains(f)).collect();
    assert!(left.is_empty(), "shared memory left behind: {left:?}");
}

#[test]
fn ctrl_c_to_the_supervisor_checkpoints_and_stops_every_process_leaving_no_shared_memory() {
    stops_cleanly(libc::SIGINT, false);
}

#[test]
fn ctrl_c_in_a_terminal_signals_the_whole_group_and_still_stops_once_without_restarts() {
    stops_cleanly(libc::SIGINT, true);
}

#[test]
fn sigterm_to_the_whole_group_stops_once_without_restarts() {
    stops_cleanly(libc::SIGTERM, true);
}

#[test]
fn sigterm_to_the_supervisor_stops_once_without_restarts() {
    stops_cleanly(libc::SIGTERM, false);
}

/// The chaos command's CI version: one minute of kill -9 every 6 s under training load.
#[test]
fn a_short_chaos_run_loses_no_report_and_leaves_readable_checkpoints_and_no_shared_memory() {
    let _serial = serial();
    let tmp = tempfile::tempdir().unwrap();
    let config = write_config(tmp.path(), "");
    let out = tmp.path().join("run");
    let mut chaos = Proc::start(
        tmp.path(),
        "chaos",
        &args(&[
            "chaos",
            "--config",
            config.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
            "--minutes",
            "1",
            "--every",
            "6",
            "--seed",
            "3",
        ]),
    );
    let status = chaos.wait_exit(6 * MINUTE);
    let log = format!("{}\n{}", chaos.output(), std::fs::read_to_string(out.join("chaos-train.log")).unwrap_or_default());
    assert!(status.success(), "{log}");
    let report: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(out.join("chaos.json")).unwrap()).unwrap();
    let faults: u64 = report["faults"].as_object().unwrap().values().map(|n| n.as_u64().unwrap()).sum();
    assert!(faults >= 9, "{report}");
    assert_eq!(report["reports_lost"], 0, "{report}");
    assert!(report["reports_acknowledged"].as_u64().unwrap() > 0, "{report}");
    assert!(report["checkpoints"].as_u64().unwrap() >= 1, "{report}");
    assert_eq!(report["checkpoints_readable"], report["checkpoints"], "{report}");
    assert_eq!(report["clean_exit"], true, "{report}");
    assert_eq!(report["shm_left"].as_array().unwrap().len(), 0, "{report}");
    assert!(report["iteration_at_end"].as_u64() > report["iteration_at_start"].as_u64(), "training went on under the faults: {report}");
}

/// Hand-started processes of one run (so tests can kill and restart each).
struct Cluster {
    dir: std::path::PathBuf,
    config: String,
    out: String,
    taskctl_addr: String,
    learner_addr: String,
    transport: &'static str,
    shm_run: String,
}

impl Cluster {
    fn new(dir: &Path, transport: &'static str, extra: &str) -> Self {
        // The supervisor's own choice of ports, which holds both listeners until both are known.
        let (taskctl_addr, learner_addr) = support::two_free_ports();
        Self {
            dir: dir.to_path_buf(),
            config: write_config(dir, extra).display().to_string(),
            out: dir.join("run").display().to_string(),
            taskctl_addr: taskctl_addr.to_string(),
            learner_addr: learner_addr.to_string(),
            transport,
            shm_run: {
                // Each cluster gets its own services, whatever earlier tests left behind.
                static COUNT: std::sync::atomic::AtomicUsize = std::sync::atomic::AtomicUsize::new(0);
                format!("test-{}-{}", std::process::id(), COUNT.fetch_add(1, std::sync::atomic::Ordering::SeqCst))
            },
        }
    }

    fn taskctl(&self) -> Proc {
        let snapshot = self.dir.join("taskctl.snapshot").display().to_string();
        Proc::start(
            &self.dir,
            "taskctl",
            &args(&["taskctl", "--config", &self.config, "--listen", &self.taskctl_addr, "--snapshot", &snapshot]),
        )
    }

    fn learner(&self) -> Proc {
        Proc::start(
            &self.dir,
            "learner",
            &args(&[
                "learner",
                "--config",
                &self.config,
                "--out",
                &self.out,
                "--listen",
                &self.learner_addr,
                "--transport",
                self.transport,
                "--shm-run",
                &self.shm_run,
                "--actors",
                "2",
                "--taskctl",
                &self.taskctl_url(),
            ]),
        )
    }

    fn actor(&self, name: &str) -> Proc {
        Proc::start(
            &self.dir,
            name,
            &args(&[
                "actor",
                "--config",
                &self.config,
                "--name",
                name,
                "--envs",
                "4",
                "--taskctl",
                &self.taskctl_url(),
                "--transport",
                self.transport,
                "--learner",
                &self.learner_url(),
                "--shm-run",
                &self.shm_run,
                "--max-actors",
                "2",
            ]),
        )
    }

    fn taskctl_url(&self) -> String {
        format!("http://{}", self.taskctl_addr)
    }

    fn learner_url(&self) -> String {
        format!("http://{}", self.learner_addr)
    }
}

fn iteration(clients: &Clients, c: &Cluster) -> u64 {
    clients.status(&c.learner_url()).map_or(0, |s| s.iteration)
}

#[test]
fn an_actor_killed_mid_rollout_is_dropped_and_a_restarted_one_rejoins() {
    let _serial = serial();
    let tmp = tempfile::tempdir().unwrap();
    let c = Cluster::new(tmp.path(), "grpc", "");
    let clients = Clients::new(transport::Security::default());
    let _taskctl = c.taskctl();
    let learner = c.learner();
    let a0 = c.actor("a0");
    let mut a1 = c.actor("a1");
    wait_until(2 * MINUTE, "iteration 3", &[&learner, &a0, &a1], || iteration(&clients, &c) >= 3);
    a1.kill9();
    let killed_at = iteration(&clients, &c);
    // Training goes on with a0 alone once a1 has missed the timeout.
    wait_until(MINUTE, "5 iterations after the kill", &[&learner, &a0], || iteration(&clients, &c) >= killed_at + 5);
    let status = clients.status(&c.learner_url()).unwrap();
    assert_eq!(status.connected_actors, vec!["a0".to_string()]);
    assert!(learner.output().contains("dropping actor a1"), "{}", learner.output());
    // `dronerace status` prints the same from the command line.
    let cli = std::process::Command::new(env!("CARGO_BIN_EXE_dronerace")).args(["status", "--learner", &c.learner_url()]).output().unwrap();
    let printed = String::from_utf8_lossy(&cli.stdout);
    assert!(
        cli.status.success() && printed.lines().any(|l| l == "connected actors a0"),
        "{printed}{}",
        String::from_utf8_lossy(&cli.stderr)
    );
    // A restarted a1 takes back its environments and rejoins.
    let a1 = c.actor("a1");
    wait_until(MINUTE, "a1 to rejoin", &[&learner, &a0, &a1], || {
        clients.status(&c.learner_url()).is_some_and(|s| s.connected_actors.len() == 2)
    });
    // Log lines carry timestamps: compare what follows "environments".
    let ranges: Vec<String> = a1.output().lines().filter_map(|l| l.split_once(": environments ").map(|(_, r)| r.to_string())).collect();
    assert_eq!(ranges.len(), 2, "{}", a1.output());
    assert_eq!(ranges[0], ranges[1], "the restarted actor got other environments");
    // Every update used whole rollouts only: each step of env_steps is one or two whole chunks
    // (4 environments × 32 steps), never a part of one.
    let rows = metrics_rows(tmp.path().join("run").as_path());
    let mut previous = 0;
    for (i, steps) in rows {
        let delta = steps - previous;
        assert!(delta == 128 || delta == 256, "iteration {i} trained on {delta} transitions");
        previous = steps;
    }
}

#[test]
fn a_killed_learner_resumes_from_its_checkpoint_and_the_running_actors_reconnect() {
    let _serial = serial();
    let tmp = tempfile::tempdir().unwrap();
    let c = Cluster::new(tmp.path(), "shm", "");
    let clients = Clients::new(transport::Security::default());
    let _taskctl = c.taskctl();
    let mut learner = c.learner();
    let mut a0 = c.actor("a0");
    let mut a1 = c.actor("a1");
    wait_until(2 * MINUTE, "iteration 4", &[&learner, &a0, &a1], || iteration(&clients, &c) >= 4);
    let before = clients.status(&c.learner_url()).unwrap();
    learner.kill9();
    let checkpointed = metrics_rows(tmp.path().join("run").as_path()).len() as u64;
    let learner = c.learner();
    wait_until(MINUTE, "the restarted learner to answer", &[&learner], || clients.status(&c.learner_url()).is_some());
    let after = clients.status(&c.learner_url()).unwrap();
    assert_ne!(after.learner_epoch, before.learner_epoch);
    assert!(
        after.iteration + 1 >= checkpointed && after.iteration >= 3,
        "resumed at {} (checkpoints up to {checkpointed})",
        after.iteration
    );
    let resumed_at = after.iteration;
    // The same actor processes (never restarted) feed the new learner.
    wait_until(MINUTE, "3 iterations with the new learner", &[&learner, &a0, &a1], || iteration(&clients, &c) >= resumed_at + 3);
    assert!(a0.running() && a1.running());
    assert_eq!(clients.status(&c.learner_url()).unwrap().connected_actors.len(), 2);
    assert!(learner.output().contains("resuming the run"), "{}", learner.output());
}

#[test]
fn a_killed_task_controller_restores_its_snapshot_and_loses_no_report() {
    let _serial = serial();
    let tmp = tempfile::tempdir().unwrap();
    let c = Cluster::new(tmp.path(), "shm", "");
    let clients = Clients::new(transport::Security::default());
    let mut taskctl = c.taskctl();
    let learner = c.learner();
    let a0 = c.actor("a0");
    let a1 = c.actor("a1");
    wait_until(2 * MINUTE, "iteration 5", &[&learner, &a0, &a1], || iteration(&clients, &c) >= 5);
    let tasks = clients.tasks(&c.taskctl_url());
    taskctl.kill9();
    // What the dead controller had acknowledged is in its snapshot (written before each answer).
    let acknowledged = taskctl::TaskController::restore(&tmp.path().join("taskctl.snapshot")).unwrap();
    let taskctl = c.taskctl();
    wait_until(MINUTE, "the restarted task controller", &[&taskctl], || tasks.tasks().is_ok());
    let restored = tasks.tasks().unwrap();
    assert_eq!(restored.len(), 8);
    for (slot, task) in acknowledged.slots().iter().zip(&restored) {
        assert!(task.last_rollout >= slot.last_iteration, "env {}: {:?} < {:?}", task.env, task.last_rollout, slot.last_iteration);
        assert!(task.switches >= slot.switches);
    }
    // Reporting goes on: every environment gets newer reports, and training continues.
    let at = iteration(&clients, &c);
    wait_until(MINUTE, "new reports and iterations", &[&taskctl, &learner, &a0, &a1], || {
        let now = tasks.tasks().unwrap_or_default();
        iteration(&clients, &c) >= at + 3 && now.iter().zip(acknowledged.slots()).all(|(t, s)| t.last_rollout > s.last_iteration)
    });
    // The command-line view of the same state: one row per environment, with its actor.
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_dronerace")).args(["tasks", "--taskctl", &c.taskctl_url()]).output().unwrap();
    let table = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    assert_eq!(table.lines().filter(|l| l.contains(" a0 ") || l.contains(" a1 ")).count(), 8, "{table}");
}

#[test]
fn bad_messages_are_refused_with_a_clear_status() {
    use proto::v1;
    let _serial = serial();
    let tmp = tempfile::tempdir().unwrap();
    std::fs::write(tmp.path().join("token"), "t0ken\n").unwrap();
    let token = tmp.path().join("token").display().to_string();
    let c = Cluster::new(tmp.path(), "grpc", &format!("\n[network]\ntoken_file = {token:?}\n"));
    let _taskctl = c.taskctl();
    let learner = c.learner();
    let authed = Clients::new(
        transport::Security::load(&transport::NetworkConfig { token_file: Some(token.clone().into()), ..Default::default() }).unwrap(),
    );
    let anonymous = Clients::new(transport::Security::default());
    // The server answers Status while the learner is still starting (with epoch 0); rollouts
    // are admitted once it has published its first weights and set its epoch.
    wait_until(MINUTE, "the learner", &[&learner], || authed.status(&c.learner_url()).is_some_and(|s| s.learner_epoch != 0));

    wait_until(MINUTE, "the task controller", &[&learner], || authed.tasks(&c.taskctl_url()).tasks().is_ok());

    // Missing and wrong tokens.
    std::fs::write(tmp.path().join("wrong"), "t0keN\n").unwrap();
    let wrong_token = transport::NetworkConfig { token_file: Some(tmp.path().join("wrong")), ..Default::default() };
    let wrong = Clients::new(transport::Security::load(&wrong_token).unwrap());
    for clients in [&anonymous, &wrong] {
        let _g = clients.rt.enter();
        let mut learner_client = transport::grpc_link::learner_client(&c.learner_url(), &clients.security).unwrap();
        let e = clients.rt.block_on(learner_client.status(v1::StatusRequest {})).unwrap_err();
        assert_eq!(e.code(), tonic::Code::Unauthenticated, "{e:?}");
        let e = clients.tasks(&c.taskctl_url()).tasks().unwrap_err();
        assert!(!e.is_transient() && e.to_string().contains("Unauthenticated"), "{e:?}");
    }

    let status = authed.status(&c.learner_url()).unwrap();
    let push = |parts: Vec<v1::RolloutPart>| {
        let _g = authed.rt.enter();
        // The client's own limit would stop an oversized message before the server sees it.
        let client = transport::grpc_link::learner_client(&c.learner_url(), &authed.security).unwrap();
        let mut client = client.max_encoding_message_size(64 << 20);
        authed.rt.block_on(client.push_rollouts(tokio_stream::iter(parts))).map(|r| r.into_inner().accepted)
    };
    let part = |data: Vec<u8>, epoch: u64, version: u64| v1::RolloutPart {
        actor: "probe".into(),
        learner_epoch: epoch,
        policy_version: version,
        part: 0,
        parts: 1,
        data: data.into(),
    };
    // Rows of the run's own observation length, so that only what each probe breaks is wrong.
    let observation_dim = runtime::ResolvedRun::read(Path::new(&c.config)).unwrap().learner().architecture.observation_dim;
    let chunk = |version: u64, first_env: usize, poison: bool| {
        let mut chunk = rollout::RolloutChunk::zeroed(version, first_env, 2, 3, observation_dim, sim::ACTION_DIM);
        if poison {
            chunk.observations[5] = f32::NAN;
        }
        chunk.to_bytes()
    };
    let (epoch, version) = (status.learner_epoch, status.iteration);
    let code = |r: Result<u64, tonic::Status>| r.unwrap_err().code();
    assert_eq!(code(push(vec![part(b"garbage".to_vec(), epoch, version)])), tonic::Code::InvalidArgument, "malformed");
    assert_eq!(code(push(vec![part(chunk(version, 0, true), epoch, version)])), tonic::Code::InvalidArgument, "NaN");
    assert_eq!(code(push(vec![part(chunk(version, 7, false), epoch, version)])), tonic::Code::InvalidArgument, "unknown envs");
    assert_eq!(code(push(vec![part(chunk(version + 5, 0, false), epoch, version + 5)])), tonic::Code::FailedPrecondition, "future version");
    assert_eq!(code(push(vec![part(chunk(version, 0, false), epoch ^ 1, version)])), tonic::Code::FailedPrecondition, "other epoch");
    let oversized = vec![0u8; transport::security::MAX_MESSAGE_BYTES + 1024];
    assert_eq!(code(push(vec![part(oversized, epoch, version)])), tonic::Code::OutOfRange, "oversized");
    let mut split = part(chunk(version, 0, false), epoch, version);
    split.parts = 2;
    assert_eq!(code(push(vec![split])), tonic::Code::InvalidArgument, "a stream ending inside a rollout");
    // A well-formed rollout of the current version is accepted, and the learner is still up.
    assert_eq!(push(vec![part(chunk(version, 0, false), epoch, version)]).unwrap(), 1);
    assert!(authed.status(&c.learner_url()).unwrap().refused_chunks >= 5);

    // The task controller refuses bad reports with statuses naming the problem.
    let tasks = authed.tasks(&c.taskctl_url());
    tasks.register("probe", 2).unwrap();
    // Refusals come back permanent, with the status and the controller's reason.
    let refused = |r: Result<Vec<_>, taskctl::TaskServiceError>| {
        let e = r.unwrap_err();
        assert!(!e.is_transient(), "{e}");
        e.to_string()
    };
    assert!(refused(tasks.report("nobody", 0, &[1.0])).contains("NotFound"));
    let e = refused(tasks.report("probe", 0, &[1.0]));
    assert!(e.contains("InvalidArgument") && e.contains("2 environments but reported 1 rewards"), "{e}");
    assert!(refused(tasks.report("probe", 0, &[1.0, f64::INFINITY])).contains("InvalidArgument"));
    assert!(tasks.register("bad name!", 1).unwrap_err().to_string().contains("InvalidArgument"));
    assert!(tasks.register("greedy", 100).unwrap_err().to_string().contains("ResourceExhausted"));
    tasks.report("probe", 0, &[1.0, 2.0]).unwrap();
    assert!(refused(tasks.report("probe", 0, &[1.0, 2.0])).contains("AlreadyExists"), "a repeated rollout");
}
