//! Evaluation protocol (SPEC §9): deployments per track with a deterministic controller,
//! success = at least one lap and no crash, S_pw = mean of success / fastest lap.

use std::sync::Arc;

use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::observation::ObservationLayout;
use crate::race::{CrashCause, EnvConfig, RaceEnv};
use crate::reference_pilot::Controller;
use crate::track::Track;
use crate::vec_env::ACTION_DIM;

/// How an evaluation is run.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct EvalConfig {
    /// Deployments per track. Default 25.
    pub runs: usize,
    /// Steps per deployment. Default 1000.
    pub steps: u32,
    /// Seed of the start perturbations; deployment k of track t uses stream `t · runs + k`.
    pub seed: u64,
    /// Environment setting; default nominal dynamics with start-position perturbation.
    pub env: EnvConfig,
}

impl Default for EvalConfig {
    fn default() -> Self {
        Self { runs: 25, steps: 1000, seed: 0, env: EnvConfig::evaluation() }
    }
}

/// Outcome of one deployment.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Deployment {
    /// At least one lap and no crash.
    pub success: bool,
    /// Every completed lap time (s).
    pub lap_times: Vec<f64>,
    /// Crash that ended it, if any.
    pub crash: Option<CrashCause>,
    /// Target gates passed.
    pub gates_passed: u32,
    /// Steps flown.
    pub steps: u32,
    /// Target gate when it ended: a gate-frame crash on another gate hit a gate the state
    /// observation of SPEC §5 does not show (unless it was the next one).
    #[serde(default)]
    pub target: usize,
}

/// How one deployment ended (SPEC §9 success, or why not).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Outcome {
    /// At least one lap and no crash.
    Success,
    /// Crashed (whether or not it had completed a lap before).
    Crash(CrashCause),
    /// No crash, but no lap within the step limit.
    NoLap,
}

/// How many deployments ended each way.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct OutcomeCounts {
    /// Deployments counted.
    pub deployments: usize,
    /// Successes.
    pub success: usize,
    /// Crashes on the ground.
    pub ground: usize,
    /// Crashes into the ceiling.
    pub ceiling: usize,
    /// Crashes into a side wall of the arena.
    pub wall: usize,
    /// Crashes into a gate frame, indexed by gate (length = the largest gate index hit + 1).
    pub gate: Vec<usize>,
    /// Of the gate-frame crashes, those on a gate that was not the target.
    #[serde(default)]
    pub gate_not_target: usize,
    /// No crash and no lap within the step limit.
    pub no_lap: usize,
}

impl OutcomeCounts {
    /// Counts the outcomes of `deployments`.
    pub fn of<'a>(deployments: impl IntoIterator<Item = &'a Deployment>) -> Self {
        let mut counts = Self::default();
        for d in deployments {
            counts.add(d);
        }
        counts
    }

    fn add(&mut self, deployment: &Deployment) {
        self.deployments += 1;
        match deployment.outcome() {
            Outcome::Success => self.success += 1,
            Outcome::NoLap => self.no_lap += 1,
            Outcome::Crash(CrashCause::Ground) => self.ground += 1,
            Outcome::Crash(CrashCause::Ceiling) => self.ceiling += 1,
            Outcome::Crash(CrashCause::Wall) => self.wall += 1,
            Outcome::Crash(CrashCause::Gate(i)) => {
                if self.gate.len() <= i {
                    self.gate.resize(i + 1, 0);
                }
                self.gate[i] += 1;
                if i != deployment.target {
                    self.gate_not_target += 1;
                }
            }
        }
    }

    /// Adds another set of counts to these (e.g. several seeds' evaluations).
    pub fn merge(&mut self, other: &OutcomeCounts) {
        self.deployments += other.deployments;
        self.success += other.success;
        self.ground += other.ground;
        self.ceiling += other.ceiling;
        self.wall += other.wall;
        self.no_lap += other.no_lap;
        self.gate_not_target += other.gate_not_target;
        if self.gate.len() < other.gate.len() {
            self.gate.resize(other.gate.len(), 0);
        }
        for (mine, theirs) in self.gate.iter_mut().zip(&other.gate) {
            *mine += theirs;
        }
    }

    /// Crashes into any gate frame.
    pub fn gate_total(&self) -> usize {
        self.gate.iter().sum()
    }

    /// `count` as a fraction of the deployments (0 when there are none).
    pub fn fraction(&self, count: usize) -> f64 {
        if self.deployments == 0 { 0.0 } else { count as f64 / self.deployments as f64 }
    }

    /// Gate-frame crashes by gate, e.g. `g0 3, g4 1` (`–` when none).
    pub fn gate_summary(&self) -> String {
        let parts: Vec<String> = self.gate.iter().enumerate().filter(|(_, n)| **n > 0).map(|(i, n)| format!("g{i} {n}")).collect();
        if parts.is_empty() { "–".into() } else { parts.join(", ") }
    }
}

impl Deployment {
    /// How this deployment ended.
    pub fn outcome(&self) -> Outcome {
        match (self.crash, self.success) {
            (Some(cause), _) => Outcome::Crash(cause),
            (None, true) => Outcome::Success,
            (None, false) => Outcome::NoLap,
        }
    }

    /// Fastest completed lap (s).
    pub fn fastest_lap(&self) -> Option<f64> {
        self.lap_times.iter().copied().reduce(f64::min)
    }

    /// This deployment's S_pw contribution: success / fastest lap (s⁻¹).
    pub fn score(&self) -> f64 {
        match (self.success, self.fastest_lap()) {
            (true, Some(t)) => 1.0 / t,
            _ => 0.0,
        }
    }
}

/// Results on one track.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TrackResult {
    /// Track name.
    pub track: String,
    /// Fraction of successful deployments.
    pub success_rate: f64,
    /// Mean over the laps of successful deployments (s).
    pub mean_lap: Option<f64>,
    /// Fastest lap of any successful deployment (s).
    pub fastest_lap: Option<f64>,
    /// This track's S_pw (s⁻¹).
    pub s_pw: f64,
    /// How its deployments ended.
    pub outcomes: OutcomeCounts,
    /// Every deployment.
    pub deployments: Vec<Deployment>,
}

/// A full evaluation report.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct EvalReport {
    /// Name of the controller evaluated.
    pub controller: String,
    /// How it was run.
    pub config: EvalConfig,
    /// S_pw over all deployments of all tracks (s⁻¹).
    pub s_pw: f64,
    /// Fraction of all deployments that succeeded.
    pub success_rate: f64,
    /// Mean over every lap of every successful deployment (s).
    pub mean_lap: Option<f64>,
    /// Fastest lap of any successful deployment (s).
    pub fastest_lap: Option<f64>,
    /// How all deployments ended.
    pub outcomes: OutcomeCounts,
    /// Per-track results, in the order the tracks were given.
    pub tracks: Vec<TrackResult>,
}

/// The header of [`Trajectory::to_csv`]: time, world position, world velocity, attitude
/// (body to world, w x y z), body rates, the action taken there, target gate and laps.
pub const TRAJECTORY_HEADER: &str = "t,x,y,z,vx,vy,vz,qw,qx,qy,qz,p,q,r,a0,a1,a2,a3,target_gate,laps";

/// The states of one deployment, one row per policy step (before the action), and the state
/// after its last step (with no action).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Trajectory {
    /// Rows of [`TRAJECTORY_HEADER`]'s columns.
    pub rows: Vec<[f64; 20]>,
}

impl Trajectory {
    fn record(&mut self, env: &RaceEnv, action: Option<&[f32; 4]>) {
        let b = env.body();
        let a = action.map_or([f64::NAN; 4], |a| a.map(f64::from));
        let q = b.attitude;
        self.rows.push([
            env.time(),
            b.position.x,
            b.position.y,
            b.position.z,
            b.velocity.x,
            b.velocity.y,
            b.velocity.z,
            q.w,
            q.i,
            q.j,
            q.k,
            b.body_rates.x,
            b.body_rates.y,
            b.body_rates.z,
            a[0],
            a[1],
            a[2],
            a[3],
            env.target_gate() as f64,
            f64::from(env.stats().laps),
        ]);
    }

    /// The file `dronerace eval --trajectories` writes deployment `run` of track `index`
    /// (`track`) to: `<index>-<track>-<run>.csv`, the name kept to letters, digits, '-' and '_'.
    pub fn file_name(index: usize, track: &str, run: usize) -> String {
        let track: String = track.chars().map(|c| if c.is_ascii_alphanumeric() || c == '-' { c } else { '_' }).collect();
        format!("{index:02}-{track}-{run:03}.csv")
    }

    /// The rows as CSV under [`TRAJECTORY_HEADER`] (the last row's action cells empty).
    pub fn to_csv(&self) -> String {
        let mut out = String::from(TRAJECTORY_HEADER);
        out.push('\n');
        for row in &self.rows {
            let cells: Vec<String> = row.iter().map(|v| if v.is_nan() { String::new() } else { format!("{v}") }).collect();
            out.push_str(&cells.join(","));
            out.push('\n');
        }
        out
    }
}

/// Flies one deployment and records it.
pub fn deploy(track: Arc<Track>, controller: &mut dyn Controller, config: &EvalConfig, stream: u64) -> Deployment {
    deploy_recording(track, controller, config, stream, None)
}

/// [`deploy`], also recording its states into `trajectory` when given.
pub fn deploy_recording(
    track: Arc<Track>,
    controller: &mut dyn Controller,
    config: &EvalConfig,
    stream: u64,
    mut trajectory: Option<&mut Trajectory>,
) -> Deployment {
    let mut flight = Flight::new(track, config, stream);
    controller.reset(&flight.env);
    while !flight.is_over() {
        let action = controller.act(&flight.env);
        if let Some(t) = trajectory.as_deref_mut() {
            t.record(&flight.env, Some(&action));
        }
        flight.step(&action);
    }
    if let Some(t) = trajectory {
        t.record(&flight.env, None);
    }
    flight.into_deployment()
}

/// One deployment in flight: its environment and what it has flown so far. [`deploy`] flies
/// one to the end; [`evaluate_batched`] steps many in lockstep.
struct Flight {
    env: RaceEnv,
    steps_left: u32,
    lap_times: Vec<f64>,
    crash: Option<CrashCause>,
    ended: bool,
}

impl Flight {
    /// Deployment `stream` of `config` on `track`, at its (perturbed) start.
    fn new(track: Arc<Track>, config: &EvalConfig, stream: u64) -> Self {
        let mut env_config = config.env;
        env_config.race.max_episode_steps = config.steps;
        let env = RaceEnv::new(track, env_config, config.seed, stream);
        Self { env, steps_left: config.steps, lap_times: Vec::new(), crash: None, ended: false }
    }

    /// True once it crashed, timed out or used its steps.
    fn is_over(&self) -> bool {
        self.ended || self.steps_left == 0
    }

    fn step(&mut self, action: &[f32; 4]) {
        let out = self.env.step(action);
        self.steps_left -= 1;
        self.lap_times.extend(out.lap_time);
        if out.done() {
            self.crash = out.crash;
            self.ended = true;
        }
    }

    fn into_deployment(self) -> Deployment {
        Deployment {
            success: self.crash.is_none() && !self.lap_times.is_empty(),
            lap_times: self.lap_times,
            crash: self.crash,
            gates_passed: self.env.stats().gates_passed,
            steps: self.env.stats().length,
            target: self.env.target_gate(),
        }
    }
}

/// [`evaluate`] for a controller that acts on many observations at once (a policy called from
/// another language, a batched network): every deployment of every track flies in lockstep,
/// and each step `act` gets the observations (in `layout`) of the deployments still flying,
/// one row each, and writes one 4-number action row per observation row. The deployments,
/// their starts and so the report are those of [`evaluate`] with the same controller.
pub fn evaluate_batched<E>(
    controller_name: &str,
    tracks: &[Arc<Track>],
    layout: ObservationLayout,
    config: &EvalConfig,
    mut act: impl FnMut(&[f32], &mut [f32]) -> Result<(), E>,
) -> Result<EvalReport, E> {
    let mut flights: Vec<Flight> = (0..tracks.len())
        .flat_map(|t| (0..config.runs).map(move |k| (t, k)))
        .map(|(t, k)| Flight::new(tracks[t].clone(), config, (t * config.runs + k) as u64))
        .collect();
    let dim = layout.dim();
    let (mut observations, mut actions) = (Vec::new(), Vec::new());
    loop {
        let mut flying: Vec<&mut Flight> = flights.iter_mut().filter(|f| !f.is_over()).collect();
        if flying.is_empty() {
            break;
        }
        observations.resize(flying.len() * dim, 0.0);
        actions.resize(flying.len() * ACTION_DIM, 0.0);
        flying.par_iter().zip(observations.par_chunks_mut(dim)).for_each(|(f, row)| f.env.observe_in(layout, row));
        act(&observations, &mut actions)?;
        flying.par_iter_mut().zip(actions.par_chunks(ACTION_DIM)).for_each(|(f, a)| f.step(&[a[0], a[1], a[2], a[3]]));
    }
    let deployments: Vec<Deployment> = flights.into_iter().map(Flight::into_deployment).collect();
    Ok(report(controller_name, tracks, config, deployments))
}

/// Evaluates a controller on `tracks`; all deployments run in parallel, each with a fresh
/// controller from `make_controller`.
pub fn evaluate(
    controller_name: &str,
    tracks: &[Arc<Track>],
    make_controller: &(dyn Fn() -> Box<dyn Controller> + Sync),
    config: &EvalConfig,
) -> EvalReport {
    evaluate_recording(controller_name, tracks, make_controller, config, false).0
}

/// [`evaluate`], also returning every deployment's [`Trajectory`] when `record` is set (track
/// by track, deployments in order; empty otherwise).
pub fn evaluate_recording(
    controller_name: &str,
    tracks: &[Arc<Track>],
    make_controller: &(dyn Fn() -> Box<dyn Controller> + Sync),
    config: &EvalConfig,
    record: bool,
) -> (EvalReport, Vec<Trajectory>) {
    let jobs: Vec<(usize, usize)> = (0..tracks.len()).flat_map(|t| (0..config.runs).map(move |k| (t, k))).collect();
    let (deployments, trajectories): (Vec<Deployment>, Vec<Trajectory>) = jobs
        .par_iter()
        .map(|&(t, k)| {
            let mut controller = make_controller();
            let mut trajectory = Trajectory::default();
            let recording = record.then_some(&mut trajectory);
            let d = deploy_recording(tracks[t].clone(), controller.as_mut(), config, (t * config.runs + k) as u64, recording);
            (d, trajectory)
        })
        .unzip();
    let trajectories = if record { trajectories } else { Vec::new() };
    (report(controller_name, tracks, config, deployments), trajectories)
}

/// The report of `deployments`, track by track (each track's `config.runs` in order).
fn report(controller_name: &str, tracks: &[Arc<Track>], config: &EvalConfig, deployments: Vec<Deployment>) -> EvalReport {
    let mut per_track = deployments.chunks(config.runs.max(1));
    let results: Vec<TrackResult> = tracks
        .iter()
        .map(|track| {
            let runs = per_track.next().map(<[Deployment]>::to_vec).unwrap_or_default();
            summarise(&track.name, runs)
        })
        .collect();
    let all = summarise("all", deployments);
    EvalReport {
        controller: controller_name.to_owned(),
        config: *config,
        s_pw: all.s_pw,
        success_rate: all.success_rate,
        mean_lap: all.mean_lap,
        fastest_lap: all.fastest_lap,
        outcomes: all.outcomes,
        tracks: results,
    }
}

fn summarise(track: &str, deployments: Vec<Deployment>) -> TrackResult {
    let n = deployments.len().max(1) as f64;
    let laps: Vec<f64> = deployments.iter().filter(|d| d.success).flat_map(|d| d.lap_times.iter().copied()).collect();
    TrackResult {
        track: track.to_owned(),
        success_rate: deployments.iter().filter(|d| d.success).count() as f64 / n,
        mean_lap: (!laps.is_empty()).then(|| laps.iter().sum::<f64>() / laps.len() as f64),
        fastest_lap: laps.iter().copied().reduce(f64::min),
        s_pw: deployments.iter().map(Deployment::score).sum::<f64>() / n,
        outcomes: OutcomeCounts::of(&deployments),
        deployments,
    }
}

impl EvalReport {
    /// A Markdown table: one row per track, then the totals.
    pub fn to_markdown(&self) -> String {
        let secs = |t: Option<f64>| t.map_or("–".to_owned(), |t| format!("{t:.3}"));
        let disturbance = &self.config.env.disturbance;
        let flown_in = if disturbance.any() { format!("; flown in {}", disturbance.describe()) } else { String::new() };
        let mut out = format!(
            "## Evaluation of `{}`\n\n{} deployments × {} steps per track, seed {}{flown_in}.\n\n",
            self.controller, self.config.runs, self.config.steps, self.config.seed
        );
        out.push_str(
            "| track | success | mean lap (s) | fastest lap (s) | S_pw (1/s) | ground | ceiling | wall | gate frame | not the target | no lap | gate frames hit |\n\
             |---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|\n",
        );
        let row = |name: &str, success: f64, mean: Option<f64>, fastest: Option<f64>, s_pw: f64, o: &OutcomeCounts| {
            format!(
                "| {name} | {:.0} % | {} | {} | {s_pw:.4} | {} | {} | {} | {} | {} | {} | {} |\n",
                100.0 * success,
                secs(mean),
                secs(fastest),
                o.ground,
                o.ceiling,
                o.wall,
                o.gate_total(),
                o.gate_not_target,
                o.no_lap,
                o.gate_summary()
            )
        };
        for t in &self.tracks {
            out.push_str(&row(&t.track, t.success_rate, t.mean_lap, t.fastest_lap, t.s_pw, &t.outcomes));
        }
        let all = format!("**all {} tracks**", self.tracks.len());
        out.push_str(&row(&all, self.success_rate, self.mean_lap, self.fastest_lap, self.s_pw, &self.outcomes));
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::reference_pilot::ReferencePilot;
    use crate::track::{Arena, Gate};
    use nalgebra::Vector3;

    /// Hovers in place: never passes a gate, never crashes.
    struct Hover;
    impl Controller for Hover {
        fn reset(&mut self, _: &RaceEnv) {}
        fn act(&mut self, env: &RaceEnv) -> [f32; 4] {
            crate::quadrotor::Command::hover().to_action(&env.config().quadrotor).map(|a| a as f32)
        }
    }

    fn oval() -> Arc<Track> {
        let g = |x, y, yaw_deg: f64| Gate::new(Vector3::new(x, y, 2.5), yaw_deg.to_radians());
        let gates = vec![g(0.0, -6.0, 0.0), g(9.0, 0.0, 90.0), g(0.0, 6.0, 180.0), g(-9.0, 0.0, -90.0)];
        Arc::new(Track::new("oval", gates, None, Arena::default()).unwrap())
    }

    /// Steers from the observation alone (a fixed linear map, crashing on some deployments and
    /// lapping on none): what a policy does, without a network.
    fn steer(observation: &[f32]) -> [f32; 4] {
        std::array::from_fn(|j| (0.3 * observation[j] - 0.2 * observation[j + 4] + 0.1 * j as f32).tanh())
    }

    /// [`steer`] as a controller, reading the default layout as a policy reads its own.
    struct Steer;
    impl Controller for Steer {
        fn reset(&mut self, _: &RaceEnv) {}
        fn act(&mut self, env: &RaceEnv) -> [f32; 4] {
            steer(&env.observation_in(ObservationLayout::default()))
        }
    }

    #[test]
    fn lockstep_evaluation_flies_the_deployments_evaluate_flies() {
        let config = EvalConfig { runs: 3, steps: 300, ..EvalConfig::default() };
        let tracks = [oval(), oval()];
        let one_by_one = evaluate("steer", &tracks, &|| Box::new(Steer), &config);
        let mut calls = 0;
        let layout = ObservationLayout::default();
        let batched = evaluate_batched::<()>("steer", &tracks, layout, &config, |observations, actions| {
            calls += 1;
            for (o, a) in observations.chunks(layout.dim()).zip(actions.chunks_mut(ACTION_DIM)) {
                a.copy_from_slice(&steer(o));
            }
            Ok(())
        })
        .unwrap();
        assert_eq!(batched, one_by_one);
        let longest = one_by_one.tracks.iter().flat_map(|t| &t.deployments).map(|d| d.steps).max().unwrap();
        assert_eq!(calls, longest as usize, "one call per step while any deployment flies");
        let ends: std::collections::HashSet<u32> = one_by_one.tracks.iter().flat_map(|t| &t.deployments).map(|d| d.steps).collect();
        assert!(ends.len() > 1, "deployments end at different steps, so the lockstep drops finished ones: {ends:?}");
        // An error from the controller stops the evaluation and comes back.
        assert_eq!(evaluate_batched("fails", &tracks, layout, &config, |_, _| Err("no")), Err("no"));
    }

    #[test]
    fn s_pw_is_the_mean_of_success_over_fastest_lap() {
        let ok = |t: &[f64]| Deployment { success: true, lap_times: t.to_vec(), crash: None, gates_passed: 9, steps: 1000, target: 1 };
        let crashed =
            Deployment { success: false, lap_times: vec![2.0], crash: Some(CrashCause::Ground), gates_passed: 5, steps: 300, target: 1 };
        let r = summarise("t", vec![ok(&[5.0, 4.0]), ok(&[8.0]), crashed]);
        assert_eq!((r.outcomes.success, r.outcomes.ground, r.outcomes.deployments), (2, 1, 3));
        assert!((r.s_pw - (0.25 + 0.125 + 0.0) / 3.0).abs() < 1e-12);
        assert!((r.success_rate - 2.0 / 3.0).abs() < 1e-12);
        assert_eq!(r.fastest_lap, Some(4.0));
        assert!((r.mean_lap.unwrap() - 17.0 / 3.0).abs() < 1e-12);
    }

    #[test]
    fn a_hovering_controller_scores_zero_and_the_pilot_scores_on_an_oval() {
        let config = EvalConfig { runs: 4, steps: 600, ..EvalConfig::default() };
        let hover = evaluate("hover", &[oval()], &|| Box::new(Hover), &config);
        assert_eq!(hover.s_pw, 0.0);
        assert!(hover.tracks[0].deployments.iter().all(|d| d.crash.is_none() && d.lap_times.is_empty()));
        let pilot = evaluate("pilot", &[oval()], &|| Box::new(ReferencePilot::default()), &config);
        assert_eq!(pilot.success_rate, 1.0, "{:#?}", pilot.tracks[0].deployments);
        assert!(pilot.s_pw > 0.0);
        // Deterministic: the same seed reproduces the report exactly.
        assert_eq!(pilot, evaluate("pilot", &[oval()], &|| Box::new(ReferencePilot::default()), &config));
    }

    /// One hand-built deployment per outcome, each classified and counted where it belongs.
    #[test]
    fn every_outcome_is_classified_and_counted() {
        let d = |success: bool, laps: &[f64], crash: Option<CrashCause>| Deployment {
            success,
            lap_times: laps.to_vec(),
            crash,
            gates_passed: 3,
            steps: 500,
            target: 2,
        };
        let cases = [
            (d(true, &[6.0], None), Outcome::Success),
            (d(false, &[], Some(CrashCause::Ground)), Outcome::Crash(CrashCause::Ground)),
            (d(false, &[], Some(CrashCause::Ceiling)), Outcome::Crash(CrashCause::Ceiling)),
            (d(false, &[], Some(CrashCause::Wall)), Outcome::Crash(CrashCause::Wall)),
            // A crash after a completed lap is a crash, not a success.
            (d(false, &[6.0], Some(CrashCause::Gate(2))), Outcome::Crash(CrashCause::Gate(2))),
            // A frame of a gate that was not the target (2).
            (d(false, &[], Some(CrashCause::Gate(0))), Outcome::Crash(CrashCause::Gate(0))),
            (d(false, &[], None), Outcome::NoLap),
        ];
        for (deployment, expected) in &cases {
            assert_eq!(deployment.outcome(), *expected);
        }
        let counts = OutcomeCounts::of(cases.iter().map(|(d, _)| d));
        assert_eq!(
            (counts.success, counts.ground, counts.ceiling, counts.wall, counts.gate.clone(), counts.no_lap),
            (1, 1, 1, 1, vec![1, 0, 1], 1)
        );
        assert_eq!(counts.gate_summary(), "g0 1, g2 1");
        assert_eq!((counts.deployments, counts.gate_not_target), (7, 1));
        let mut twice = counts.clone();
        twice.merge(&OutcomeCounts { deployments: 1, gate: vec![0, 0, 0, 1], ..OutcomeCounts::default() });
        twice.merge(&counts);
        assert_eq!((twice.deployments, twice.success, twice.gate.clone(), twice.gate_not_target), (15, 2, vec![2, 0, 2, 1], 2));
    }

    /// Real flights into the floor and the ceiling end with those causes.
    #[test]
    fn flights_into_the_floor_ceiling_wall_and_a_frame_are_told_apart() {
        let config = EvalConfig {
            runs: 1,
            steps: 200,
            env: EnvConfig { randomization: crate::RandomizationParams::none(), ..EnvConfig::evaluation() },
            ..EvalConfig::default()
        };
        // Constant actions from the start pose of the oval (gate 0 at (0, -6, 2.5), facing +x).
        struct Constant([f32; 4]);
        impl Controller for Constant {
            fn reset(&mut self, _: &RaceEnv) {}
            fn act(&mut self, _: &RaceEnv) -> [f32; 4] {
                self.0
            }
        }
        let fly = |action: [f32; 4]| deploy(oval(), &mut Constant(action), &config, 0).outcome();
        assert_eq!(fly([-1.0, 0.0, 0.0, 0.0]), Outcome::Crash(CrashCause::Ground), "no thrust");
        assert_eq!(fly([1.0, 0.0, 0.0, 0.0]), Outcome::Crash(CrashCause::Ceiling), "full thrust, level");
        // Wall and gate-frame causes from placed states: race.rs tests.
    }
}
