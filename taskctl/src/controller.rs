//! The task controller: one slot per environment (its track and reward window), switching
//! decisions, switch history, and snapshots that survive a restart.
//!
//! Decisions and new-track seeds are drawn from `(seed, environment, iteration)` alone, so the
//! same seed and the same reports give the same decisions whatever order actors report in.

use std::collections::VecDeque;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use serde::{Deserialize, Serialize};
use sim::Track;

use crate::switching::{SwitchParams, SwitchPolicy, flatness_score, spearman_over_time, uniform};
use racetracks::{GenerateError, TrackGenerator};
use sim::seed::mix;

/// Seeds tried for a new track before a switch gives up.
const SEED_TRIES: u64 = 10;

/// Furthest a report may run ahead of the next expected rollout index. A gap means
/// acknowledged reports were lost with a restored state — a handful, never thousands — so a
/// larger jump is refused rather than taken as the new count.
pub const MAX_ROLLOUT_GAP: u64 = 10_000;

/// What the controller knows about one environment.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct EnvSlot {
    /// Current track.
    pub track: Arc<Track>,
    /// Generator seed of the current track (`None` for a track given at start).
    pub track_seed: Option<u64>,
    /// Cumulative rollout rewards on the current track, oldest first, at most l.
    pub window: VecDeque<f64>,
    /// Last iteration reported.
    pub last_iteration: Option<u64>,
    /// ρ of the window after the last report.
    pub rho: Option<f64>,
    /// q of the window after the last report.
    pub q: Option<f64>,
    /// Switches so far.
    pub switches: u32,
}

/// One switch, for the history.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SwitchEvent {
    /// Iteration of the report that caused it.
    pub iteration: u64,
    /// Environment.
    pub env: usize,
    /// Name of the track replaced.
    pub old_track: String,
    /// Name of the new track.
    pub new_track: String,
    /// Seed of the new track.
    pub new_seed: u64,
    /// ρ at the switch.
    pub rho: f64,
    /// q at the switch (the random policy's probability for it).
    pub q: f64,
}

/// The environments one actor process runs, and where its reports continue.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ActorRange {
    /// Actor name.
    pub actor: String,
    /// Global index of its first environment.
    pub first_env: usize,
    /// Number of environments.
    pub envs: usize,
    /// Rollout index its next report must carry (at least).
    pub next_rollout: u64,
}

/// A report the controller refuses.
#[derive(Debug, thiserror::Error)]
pub enum TaskError {
    /// The environment index is out of range.
    #[error("unknown environment {env} (the controller has {envs})")]
    UnknownEnv {
        /// Index given.
        env: usize,
        /// Environments held.
        envs: usize,
    },
    /// The reward is NaN or infinite.
    #[error("environment {env}: reward {reward} is not a finite number")]
    NotFinite {
        /// Environment.
        env: usize,
        /// Reward given.
        reward: f64,
    },
    /// The iteration is not after the last one reported for this environment.
    #[error("environment {env}: iteration {iteration} is not after the last reported iteration {last}")]
    StaleIteration {
        /// Environment.
        env: usize,
        /// Iteration given.
        iteration: u64,
        /// Last iteration accepted.
        last: u64,
    },
    /// No new track could be generated.
    #[error(transparent)]
    Generate(#[from] GenerateError),
    /// A controller needs at least one environment.
    #[error("a task controller needs at least one environment")]
    NoEnvironments,
    /// An actor asked for more environments than are left unassigned.
    #[error("actor {actor:?} asks for {envs} environments but only {free} of {total} are unassigned")]
    NoRoom {
        /// Actor.
        actor: String,
        /// Environments asked for.
        envs: usize,
        /// Environments left.
        free: usize,
        /// Environments in all.
        total: usize,
    },
    /// A known actor came back with another environment count.
    #[error("actor {actor:?} registered {had} environments before, now asks for {asks}")]
    RangeChanged {
        /// Actor.
        actor: String,
        /// Earlier count.
        had: usize,
        /// Count asked for now.
        asks: usize,
    },
    /// A report from an actor that never registered.
    #[error("actor {0:?} is not registered")]
    UnknownActor(String),
    /// A report whose reward count differs from the actor's environment count.
    #[error("actor {actor:?} runs {envs} environments but reported {got} rewards")]
    RewardCount {
        /// Actor.
        actor: String,
        /// Its environments.
        envs: usize,
        /// Rewards given.
        got: usize,
    },
    /// A rollout index further ahead of the next expected one than any lost reports explain
    /// (or the last index there is): taking it would freeze the actor's curriculum, every later
    /// honest report then looking stale.
    #[error("actor {actor:?}: rollout {rollout} is more than {MAX_ROLLOUT_GAP} ahead of the next expected {next}")]
    RolloutTooFarAhead {
        /// Actor.
        actor: String,
        /// Index given.
        rollout: u64,
        /// Next index expected.
        next: u64,
    },
    /// A rollout index at or below one already reported.
    #[error("actor {actor:?}: rollout {rollout} was reported already (next is {next})")]
    StaleRollout {
        /// Actor.
        actor: String,
        /// Index given.
        rollout: u64,
        /// Next index expected.
        next: u64,
    },
}

/// A snapshot that could not be written or read.
#[derive(Debug, thiserror::Error)]
pub enum SnapshotError {
    /// Reading or writing failed.
    #[error("{file}: {source}")]
    Io {
        /// The file.
        file: PathBuf,
        /// The underlying error.
        source: std::io::Error,
    },
    /// The file is not an intact snapshot frame; it is refused rather than half-used.
    #[error("{file}: refusing a corrupt snapshot: {source}")]
    Corrupt {
        /// The file.
        file: PathBuf,
        /// What is wrong with the frame (magic, format, length or checksum).
        source: frames::FrameError,
    },
    /// The frame is intact but its body is not a controller state this version reads.
    #[error("{file}: refusing a snapshot whose contents do not parse: {source}")]
    Contents {
        /// The file.
        file: PathBuf,
        /// The parse error.
        source: serde_json::Error,
    },
}

/// Everything a controller holds; what a snapshot stores.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
struct State {
    seed: u64,
    generator: TrackGenerator,
    switching: SwitchParams,
    slots: Vec<EnvSlot>,
    history: Vec<SwitchEvent>,
    /// Actor processes and their environment ranges (empty when training in one process).
    #[serde(default)]
    actors: Vec<ActorRange>,
}

/// Owns track generation and switching for every environment.
#[derive(Clone, Debug, PartialEq)]
pub struct TaskController {
    state: State,
}

/// The snapshot's frame (`frames`); its body is the state as JSON.
const SNAPSHOT: frames::FrameKind = frames::FrameKind { magic: b"DRTASKS\0", format: 2, name: "dronerace task-controller snapshot" };

impl TaskController {
    /// `envs` environments, each with a freshly generated track.
    pub fn new(envs: usize, generator: TrackGenerator, switching: SwitchParams, seed: u64) -> Result<Self, TaskError> {
        if envs == 0 {
            return Err(TaskError::NoEnvironments);
        }
        let mut state = State { seed, generator, switching, slots: Vec::with_capacity(envs), history: Vec::new(), actors: Vec::new() };
        for env in 0..envs {
            let (track, track_seed) = state.new_track(env, 0)?;
            state.slots.push(EnvSlot::new(track, Some(track_seed)));
        }
        Ok(Self { state })
    }

    /// Environments start on the given tracks (e.g. one library track for single-track PPO).
    pub fn with_tracks(tracks: Vec<Arc<Track>>, generator: TrackGenerator, switching: SwitchParams, seed: u64) -> Result<Self, TaskError> {
        if tracks.is_empty() {
            return Err(TaskError::NoEnvironments);
        }
        let slots = tracks.into_iter().map(|t| EnvSlot::new(t, None)).collect();
        Ok(Self { state: State { seed, generator, switching, slots, history: Vec::new(), actors: Vec::new() } })
    }

    /// Takes environment `env`'s cumulative reward of the rollout of `iteration`; returns its
    /// new track when it switches.
    pub fn report(&mut self, env: usize, iteration: u64, reward: f64) -> Result<Option<Arc<Track>>, TaskError> {
        let envs = self.state.slots.len();
        let params = self.state.switching;
        let slot = self.state.slots.get_mut(env).ok_or(TaskError::UnknownEnv { env, envs })?;
        if !reward.is_finite() {
            return Err(TaskError::NotFinite { env, reward });
        }
        if let Some(last) = slot.last_iteration.filter(|&last| iteration <= last) {
            return Err(TaskError::StaleIteration { env, iteration, last });
        }
        slot.last_iteration = Some(iteration);
        slot.window.push_back(reward);
        while slot.window.len() > params.window {
            slot.window.pop_front();
        }
        let rho = spearman_over_time(slot.window.make_contiguous());
        let q = flatness_score(rho, params.alpha);
        (slot.rho, slot.q) = (Some(rho), Some(q));
        let probability = match params.policy {
            SwitchPolicy::Adaptive if slot.window.len() >= params.window => q,
            SwitchPolicy::Random => params.random_probability,
            _ => return Ok(None),
        };
        if uniform(self.state.seed, env as u64, iteration) >= probability {
            return Ok(None);
        }
        let generation = u64::from(slot.switches) + 1;
        let (track, new_seed) = self.state.new_track(env, generation)?;
        let slot = &mut self.state.slots[env];
        self.state.history.push(SwitchEvent {
            iteration,
            env,
            old_track: slot.track.name.clone(),
            new_track: track.name.clone(),
            new_seed,
            rho,
            q: probability,
        });
        slot.track = track.clone();
        slot.track_seed = Some(new_seed);
        slot.window.clear();
        slot.switches += 1;
        Ok(Some(track))
    }

    /// Gives actor `actor` a range of `envs` environments, or its earlier range when it comes
    /// back (after a restart of either process).
    pub fn register(&mut self, actor: &str, envs: usize) -> Result<ActorRange, TaskError> {
        if let Some(known) = self.state.actors.iter().find(|a| a.actor == actor) {
            if known.envs != envs {
                return Err(TaskError::RangeChanged { actor: actor.into(), had: known.envs, asks: envs });
            }
            return Ok(known.clone());
        }
        let total = self.state.slots.len();
        // The first gap that holds `envs`: ranges given back by actors that are gone are reused.
        let mut taken: Vec<(usize, usize)> = self.state.actors.iter().map(|a| (a.first_env, a.first_env + a.envs)).collect();
        taken.sort_unstable();
        let free = total - taken.iter().map(|(start, end)| end - start).sum::<usize>();
        let mut gap_start = 0;
        let mut first_env = None;
        for &(start, end) in taken.iter().chain([(total, total)].iter()) {
            if start >= gap_start && start - gap_start >= envs {
                first_env = Some(gap_start);
                break;
            }
            gap_start = gap_start.max(end);
        }
        let Some(first_env) = first_env.filter(|_| envs > 0) else {
            return Err(TaskError::NoRoom { actor: actor.into(), envs, free, total });
        };
        // Environments keep their rollout history: an actor taking over a range continues after it.
        let next_rollout = self.state.slots[first_env..first_env + envs]
            .iter()
            .filter_map(|s| s.last_iteration)
            .max()
            .map_or(0, |last| last.saturating_add(1));
        let range = ActorRange { actor: actor.into(), first_env, envs, next_rollout };
        self.state.actors.push(range.clone());
        Ok(range)
    }

    /// Takes back `actor`'s range (it is gone): the environments keep their tracks and history
    /// for whoever registers them next. Returns the range it held.
    pub fn release(&mut self, actor: &str) -> Option<ActorRange> {
        let at = self.state.actors.iter().position(|a| a.actor == actor)?;
        Some(self.state.actors.remove(at))
    }

    /// Takes one rollout's cumulative rewards of all of an actor's environments (refused
    /// whole if anything is wrong); returns the environments that switched and their tracks.
    #[allow(clippy::expect_used, reason = "the actor was found above; the borrow checker needs a second lookup to mutate")]
    pub fn report_rollout(&mut self, actor: &str, rollout: u64, rewards: &[f64]) -> Result<Vec<(usize, Arc<Track>)>, TaskError> {
        let range = self.state.actors.iter().find(|a| a.actor == actor).ok_or_else(|| TaskError::UnknownActor(actor.into()))?;
        if rewards.len() != range.envs {
            return Err(TaskError::RewardCount { actor: actor.into(), envs: range.envs, got: rewards.len() });
        }
        if rollout < range.next_rollout {
            return Err(TaskError::StaleRollout { actor: actor.into(), rollout, next: range.next_rollout });
        }
        if let Some((i, &reward)) = rewards.iter().enumerate().find(|(_, r)| !r.is_finite()) {
            return Err(TaskError::NotFinite { env: range.first_env + i, reward });
        }
        if rollout - range.next_rollout > MAX_ROLLOUT_GAP || rollout == u64::MAX {
            return Err(TaskError::RolloutTooFarAhead { actor: actor.into(), rollout, next: range.next_rollout });
        }
        if rollout > range.next_rollout {
            // Actors number reports consecutively and count one only once it is acknowledged:
            // a gap means acknowledged reports were not in the state this controller restored.
            let lost = rollout - range.next_rollout;
            tracing::error!(actor, lost, "acknowledged reports lost: report {rollout} follows {}", range.next_rollout);
        }
        let first_env = range.first_env;
        let mut switches = Vec::new();
        for (i, &reward) in rewards.iter().enumerate() {
            if let Some(track) = self.report(first_env + i, rollout, reward)? {
                switches.push((first_env + i, track));
            }
        }
        let range = self.state.actors.iter_mut().find(|a| a.actor == actor).expect("found above");
        range.next_rollout = rollout + 1;
        Ok(switches)
    }

    /// Registered actors.
    pub fn actors(&self) -> &[ActorRange] {
        &self.state.actors
    }

    /// Number of environments.
    pub fn len(&self) -> usize {
        self.state.slots.len()
    }

    /// True when there are no environments (never, for a constructed controller).
    pub fn is_empty(&self) -> bool {
        self.state.slots.is_empty()
    }

    /// Every environment's slot.
    pub fn slots(&self) -> &[EnvSlot] {
        &self.state.slots
    }

    /// Mean flatness score q over the environments that have one (`None` while none has).
    pub fn mean_q(&self) -> Option<f64> {
        let qs: Vec<f64> = self.state.slots.iter().filter_map(|s| s.q).collect();
        (!qs.is_empty()).then(|| qs.iter().sum::<f64>() / qs.len() as f64)
    }

    /// Current track of every environment.
    pub fn tracks(&self) -> Vec<Arc<Track>> {
        self.state.slots.iter().map(|s| s.track.clone()).collect()
    }

    /// Every switch so far, oldest first.
    pub fn history(&self) -> &[SwitchEvent] {
        &self.state.history
    }

    /// Switching parameters.
    pub fn switching(&self) -> &SwitchParams {
        &self.state.switching
    }

    /// The whole state as snapshot bytes: a frame (magic, format, length, CRC-32) around the
    /// state as JSON.
    #[allow(clippy::expect_used, reason = "controller state always serialises")]
    pub fn to_snapshot_bytes(&self) -> Vec<u8> {
        SNAPSHOT.encode(&serde_json::to_vec(&self.state).expect("controller state always serialises"))
    }

    /// Writes [`TaskController::to_snapshot_bytes`] atomically: a temporary file, fsync, rename.
    pub fn snapshot(&self, path: &Path) -> Result<(), SnapshotError> {
        durable::write_atomic(path, &self.to_snapshot_bytes()).map_err(|source| SnapshotError::Io { file: path.to_path_buf(), source })
    }

    /// Reads a snapshot file, refusing anything truncated, altered or of another format.
    pub fn restore(path: &Path) -> Result<Self, SnapshotError> {
        let bytes = std::fs::read(path).map_err(|source| SnapshotError::Io { file: path.to_path_buf(), source })?;
        Self::from_snapshot_bytes(&bytes, path)
    }

    /// Decodes snapshot bytes; `origin` names their source in errors. (Snapshots of the text-header
    /// layout before 87bc9c6 are refused as a bad magic: no run of that age is resumed any more.)
    pub fn from_snapshot_bytes(bytes: &[u8], origin: &Path) -> Result<Self, SnapshotError> {
        let body = SNAPSHOT.decode(bytes).map_err(|source| SnapshotError::Corrupt { file: origin.to_path_buf(), source })?;
        let state: State = serde_json::from_slice(body).map_err(|source| SnapshotError::Contents { file: origin.to_path_buf(), source })?;
        Ok(Self { state })
    }
}

impl EnvSlot {
    fn new(track: Arc<Track>, track_seed: Option<u64>) -> Self {
        Self { track, track_seed, window: VecDeque::new(), last_iteration: None, rho: None, q: None, switches: 0 }
    }
}

impl State {
    /// Track number `generation` of environment `env`, from a seed that depends only on them.
    #[allow(clippy::expect_used, reason = "at least one seed tried")]
    fn new_track(&self, env: usize, generation: u64) -> Result<(Arc<Track>, u64), GenerateError> {
        let mut last_error = None;
        for attempt in 0..SEED_TRIES {
            let track_seed = mix(mix(mix(self.seed ^ 0x7472_6163_6b73) ^ env as u64) ^ (generation << 8 | attempt));
            if racetracks::track_sets::is_held_out(track_seed) {
                // Validation and test tracks are never trained on (a 2⁻⁴³ chance per draw).
                continue;
            }
            let name = format!("{:?}-{track_seed:016x}", self.generator.kind).to_lowercase();
            match self.generator.generate(track_seed, &name) {
                Ok(g) => return Ok((Arc::new(g.track), track_seed)),
                Err(e) => last_error = Some(e),
            }
        }
        Err(last_error.expect("at least one seed tried"))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn controller(policy: SwitchPolicy, window: usize, envs: usize) -> TaskController {
        let switching = SwitchParams { policy, window, ..SwitchParams::default() };
        TaskController::new(envs, TrackGenerator::default(), switching, 11).unwrap()
    }

    #[test]
    fn adaptive_never_switches_before_the_window_is_full() {
        let mut c = controller(SwitchPolicy::Adaptive, 10, 1);
        // Constant rewards: ρ = 0, q = 1, so it switches exactly when the window fills.
        for iteration in 0..9 {
            assert!(c.report(0, iteration, 5.0).unwrap().is_none(), "iteration {iteration}");
            assert_eq!(c.slots()[0].q, Some(1.0));
        }
        let new = c.report(0, 9, 5.0).unwrap().expect("switches when the window holds l values");
        assert_eq!(c.slots()[0].track, new);
        assert!(c.slots()[0].window.is_empty());
        assert_eq!(c.history().len(), 1);
        assert_eq!((c.history()[0].iteration, c.history()[0].env), (9, 0));
    }

    #[test]
    fn a_steady_trend_scores_as_not_flat() {
        let mut c = controller(SwitchPolicy::Adaptive, 20, 1);
        for iteration in 0..19 {
            c.report(0, iteration, iteration as f64).unwrap();
        }
        // Rising rewards: ρ = 1, q = 1 / (1 + 1000).
        c.report(0, 19, 19.0).unwrap();
        assert_eq!(c.slots()[0].rho, Some(1.0));
        assert!((c.slots()[0].q.unwrap() - 1.0 / 1001.0).abs() < 1e-15);
    }

    #[test]
    fn the_random_policy_switches_at_its_rate() {
        let switching = SwitchParams { policy: SwitchPolicy::Random, random_probability: 0.05, ..SwitchParams::default() };
        let mut c = TaskController::new(10, TrackGenerator::default(), switching, 3).unwrap();
        let reports = 10 * 2000;
        for iteration in 0..2000 {
            for env in 0..10 {
                c.report(env, iteration, 1.0).unwrap();
            }
        }
        let switches = c.history().len() as f64;
        let (mean, sd) = (reports as f64 * 0.05, (reports as f64 * 0.05 * 0.95).sqrt());
        assert!((switches - mean).abs() < 5.0 * sd, "{switches} switches, expected {mean} ± {sd}");
    }

    #[test]
    fn none_never_switches() {
        let mut c = controller(SwitchPolicy::None, 5, 2);
        for iteration in 0..100 {
            assert!(c.report(iteration as usize % 2, iteration, 1.0).unwrap().is_none());
        }
    }

    #[test]
    fn same_seed_and_reports_give_the_same_decisions_in_any_report_order() {
        let mut a = controller(SwitchPolicy::Adaptive, 8, 4);
        let mut b = controller(SwitchPolicy::Adaptive, 8, 4);
        for iteration in 0..200u64 {
            let reward = |env: usize| ((iteration * 7 + env as u64 * 13) % 5) as f64;
            for env in 0..4 {
                a.report(env, iteration, reward(env)).unwrap();
            }
            for env in (0..4).rev() {
                b.report(env, iteration, reward(env)).unwrap();
            }
        }
        assert!(!a.history().is_empty());
        let key = |c: &TaskController| {
            let mut h: Vec<_> = c.history().iter().map(|e| (e.iteration, e.env, e.new_seed)).collect();
            h.sort();
            h
        };
        assert_eq!(key(&a), key(&b));
        assert_eq!(a.tracks(), b.tracks());
    }

    #[test]
    fn bad_reports_are_refused() {
        let mut c = controller(SwitchPolicy::Adaptive, 5, 2);
        assert!(matches!(c.report(2, 0, 1.0), Err(TaskError::UnknownEnv { env: 2, envs: 2 })));
        assert!(matches!(c.report(0, 0, f64::NAN), Err(TaskError::NotFinite { .. })));
        c.report(0, 3, 1.0).unwrap();
        let e = c.report(0, 3, 1.0).unwrap_err();
        assert!(e.to_string().contains("iteration 3 is not after"), "{e}");
        assert_eq!(c.slots()[0].window.len(), 1, "a refused report changes nothing");
    }

    #[test]
    fn actors_get_disjoint_ranges_that_survive_a_restart() {
        let mut c = controller(SwitchPolicy::Random, 10, 6);
        let a = c.register("a", 4).unwrap();
        assert_eq!((a.first_env, a.envs, a.next_rollout), (0, 4, 0));
        assert!(matches!(c.register("b", 3), Err(TaskError::NoRoom { free: 2, .. })));
        let b = c.register("b", 2).unwrap();
        assert_eq!(b.first_env, 4);
        assert!(matches!(c.register("a", 3), Err(TaskError::RangeChanged { .. })));
        c.report_rollout("a", 0, &[1.0; 4]).unwrap();
        c.report_rollout("a", 1, &[1.0; 4]).unwrap();
        assert!(matches!(c.report_rollout("a", 1, &[1.0; 4]), Err(TaskError::StaleRollout { next: 2, .. })));
        assert!(matches!(c.report_rollout("a", 2, &[1.0; 3]), Err(TaskError::RewardCount { got: 3, .. })));
        assert!(matches!(c.report_rollout("c", 0, &[1.0]), Err(TaskError::UnknownActor(_))));
        // A non-finite reward refuses the whole report: nothing of it is applied.
        let before = c.clone();
        assert!(matches!(c.report_rollout("b", 0, &[1.0, f64::NAN]), Err(TaskError::NotFinite { env: 5, .. })));
        assert_eq!(c, before);
        // After a restart from a snapshot, "a" gets its range back and continues at rollout 2.
        let restored = TaskController::from_snapshot_bytes(&c.to_snapshot_bytes(), Path::new("mem")).unwrap();
        let mut restored = restored;
        assert_eq!(restored.register("a", 4).unwrap().next_rollout, 2);
        // A released range goes to the next actor that fits, which continues its history.
        assert_eq!(restored.release("a").map(|r| r.first_env), Some(0));
        assert_eq!(restored.release("a"), None);
        let c2 = restored.register("c", 3).unwrap();
        assert_eq!((c2.first_env, c2.next_rollout), (0, 2));
        assert!(matches!(restored.register("d", 2), Err(TaskError::NoRoom { free: 1, .. })), "1 left at 3, none fits 2");
        assert_eq!(restored.register("d", 1).unwrap().first_env, 3);
    }

    /// A report numbered 2^64 − 1 wrapped the next expected index to 0, so that every later
    /// report was "already reported" and the curriculum froze, snapshot and all. It is refused,
    /// as is any jump far beyond lost reports, and the actor's next honest report is taken.
    #[test]
    fn a_report_at_the_end_of_the_counter_is_refused_and_the_curriculum_goes_on() {
        let mut c = controller(SwitchPolicy::Random, 10, 2);
        c.register("a", 2).unwrap();
        c.report_rollout("a", 0, &[1.0; 2]).unwrap();
        for hostile in [u64::MAX, u64::MAX - 1, 1 + MAX_ROLLOUT_GAP + 1] {
            let before = c.clone();
            let e = c.report_rollout("a", hostile, &[1.0; 2]).unwrap_err();
            assert!(matches!(e, TaskError::RolloutTooFarAhead { rollout, next: 1, .. } if rollout == hostile), "{e}");
            assert_eq!(c, before, "nothing of it applied");
        }
        let restored = TaskController::from_snapshot_bytes(&c.to_snapshot_bytes(), Path::new("mem")).unwrap();
        assert_eq!(restored.actors()[0].next_rollout, 1);
        c.report_rollout("a", 1, &[1.0; 2]).unwrap();
        // A gap that lost reports explain is still taken (and logged).
        c.report_rollout("a", 2 + MAX_ROLLOUT_GAP, &[1.0; 2]).unwrap();
        assert_eq!(c.actors()[0].next_rollout, 3 + MAX_ROLLOUT_GAP);
    }

    #[test]
    fn snapshot_round_trip_continues_identically() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("taskctl.snapshot");
        let mut c = controller(SwitchPolicy::Adaptive, 6, 3);
        for iteration in 0..50 {
            for env in 0..3 {
                c.report(env, iteration, (iteration % 3) as f64).unwrap();
            }
        }
        c.snapshot(&path).unwrap();
        let mut restored = TaskController::restore(&path).unwrap();
        assert_eq!(restored, c);
        for iteration in 50..120 {
            for env in 0..3 {
                let a = c.report(env, iteration, (iteration % 4) as f64).unwrap();
                let b = restored.report(env, iteration, (iteration % 4) as f64).unwrap();
                assert_eq!(a, b);
            }
        }
        assert_eq!(restored, c);
    }

    #[test]
    fn corrupt_or_truncated_snapshots_are_refused() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("s.snapshot");
        controller(SwitchPolicy::Adaptive, 6, 2).snapshot(&path).unwrap();
        let good = std::fs::read(&path).unwrap();
        let refuse = |bytes: &[u8], expect: &str| {
            std::fs::write(&path, bytes).unwrap();
            let e = TaskController::restore(&path).unwrap_err().to_string();
            assert!(e.contains("s.snapshot") && e.contains(expect), "{e}");
        };
        refuse(&good[..good.len() - 10], "truncated");
        let mut flipped = good.clone();
        let last = flipped.len() - 20;
        flipped[last] ^= 0x01;
        refuse(&flipped, "checksum");
        refuse(b"{\"hello\": 1}\n", "bad magic");
        refuse(b"", "bad magic");
        let mut other = good.clone();
        other[8..12].copy_from_slice(&9u32.to_le_bytes());
        refuse(&other, "format 9");
        // An intact frame around a body that is not a controller state.
        refuse(&SNAPSHOT.encode(b"{\"hello\": 1}"), "do not parse");
    }
}
