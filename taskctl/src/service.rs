//! The curriculum as a service: what actors, the learner and `dronerace tasks` ask of the task
//! controller, with no transport in sight. [`LocalTasks`] serves it in a process; the gRPC
//! adapter (`transport::task_grpc`) puts a `LocalTasks` on the network and `transport::task_client::TaskClient`
//! implements the same trait on the caller's side, so a loop written against [`TaskService`]
//! runs unchanged in one process or across machines.

use std::path::PathBuf;
use std::sync::Arc;

use parking_lot::Mutex;
use sim::Track;
use tokio::sync::broadcast;

use crate::controller::{ActorRange, SwitchEvent, TaskController, TaskError};

/// An actor's environments as the task controller assigned them.
#[derive(Clone, Debug)]
pub struct Registration {
    /// Global index of the first environment.
    pub first_env: usize,
    /// Their current tracks.
    pub tracks: Vec<Arc<Track>>,
    /// Rollout index of the next report.
    pub next_rollout: u64,
}

/// One environment's task as the controller sees it.
#[derive(Clone, Debug, PartialEq)]
pub struct TaskInfo {
    /// Global environment index.
    pub env: usize,
    /// The actor running it (`None` while no actor has registered it).
    pub actor: Option<String>,
    /// Its current track.
    pub track: Arc<Track>,
    /// Rewards in its switching window.
    pub window_length: usize,
    /// ρ after its last report.
    pub rho: Option<f64>,
    /// q after its last report.
    pub q: Option<f64>,
    /// Switches so far.
    pub switches: u32,
    /// Last rollout reported for it.
    pub last_rollout: Option<u64>,
}

/// Counts over all environments (what a progress line shows; no tracks travel).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Summary {
    /// Environments.
    pub envs: usize,
    /// Switches so far.
    pub switches: u64,
    /// Mean flatness score q (`None` before the first report).
    pub mean_q: Option<f64>,
}

/// A change of the curriculum, as watchers see it.
#[derive(Clone, Debug, PartialEq)]
pub enum TaskEvent {
    /// An actor registered (or came back) and holds this range.
    Registered(ActorRange),
    /// An environment switched track.
    Switched(SwitchEvent),
}

/// Why a call failed; [`TaskServiceError::is_transient`] says whether trying again can help.
#[derive(Debug, thiserror::Error)]
pub enum TaskServiceError {
    /// The controller refused the request; it will refuse it again.
    #[error(transparent)]
    Refused(#[from] TaskError),
    /// A remote controller refused the request (its reason as it sent it); permanent.
    #[error("task controller: {0}")]
    RefusedRemotely(String),
    /// The change could not be made durable, so it was not made; the disk may recover.
    #[error("task controller snapshot {file}: {source}")]
    Snapshot {
        /// The snapshot file.
        file: PathBuf,
        /// The underlying error.
        source: std::io::Error,
    },
    /// The controller is unreachable, restarting or slow: the same call may succeed later.
    #[error("task controller unavailable: {0}")]
    Unavailable(String),
    /// An answer that does not decode (a version mismatch or a bug); permanent.
    #[error("task controller answer: {0}")]
    BadAnswer(String),
}

impl TaskServiceError {
    /// True when the same call may succeed later (retry rules use this, never status codes).
    pub fn is_transient(&self) -> bool {
        matches!(self, Self::Unavailable(_) | Self::Snapshot { .. })
    }
}

/// The task controller's operations, whatever carries them.
pub trait TaskService: Send + Sync {
    /// Registers actor `actor` with `envs` environments (or gives back its earlier range).
    fn register(&self, actor: &str, envs: usize) -> Result<Registration, TaskServiceError>;
    /// Takes one rollout's cumulative rewards; returns `(global env, new track)` switches.
    fn report(&self, actor: &str, rollout: u64, rewards: &[f64]) -> Result<Vec<(usize, Arc<Track>)>, TaskServiceError>;
    /// One environment's task.
    fn task(&self, env: usize) -> Result<TaskInfo, TaskServiceError>;
    /// Every environment's task.
    fn tasks(&self) -> Result<Vec<TaskInfo>, TaskServiceError>;
    /// Counts over all environments.
    fn summary(&self) -> Result<Summary, TaskServiceError>;
    /// Switches from index `from` on, oldest first.
    fn switch_history(&self, from: u64) -> Result<Vec<SwitchEvent>, TaskServiceError>;
}

/// A [`TaskController`] served in this process: changes are serialised by a lock that a panic
/// cannot poison, and, with a snapshot file, written to it before they are visible or answered
/// (so nothing acknowledged is lost when the process dies). Calls block (lock, fsync): async
/// callers run them on the blocking pool.
pub struct LocalTasks {
    controller: Mutex<TaskController>,
    snapshot: Option<PathBuf>,
    events: broadcast::Sender<TaskEvent>,
    /// When each actor last registered or reported (actors of a restored snapshot: when this
    /// service started), and after how long without either its range may go to another actor.
    contacts: Mutex<std::collections::HashMap<String, std::time::Instant>>,
    release_after: Option<std::time::Duration>,
    started: std::time::Instant,
    /// Snapshot writes that failed in a row, and the last failure.
    failed_snapshots: Mutex<(u32, String)>,
}

impl LocalTasks {
    /// Serves `controller`; `snapshot` is where every change is persisted (`None`: the caller
    /// persists the state itself, e.g. inside a training checkpoint).
    pub fn new(controller: TaskController, snapshot: Option<PathBuf>) -> Self {
        Self {
            controller: Mutex::new(controller),
            snapshot,
            events: broadcast::channel(1024).0,
            contacts: Mutex::default(),
            release_after: None,
            started: std::time::Instant::now(),
            failed_snapshots: Mutex::new((0, String::new())),
        }
    }

    /// Snapshot writes that failed in a row (each refused its change), and the last error: a
    /// process serving this can stop once the disk clearly will not take them (a full disk).
    pub fn failed_snapshots(&self) -> (u32, String) {
        self.failed_snapshots.lock().clone()
    }

    /// Lets a registration that finds no room take the ranges of actors silent for longer than
    /// `after` (the run's actor timeout): an actor that is gone for good, or renamed, does not
    /// hold its environments forever. A live actor is never disturbed unless another needs
    /// the room; if it comes back, it registers again.
    pub fn release_after(mut self, after: std::time::Duration) -> Self {
        self.release_after = Some(after);
        self
    }

    /// Notes a sign of life from `actor` if it is registered: names from refused calls are
    /// never kept, so what a client sends cannot grow this map beyond the registered actors.
    fn touch(&self, actor: &str) {
        if self.read(|c| c.actors().iter().any(|a| a.actor == actor)) {
            self.contacts.lock().insert(actor.to_string(), std::time::Instant::now());
        }
    }

    /// Actors silent for longer than the release time, other than `asking`.
    fn gone(&self, asking: &str) -> Vec<String> {
        let Some(after) = self.release_after else { return Vec::new() };
        let contacts = self.contacts.lock();
        self.read(|c| c.actors().iter().map(|a| a.actor.clone()).collect::<Vec<_>>())
            .into_iter()
            .filter(|a| a != asking && contacts.get(a).copied().unwrap_or(self.started).elapsed() > after)
            .collect()
    }

    /// Every change from now on.
    pub fn subscribe(&self) -> broadcast::Receiver<TaskEvent> {
        self.events.subscribe()
    }

    /// Reads the controller under the lock.
    pub fn read<T>(&self, f: impl FnOnce(&TaskController) -> T) -> T {
        f(&self.controller.lock())
    }

    /// Applies `change` to a copy, persists the copy, then makes it current: a change is either
    /// durable and visible, or neither. A panic inside `change` leaves the state as it was.
    fn change<T>(&self, change: impl FnOnce(&mut TaskController) -> Result<T, TaskError>) -> Result<T, TaskServiceError> {
        let mut guard = self.controller.lock();
        let mut next = guard.clone();
        let out = change(&mut next)?;
        if let Some(file) = &self.snapshot {
            let written = durable::write_atomic(file, &next.to_snapshot_bytes());
            let mut failed = self.failed_snapshots.lock();
            match written {
                Ok(()) => failed.0 = 0,
                Err(source) => {
                    *failed = (failed.0 + 1, format!("{}: {source}", file.display()));
                    return Err(TaskServiceError::Snapshot { file: file.clone(), source });
                }
            }
        }
        *guard = next;
        Ok(out)
    }

    fn info(c: &TaskController, env: usize) -> Result<TaskInfo, TaskServiceError> {
        let slot = c.slots().get(env).ok_or(TaskError::UnknownEnv { env, envs: c.len() })?;
        let actor = c.actors().iter().find(|a| (a.first_env..a.first_env + a.envs).contains(&env));
        Ok(TaskInfo {
            env,
            actor: actor.map(|a| a.actor.clone()),
            track: slot.track.clone(),
            window_length: slot.window.len(),
            rho: slot.rho,
            q: slot.q,
            switches: slot.switches,
            last_rollout: slot.last_iteration,
        })
    }
}

impl TaskService for LocalTasks {
    fn register(&self, actor: &str, envs: usize) -> Result<Registration, TaskServiceError> {
        let gone = self.gone(actor);
        let (range, tracks) = self.change(|c| {
            let range = match c.register(actor, envs) {
                Err(TaskError::NoRoom { .. }) if !gone.is_empty() => {
                    for a in &gone {
                        if let Some(r) = c.release(a) {
                            tracing::warn!(
                                "actor {a} silent beyond the actor timeout: environments {}..{} released",
                                r.first_env,
                                r.first_env + r.envs
                            );
                        }
                    }
                    c.register(actor, envs)?
                }
                other => other?,
            };
            let tracks = c.slots()[range.first_env..range.first_env + range.envs].iter().map(|s| s.track.clone()).collect();
            Ok((range, tracks))
        })?;
        // Forget the contacts of actors no longer registered (those released just now).
        self.contacts.lock().retain(|name, _| self.read(|c| c.actors().iter().any(|a| &a.actor == name)));
        self.touch(actor);
        let registration = Registration { first_env: range.first_env, tracks, next_rollout: range.next_rollout };
        // Nobody watching is not an error.
        let _ = self.events.send(TaskEvent::Registered(range));
        Ok(registration)
    }

    fn report(&self, actor: &str, rollout: u64, rewards: &[f64]) -> Result<Vec<(usize, Arc<Track>)>, TaskServiceError> {
        let changed = self.change(|c| {
            let before = c.history().len();
            let switches = c.report_rollout(actor, rollout, rewards)?;
            Ok((switches, c.history()[before..].to_vec()))
        });
        // A refused report from a registered actor is still a sign of life.
        self.touch(actor);
        let (switches, events) = changed?;
        for e in events {
            let _ = self.events.send(TaskEvent::Switched(e));
        }
        Ok(switches)
    }

    fn task(&self, env: usize) -> Result<TaskInfo, TaskServiceError> {
        self.read(|c| Self::info(c, env))
    }

    fn tasks(&self) -> Result<Vec<TaskInfo>, TaskServiceError> {
        self.read(|c| (0..c.len()).map(|env| Self::info(c, env)).collect())
    }

    fn summary(&self) -> Result<Summary, TaskServiceError> {
        Ok(self.read(|c| Summary { envs: c.len(), switches: c.history().len() as u64, mean_q: c.mean_q() }))
    }

    fn switch_history(&self, from: u64) -> Result<Vec<SwitchEvent>, TaskServiceError> {
        Ok(self.read(|c| c.history().iter().skip(usize::try_from(from).unwrap_or(usize::MAX)).cloned().collect()))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::switching::{SwitchParams, SwitchPolicy};
    use racetracks::generator::TrackGenerator;

    fn controller(envs: usize, policy: SwitchPolicy) -> TaskController {
        let switching = SwitchParams { policy, random_probability: 0.5, ..SwitchParams::default() };
        TaskController::new(envs, TrackGenerator::default(), switching, 5).unwrap()
    }

    /// A change that panics must leave the service usable: the lock is not poisoned, the state
    /// is the one before the failed change, and later changes persist.
    #[test]
    fn a_change_that_panics_does_not_break_the_ones_after() {
        let dir = tempfile::tempdir().unwrap();
        let snapshot = dir.path().join("snapshot");
        let tasks = LocalTasks::new(controller(4, SwitchPolicy::None), Some(snapshot.clone()));
        let crashed = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
            tasks.change(|c| -> Result<(), TaskError> {
                c.register("half-done", 2)?;
                panic!("handler bug")
            })
        }));
        assert!(crashed.is_err());
        assert!(tasks.read(|c| c.actors().is_empty()), "the panicking change was not applied");
        let registered = tasks.register("a", 4).unwrap();
        assert_eq!((registered.first_env, registered.tracks.len()), (0, 4));
        assert_eq!(tasks.summary().unwrap(), Summary { envs: 4, switches: 0, mean_q: None });
        assert_eq!(TaskController::restore(&snapshot).unwrap().actors().len(), 1, "the change after the panic was persisted");
    }

    /// Refused reports kept their senders' names for good (80 reports with 3.9 MB names took
    /// taskctl from 12 to 337 MiB): only registered actors' names are kept now.
    #[test]
    fn refused_reports_keep_nothing_of_their_senders() {
        let tasks = LocalTasks::new(controller(4, SwitchPolicy::None), None);
        tasks.register("a", 2).unwrap();
        for i in 0..80 {
            let name = format!("{i}{}", "x".repeat(100_000));
            assert!(tasks.report(&name, 0, &[1.0, 1.0]).is_err());
        }
        assert!(tasks.report("a", 0, &[1.0, 1.0]).is_ok());
        let kept: Vec<String> = tasks.contacts.lock().keys().cloned().collect();
        assert_eq!(kept, ["a"]);
    }

    #[test]
    fn an_actor_silent_beyond_the_timeout_gives_its_range_to_one_that_needs_room() {
        let tasks = LocalTasks::new(controller(4, SwitchPolicy::Random), None).release_after(std::time::Duration::from_millis(50));
        tasks.register("a", 2).unwrap();
        tasks.register("b", 2).unwrap();
        assert!(tasks.register("c", 2).is_err(), "both live: no room");
        std::thread::sleep(std::time::Duration::from_millis(80));
        tasks.report("b", 0, &[1.0, 1.0]).unwrap();
        let c = tasks.register("c", 2).unwrap();
        assert_eq!(c.first_env, 0, "a's range: a was silent, b had just reported");
        assert!(tasks.report("a", 0, &[1.0, 1.0]).is_err(), "a holds nothing now; it must register again");
        let never = LocalTasks::new(controller(4, SwitchPolicy::Random), None);
        never.register("a", 4).unwrap();
        std::thread::sleep(std::time::Duration::from_millis(20));
        assert!(never.register("b", 1).is_err(), "without a release time, ranges are kept");
    }

    #[test]
    fn reports_switch_tracks_emit_events_and_refusals_are_permanent() {
        let tasks = LocalTasks::new(controller(4, SwitchPolicy::Random), None);
        let mut events = tasks.subscribe();
        tasks.register("a", 4).unwrap();
        assert!(matches!(events.try_recv(), Ok(TaskEvent::Registered(r)) if r.actor == "a" && r.envs == 4));
        let mut switched = 0;
        for rollout in 0..8 {
            switched += tasks.report("a", rollout, &[1.0; 4]).unwrap().len();
        }
        assert!(switched > 0, "p = 0.5 over 32 reports");
        let history = tasks.switch_history(0).unwrap();
        assert_eq!(history.len(), switched);
        for e in &history {
            assert!(matches!(events.try_recv(), Ok(TaskEvent::Switched(s)) if &s == e));
        }
        assert_eq!(tasks.switch_history(1).unwrap()[..], history[1..]);
        let infos = tasks.tasks().unwrap();
        assert_eq!(infos.iter().map(|t| t.switches as usize).sum::<usize>(), switched);
        assert!(infos.iter().all(|t| t.actor.as_deref() == Some("a") && t.last_rollout == Some(7)));
        assert_eq!(tasks.task(2).unwrap(), infos[2]);

        let stale = tasks.report("a", 3, &[1.0; 4]).unwrap_err();
        assert!(matches!(stale, TaskServiceError::Refused(TaskError::StaleRollout { .. })) && !stale.is_transient());
        assert!(!tasks.task(4).unwrap_err().is_transient());
    }
}
