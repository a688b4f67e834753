//! Reference pilot: a non-learned controller that proves tracks are flyable and is the first
//! baseline for every learned policy.
//!
//! It builds a closed cubic Hermite path through the gate centres (tangent = gate normal),
//! gives it a speed profile limited by lateral and longitudinal acceleration, and tracks it:
//! desired acceleration → collective thrust along the current body z and body rates that turn
//! the thrust axis towards the desired one while the nose follows the path.

use nalgebra::Vector3;
use serde::{Deserialize, Serialize};

use crate::params::GRAVITY;
use crate::quadrotor::Command;
use crate::race::RaceEnv;
use crate::track::{Arena, Track};

/// Anything that flies a [`RaceEnv`]: the reference pilot, a learned policy, a replay.
pub trait Controller: Send {
    /// Called at the start of every episode.
    fn reset(&mut self, env: &RaceEnv);
    /// The normalised action for the environment's current state.
    fn act(&mut self, env: &RaceEnv) -> [f32; 4];
}

/// Tuning of the reference pilot.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct PilotParams {
    /// Top speed on straights (m/s).
    pub max_speed: f64,
    /// Lateral acceleration allowed in turns (m/s²).
    pub max_lateral_accel: f64,
    /// Longitudinal acceleration and braking allowed (m/s²).
    pub max_longitudinal_accel: f64,
    /// Shortest Hermite tangent (m): gives tight reversals room to turn.
    pub min_tangent: f64,
    /// How far ahead on the path the reference is taken, as time at the local speed (s).
    pub look_ahead: f64,
    /// Position gain (1/s²).
    pub position_gain: f64,
    /// Velocity gain (1/s).
    pub velocity_gain: f64,
    /// Thrust-axis tilt gain: body rate per radian of error (1/s).
    pub attitude_gain: f64,
    /// Heading gain: yaw rate per radian of error (1/s).
    pub yaw_gain: f64,
    /// Largest tilt of the thrust axis from vertical (rad).
    pub max_tilt: f64,
}

impl Default for PilotParams {
    fn default() -> Self {
        Self {
            max_speed: 9.0,
            max_lateral_accel: 10.0,
            max_longitudinal_accel: 7.0,
            min_tangent: 5.0,
            look_ahead: 0.08,
            position_gain: 8.0,
            velocity_gain: 5.5,
            // 16 makes the attitude loop oscillate against the 20 ms step and the rate loop.
            attitude_gain: 12.0,
            yaw_gain: 3.0,
            max_tilt: 65f64.to_radians(),
        }
    }
}

/// One sample of a pilot path.
#[derive(Clone, Copy, Debug)]
struct PathPoint {
    position: Vector3<f64>,
    tangent: Vector3<f64>,
    /// Curvature vector d²p/ds² (1/m, points to the centre of the turn).
    curvature: Vector3<f64>,
    /// Planned speed (m/s).
    speed: f64,
}

/// A sampled reference path: the closed loop through the gates, or an open lead-in.
#[derive(Clone, Debug)]
struct PilotPath {
    points: Vec<PathPoint>,
    closed: bool,
}

/// Samples per Hermite segment.
const SAMPLES_PER_SEGMENT: usize = 200;
/// Tangent lengths tried for a segment, as multiples of its chord, in order of preference.
const TANGENT_SCALES: [f64; 8] = [1.0, 0.75, 1.25, 1.5, 0.5, 2.0, 2.5, 3.0];
/// Slowest turn-limited speed a segment may demand before a wider shape is preferred (m/s).
const MIN_TURN_SPEED: f64 = 2.5;
/// Clearance the path keeps from every gate frame and the arena walls (m).
const FRAME_CLEARANCE: f64 = 0.45;

impl PilotPath {
    /// The closed loop through every gate centre along the gate normals.
    fn through_gates(track: &Track, p: &PilotParams) -> Self {
        let mut points = Vec::with_capacity(track.gates.len() * SAMPLES_PER_SEGMENT);
        for (i, a) in track.gates.iter().enumerate() {
            let b = &track.gates[track.next_index(i)];
            points.extend(clear_segment(track, (&a.position, &a.normal()), (&b.position, &b.normal()), p.min_tangent, p));
        }
        Self::from_points(points, true, p)
    }

    /// An open path from `from` (leaving along `heading`) through gate 0 and 2 m beyond, at
    /// `end_speed` from gate 0 on.
    fn lead_in(track: &Track, from: &Vector3<f64>, heading: &Vector3<f64>, end_speed: f64, p: &PilotParams) -> Self {
        let g0 = &track.gates[0];
        let (centre, normal) = (g0.position, g0.normal());
        let beyond = centre + normal * 2.0;
        let mut points = clear_segment(track, (from, heading), (&centre, &normal), 1.0, p);
        points.extend(hermite_samples((&centre, &normal), (&beyond, &normal), 2.0, SAMPLES_PER_SEGMENT / 4));
        // The start may be offset sideways from the gate by most of its opening: take the
        // resulting S-bend gently, since overshooting it means the frame.
        let gentle = PilotParams { max_lateral_accel: p.max_lateral_accel / 2.0, ..*p };
        let mut path = Self::from_points(points, false, &gentle);
        path.cap_speed_from(path.points.len() - SAMPLES_PER_SEGMENT / 4, end_speed, p);
        path
    }

    fn from_points(points: Vec<PathPoint>, closed: bool, p: &PilotParams) -> Self {
        let mut path = Self { points, closed };
        for q in &mut path.points {
            let turn_limit = (p.max_lateral_accel / q.curvature.norm().max(1e-9)).sqrt();
            q.speed = p.max_speed.min(turn_limit);
        }
        path.limit_acceleration(p);
        path
    }

    /// Caps the speed from sample `from` on and re-plans braking before it.
    fn cap_speed_from(&mut self, from: usize, cap: f64, p: &PilotParams) {
        for q in &mut self.points[from..] {
            q.speed = q.speed.min(cap);
        }
        self.limit_acceleration(p);
    }

    /// Lowers speeds so that forward and backward they change no faster than the longitudinal
    /// limit allows (twice around a closed loop so its seam settles). Only ever lowers.
    fn limit_acceleration(&mut self, p: &PilotParams) {
        let n = self.points.len();
        let limit = |v: f64, ds: f64| (v * v + 2.0 * p.max_longitudinal_accel * ds).sqrt();
        let (passes, pairs) = if self.closed { (2, n) } else { (1, n - 1) };
        for _ in 0..passes {
            for i in 0..pairs {
                let (a, b) = (i, (i + 1) % n);
                let ds = (self.points[b].position - self.points[a].position).norm();
                self.points[b].speed = self.points[b].speed.min(limit(self.points[a].speed, ds));
            }
            for i in (0..pairs).rev() {
                let (a, b) = (i, (i + 1) % n);
                let ds = (self.points[b].position - self.points[a].position).norm();
                self.points[a].speed = self.points[a].speed.min(limit(self.points[b].speed, ds));
            }
        }
    }

    /// The sample after `i`, or `None` at the end of an open path.
    fn next(&self, i: usize) -> Option<usize> {
        match (i + 1 < self.points.len(), self.closed) {
            (true, _) => Some(i + 1),
            (false, true) => Some(0),
            (false, false) => None,
        }
    }

    /// Index `distance` metres of arc after `from` (the last sample of an open path at most).
    fn ahead(&self, from: usize, distance: f64) -> usize {
        let (mut i, mut travelled) = (from, 0.0);
        while let Some(next) = self.next(i) {
            travelled += (self.points[next].position - self.points[i].position).norm();
            if travelled > distance || next == from {
                break;
            }
            i = next;
        }
        i
    }

    /// Nearest sample to `p` from a few samples behind `from` to `distance` metres ahead.
    fn nearest_ahead(&self, p: &Vector3<f64>, from: usize, distance: f64) -> usize {
        let n = self.points.len();
        let mut i = if self.closed { (from + n - 5) % n } else { from.saturating_sub(5) };
        let end = self.ahead(from, distance);
        let mut best = (f64::INFINITY, from);
        loop {
            let d = (self.points[i].position - p).norm_squared();
            if d < best.0 {
                best = (d, i);
            }
            if i == end {
                return best.1;
            }
            i = self.next(i).unwrap_or(end);
        }
    }
}

/// Samples of the cubic Hermite curve between two (position, unit direction) ends with
/// tangent length `scale`.
fn hermite_samples(
    (p0, d0): (&Vector3<f64>, &Vector3<f64>),
    (p1, d1): (&Vector3<f64>, &Vector3<f64>),
    scale: f64,
    samples: usize,
) -> Vec<PathPoint> {
    let (m0, m1) = (d0 * scale, d1 * scale);
    (0..samples)
        .map(|k| {
            let u = k as f64 / samples as f64;
            let (u2, u3) = (u * u, u * u * u);
            let position = p0 * (2.0 * u3 - 3.0 * u2 + 1.0) + m0 * (u3 - 2.0 * u2 + u) + p1 * (-2.0 * u3 + 3.0 * u2) + m1 * (u3 - u2);
            let first =
                p0 * (6.0 * u2 - 6.0 * u) + m0 * (3.0 * u2 - 4.0 * u + 1.0) + p1 * (-6.0 * u2 + 6.0 * u) + m1 * (3.0 * u2 - 2.0 * u);
            let second = p0 * (12.0 * u - 6.0) + m0 * (6.0 * u - 4.0) + p1 * (-12.0 * u + 6.0) + m1 * (6.0 * u - 2.0);
            // A zero-length curve (a gate to itself) still needs a direction.
            let speed = first.norm();
            let tangent = if speed > 1e-12 { first / speed } else { *d0 };
            let curvature = if speed > 1e-12 { (second - tangent * second.dot(&tangent)) / (speed * speed) } else { Vector3::zeros() };
            PathPoint { position, tangent, curvature, speed: 0.0 }
        })
        .collect()
}

/// The Hermite segment with the first tangent length (in [`TANGENT_SCALES`] order) that stays
/// clear of every gate frame and inside the arena without a near-cusp turn; failing that, the
/// one with the fewest samples too close, then without a cusp.
#[allow(clippy::expect_used, reason = "TANGENT_SCALES is a non-empty constant")]
fn clear_segment(
    track: &Track,
    from: (&Vector3<f64>, &Vector3<f64>),
    to: (&Vector3<f64>, &Vector3<f64>),
    min_tangent: f64,
    p: &PilotParams,
) -> Vec<PathPoint> {
    let chord = (to.0 - from.0).norm().max(min_tangent);
    let margin = Vector3::repeat(FRAME_CLEARANCE);
    let inside = Arena { min: track.arena.min + margin, max: track.arena.max - margin };
    let too_close =
        |q: &PathPoint| !inside.contains(&q.position) || track.gates.iter().any(|g| g.frame_touches_sphere(&q.position, FRAME_CLEARANCE));
    // A turn so tight that the drone must nearly stop in it.
    let cusp = |q: &PathPoint| p.max_lateral_accel / q.curvature.norm().max(1e-9) < MIN_TURN_SPEED.powi(2);
    TANGENT_SCALES
        .iter()
        .map(|s| {
            let points = hermite_samples(from, to, s * chord, SAMPLES_PER_SEGMENT);
            ((points.iter().filter(|q| too_close(q)).count(), points.iter().any(cusp)), points)
        })
        .min_by_key(|(key, _)| *key)
        .map(|(_, points)| points)
        .expect("at least one tangent scale")
}

/// The reference pilot; stateful (it remembers its path and progress).
#[derive(Clone, Debug, Default)]
pub struct ReferencePilot {
    params: PilotParams,
    /// The closed loop through the gates.
    racing_line: Option<PilotPath>,
    /// From the episode's start to gate 0; dropped once gate 0 is passed.
    lead_in: Option<PilotPath>,
    /// Where the lead-in starts (the episode's start position), while it is flown.
    lead_in_from: Option<Vector3<f64>>,
    progress: usize,
}

/// What a pilot remembers of its episode beyond the track, so that a checkpoint can hold a
/// pilot mid-flight in a few bytes: its paths are rebuilt from the track, deterministically.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct PilotMemory {
    /// Index of the path point the pilot is at.
    progress: usize,
    /// Start of the lead-in, while the pilot is still on it.
    lead_in_from: Option<[f64; 3]>,
}

impl ReferencePilot {
    /// A pilot with the given tuning.
    pub fn new(params: PilotParams) -> Self {
        Self { params, racing_line: None, lead_in: None, lead_in_from: None, progress: 0 }
    }

    /// What this pilot remembers of its episode; `None` before its first reset.
    pub fn memory(&self) -> Option<PilotMemory> {
        self.racing_line.as_ref().map(|_| PilotMemory { progress: self.progress, lead_in_from: self.lead_in_from.map(Into::into) })
    }

    /// A pilot tuned by `params` in the middle of an episode on `track`, as [`Self::memory`]
    /// left it: it acts from here exactly as the remembered pilot would.
    pub fn recall(params: PilotParams, track: &Track, memory: PilotMemory) -> Self {
        let racing_line = PilotPath::through_gates(track, &params);
        let lead_in_from = memory.lead_in_from.map(Vector3::from);
        let lead_in =
            lead_in_from.map(|from| PilotPath::lead_in(track, &from, &start_heading(track), racing_line.points[0].speed, &params));
        Self { params, racing_line: Some(racing_line), lead_in, lead_in_from, progress: memory.progress }
    }

    /// Samples of the closed path this pilot flies through `track`'s gates (for drawings).
    pub fn racing_line(&self, track: &Track) -> Vec<Vector3<f64>> {
        PilotPath::through_gates(track, &self.params).points.iter().map(|q| q.position).collect()
    }
}

/// A sample of the reference pilot's closed racing line with the gate it leads to: where a
/// training episode can start in flight ([`crate::StartGate::Flying`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LinePoint {
    /// Position (m).
    pub position: Vector3<f64>,
    /// Unit direction of travel.
    pub direction: Vector3<f64>,
    /// The default pilot's planned speed here (m/s).
    pub speed: f64,
    /// The next gate along the line.
    pub target: usize,
}

/// The default-tuned reference pilot's closed racing line through a track's gates, sample by
/// sample (each leg from gate i to gate i + 1 has the same number of samples), with its arc
/// length: where flying starts are drawn ([`crate::StartGate::Flying`]) and what the line
/// observation reads ([`crate::ObservationLayout::line_points`]).
#[derive(Clone, Debug)]
pub struct RacingLine {
    points: Vec<LinePoint>,
    /// Arc length from sample 0 to each sample (m).
    arc: Vec<f64>,
    /// Length of the closed loop (m).
    length: f64,
}

impl RacingLine {
    /// The line the default-tuned pilot would fly round `track`.
    pub fn new(track: &Track) -> Self {
        let path = PilotPath::through_gates(track, &PilotParams::default());
        let points: Vec<LinePoint> = path
            .points
            .iter()
            .enumerate()
            .map(|(k, q)| LinePoint {
                position: q.position,
                direction: q.tangent,
                speed: q.speed,
                target: track.next_index(k / SAMPLES_PER_SEGMENT),
            })
            .collect();
        let mut arc = Vec::with_capacity(points.len());
        let mut length = 0.0;
        for (k, q) in points.iter().enumerate() {
            arc.push(length);
            length += (points[(k + 1) % points.len()].position - q.position).norm();
        }
        Self { points, arc, length }
    }

    /// Its samples in racing order, starting at gate 0.
    pub fn points(&self) -> &[LinePoint] {
        &self.points
    }

    /// Index of the sample nearest to `p` on the leg that leads into gate `target`.
    ///
    /// Searching one leg only keeps the answer on the part of the line the drone is racing,
    /// where the line crosses itself or passes close to an earlier leg.
    pub fn nearest_on_leg(&self, p: &Vector3<f64>, target: usize) -> usize {
        let legs = self.points.len() / SAMPLES_PER_SEGMENT;
        let first = (target + legs - 1) % legs * SAMPLES_PER_SEGMENT;
        (first..first + SAMPLES_PER_SEGMENT)
            .map(|k| ((self.points[k].position - p).norm_squared(), k))
            .min_by(|a, b| a.0.total_cmp(&b.0))
            .map_or(first, |(_, k)| k)
    }

    /// The distance from `p` to gate `target` along the line: to the nearest sample of the leg
    /// into that gate, then along the line to the leg's end, the gate's centre (m).
    pub fn remaining_on_leg(&self, p: &Vector3<f64>, target: usize) -> f64 {
        let k = self.nearest_on_leg(p, target);
        let end = (k / SAMPLES_PER_SEGMENT + 1) * SAMPLES_PER_SEGMENT;
        let end_arc = if end == self.points.len() { self.length } else { self.arc[end] };
        (self.points[k].position - p).norm() + end_arc - self.arc[k]
    }

    /// The point `distance` metres of arc after sample `from`, round the closed loop
    /// (interpolated between samples).
    pub fn ahead(&self, from: usize, distance: f64) -> Vector3<f64> {
        let s = (self.arc[from] + distance).rem_euclid(self.length);
        let k = self.arc.partition_point(|&a| a <= s).saturating_sub(1);
        let next = (k + 1) % self.points.len();
        let span = if next == 0 { self.length - self.arc[k] } else { self.arc[next] - self.arc[k] };
        let t = if span > 0.0 { (s - self.arc[k]) / span } else { 0.0 };
        self.points[k].position.lerp(&self.points[next].position, t)
    }
}

/// The direction a drone faces at the start of `track`.
fn start_heading(track: &Track) -> Vector3<f64> {
    Vector3::new(track.start.yaw.cos(), track.start.yaw.sin(), 0.0)
}

impl Controller for ReferencePilot {
    fn reset(&mut self, env: &RaceEnv) {
        let track = env.track();
        let racing_line = PilotPath::through_gates(track, &self.params);
        let from = env.body().position;
        self.lead_in = Some(PilotPath::lead_in(track, &from, &start_heading(track), racing_line.points[0].speed, &self.params));
        self.lead_in_from = Some(from);
        self.racing_line = Some(racing_line);
        self.progress = 0;
    }

    #[allow(clippy::expect_used, reason = "the Controller contract: reset before act")]
    fn act(&mut self, env: &RaceEnv) -> [f32; 4] {
        let p = self.params;
        if self.lead_in.is_some() && env.stats().gates_passed > 0 {
            // Through gate 0: join the racing line where it leaves gate 0.
            self.lead_in = None;
            self.lead_in_from = None;
            self.progress = 0;
        }
        let path = self.lead_in.as_ref().or(self.racing_line.as_ref()).expect("reset before act");
        let body = env.body();
        // Progress only moves as far along the path as the drone can fly in a few steps, so a
        // crossing (figure eight) or a nearby reversal never makes it jump to another branch.
        self.progress = path.nearest_ahead(&body.position, self.progress, body.velocity.norm() * 0.1 + 0.3);
        let here = path.points[self.progress];
        let reference = path.points[path.ahead(self.progress, here.speed * p.look_ahead)];
        // Never ask for much more speed than the drone has: from rest, ramp up.
        let speed = reference.speed.min(body.velocity.dot(&here.tangent).max(0.0) + 0.4 * p.max_longitudinal_accel);

        let desired_accel = reference.curvature * speed.powi(2)
            + (reference.position - body.position) * p.position_gain
            + (reference.tangent * speed - body.velocity) * p.velocity_gain;
        let mut thrust = desired_accel + Vector3::new(0.0, 0.0, GRAVITY);
        // Keep the thrust axis within the tilt limit by trimming the horizontal part.
        thrust.z = thrust.z.max(0.2 * GRAVITY);
        let horizontal = thrust.xy().norm();
        let max_horizontal = thrust.z * p.max_tilt.tan();
        if horizontal > max_horizontal {
            let s = max_horizontal / horizontal;
            thrust.x *= s;
            thrust.y *= s;
        }
        let axis_desired = thrust.normalize();

        let r = body.rotation();
        let axis = r.column(2).into_owned();
        let collective = thrust.dot(&axis).max(0.0);
        let tilt_error_world = axis.cross(&axis_desired);
        let angle = tilt_error_world.norm().atan2(axis.dot(&axis_desired));
        let tilt_error_body = r.transpose() * tilt_error_world.try_normalize(1e-9).unwrap_or_default() * angle;

        let heading = here.tangent.y.atan2(here.tangent.x);
        let yaw_error = wrap_angle(heading - body.yaw());
        let command = Command {
            collective_thrust: collective,
            body_rates: Vector3::new(p.attitude_gain * tilt_error_body.x, p.attitude_gain * tilt_error_body.y, p.yaw_gain * yaw_error),
        };
        command.to_action(&env.config().quadrotor).map(|a| a.clamp(-1.0, 1.0) as f32)
    }
}

/// Wraps an angle into (-π, π].
fn wrap_angle(a: f64) -> f64 {
    let mut a = a % std::f64::consts::TAU;
    if a > std::f64::consts::PI {
        a -= std::f64::consts::TAU;
    } else if a <= -std::f64::consts::PI {
        a += std::f64::consts::TAU;
    }
    a
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::race::EnvConfig;
    use crate::randomization::RandomizationParams;
    use crate::track::{Arena, Gate};
    use std::sync::Arc;

    fn oval() -> Arc<Track> {
        let g = |x, y, yaw_deg: f64| Gate::new(Vector3::new(x, y, 2.5), yaw_deg.to_radians());
        Arc::new(
            Track::new("oval", vec![g(0.0, -6.0, 0.0), g(9.0, 0.0, 90.0), g(0.0, 6.0, 180.0), g(-9.0, 0.0, -90.0)], None, Arena::default())
                .unwrap(),
        )
    }

    #[test]
    fn hermite_path_passes_through_every_gate_along_its_normal() {
        let track = oval();
        let path = PilotPath::through_gates(&track, &PilotParams::default());
        for (i, g) in track.gates.iter().enumerate() {
            let q = path.points[i * SAMPLES_PER_SEGMENT];
            assert!((q.position - g.position).norm() < 1e-12);
            assert!((q.tangent - g.normal()).norm() < 1e-12);
        }
        assert!(path.points.iter().all(|q| q.speed > 0.5 && q.speed <= 9.0));
    }

    #[test]
    fn the_pilot_laps_an_oval_without_crashing() {
        let config = EnvConfig { randomization: RandomizationParams::none(), ..EnvConfig::evaluation() };
        let mut env = RaceEnv::new(oval(), config, 0, 0);
        let mut pilot = ReferencePilot::default();
        pilot.reset(&env);
        for _ in 0..1000 {
            let a = pilot.act(&env);
            let out = env.step(&a);
            assert!(!out.terminated, "crashed: {:?} at t = {}", out.crash, env.time());
        }
        assert!(env.stats().laps >= 2, "laps {}", env.stats().laps);
    }

    #[test]
    fn a_recalled_pilot_flies_on_exactly_as_the_remembered_one() {
        let config = EnvConfig { randomization: RandomizationParams::none(), ..EnvConfig::evaluation() };
        let mut env = RaceEnv::new(oval(), config, 0, 0);
        let mut pilot = ReferencePilot::default();
        assert_eq!(pilot.memory(), None, "nothing to remember before a reset");
        pilot.reset(&env);
        // Once on the lead-in, once on the racing line (gate 0 passed by step 150).
        for split in [20, 150] {
            while env.stats().length < split {
                let a = pilot.act(&env);
                env.step(&a);
            }
            let memory = pilot.memory().unwrap();
            assert_eq!(memory.lead_in_from.is_some(), split == 20);
            let mut recalled = ReferencePilot::recall(PilotParams::default(), env.track(), memory);
            let mut twin = env.clone();
            for _ in 0..50 {
                let (a, b) = (pilot.act(&env), recalled.act(&twin));
                assert_eq!(a, b);
                env.step(&a);
                twin.step(&b);
            }
        }
    }

    #[test]
    fn the_racing_line_is_searched_on_the_target_leg_and_walked_by_arc_length() {
        let track = oval();
        let line = RacingLine::new(&track);
        let legs = track.gates.len();
        assert_eq!(line.points().len(), legs * SAMPLES_PER_SEGMENT);
        for target in 0..legs {
            // A point on the leg into `target` is found there, and nowhere else.
            let k = (target + legs - 1) % legs * SAMPLES_PER_SEGMENT + SAMPLES_PER_SEGMENT / 3;
            let p = line.points()[k].position + Vector3::new(0.0, 0.0, 0.2);
            assert_eq!(line.nearest_on_leg(&p, target), k);
            assert_eq!(line.points()[k].target, target);
            // Searching another leg answers on that leg.
            let other = track.next_index(target);
            assert_eq!(line.points()[line.nearest_on_leg(&p, other)].target, other);
        }
        // Along the line the remaining distance falls by the arc flown and ends at the gate.
        let k = SAMPLES_PER_SEGMENT + 20;
        let (here, further) = (line.points()[k].position, line.points()[k + 100].position);
        let target = line.points()[k].target;
        let flown = line.arc[k + 100] - line.arc[k];
        assert!((line.remaining_on_leg(&here, target) - line.remaining_on_leg(&further, target) - flown).abs() < 1e-9);
        let gate = track.gates[target].position;
        let near_gate = line.points()[k / SAMPLES_PER_SEGMENT * SAMPLES_PER_SEGMENT + SAMPLES_PER_SEGMENT - 1].position;
        assert!((line.remaining_on_leg(&near_gate, target) - (gate - near_gate).norm()).abs() < 1e-3);
        // Off the line it adds the way back to it.
        let off = here + Vector3::new(0.0, 0.0, 0.5);
        assert!((line.remaining_on_leg(&off, target) - line.remaining_on_leg(&here, target) - 0.5).abs() < 1e-9);
        // Walking ahead: zero metres is the sample itself, a whole loop comes back to it, and a
        // short step lands at that distance (chord ≈ arc on a smooth line).
        for k in [0, 57, line.points().len() - 1] {
            let q = line.points()[k].position;
            assert!((line.ahead(k, 0.0) - q).norm() < 1e-9);
            assert!((line.ahead(k, line.length) - q).norm() < 1e-6);
            let step = (line.ahead(k, 0.5) - q).norm();
            assert!((step - 0.5).abs() < 0.01, "0.5 m of arc from sample {k} is {step} m away");
        }
    }

    #[test]
    fn wrap_angle_stays_in_range() {
        assert!((wrap_angle(3.0 * std::f64::consts::PI) - std::f64::consts::PI).abs() < 1e-12);
        assert!((wrap_angle(-0.5) + 0.5).abs() < 1e-12);
        assert!((wrap_angle(7.0) - (7.0 - std::f64::consts::TAU)).abs() < 1e-12);
    }
}
