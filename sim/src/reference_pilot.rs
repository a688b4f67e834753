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
use crate::racing_line::{PathLimits, PilotPath};
use crate::track::Track;

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

impl PilotParams {
    /// The limits of the path this tuning flies.
    fn limits(&self) -> PathLimits {
        PathLimits {
            max_speed: self.max_speed,
            max_lateral_accel: self.max_lateral_accel,
            max_longitudinal_accel: self.max_longitudinal_accel,
            min_tangent: self.min_tangent,
        }
    }
}

impl Default for PilotParams {
    fn default() -> Self {
        let PathLimits { max_speed, max_lateral_accel, max_longitudinal_accel, min_tangent } = PathLimits::default();
        Self {
            max_speed,
            max_lateral_accel,
            max_longitudinal_accel,
            min_tangent,
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
        let racing_line = PilotPath::through_gates(track, &params.limits());
        let lead_in_from = memory.lead_in_from.map(Vector3::from);
        let lead_in =
            lead_in_from.map(|from| PilotPath::lead_in(track, &from, &start_heading(track), racing_line.points[0].speed, &params.limits()));
        Self { params, racing_line: Some(racing_line), lead_in, lead_in_from, progress: memory.progress }
    }

    /// Samples of the closed path this pilot flies through `track`'s gates (for drawings).
    pub fn racing_line(&self, track: &Track) -> Vec<Vector3<f64>> {
        PilotPath::through_gates(track, &self.params.limits()).points.iter().map(|q| q.position).collect()
    }
}

/// The direction a drone faces at the start of `track`.
fn start_heading(track: &Track) -> Vector3<f64> {
    Vector3::new(track.start.yaw.cos(), track.start.yaw.sin(), 0.0)
}

impl Controller for ReferencePilot {
    fn reset(&mut self, env: &RaceEnv) {
        let track = env.track();
        let racing_line = PilotPath::through_gates(track, &self.params.limits());
        let from = env.estimate().position;
        self.lead_in = Some(PilotPath::lead_in(track, &from, &start_heading(track), racing_line.points[0].speed, &self.params.limits()));
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
        let body = env.estimate();
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
    use crate::racing_line::tests::oval;
    use crate::randomization::RandomizationParams;

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
    fn wrap_angle_stays_in_range() {
        assert!((wrap_angle(3.0 * std::f64::consts::PI) - std::f64::consts::PI).abs() < 1e-12);
        assert!((wrap_angle(-0.5) + 0.5).abs() < 1e-12);
        assert!((wrap_angle(7.0) - (7.0 - std::f64::consts::TAU)).abs() < 1e-12);
    }
}
