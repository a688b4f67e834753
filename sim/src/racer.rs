//! The race state a policy reads, kept from a real drone's states: what a flight stack needs to
//! fly a trained policy without the simulator. It follows target gate, laps and previous action
//! exactly as [`crate::RaceEnv`] does (a gate counts when the path between two consecutive
//! states crosses its opening, SPEC §4) and builds the observation with the same function.

use std::sync::Arc;

use nalgebra::{Quaternion, Vector3};

use crate::observation::{ObservationLayout, write_state_observation};
use crate::quadrotor::BodyState;
use crate::racing_line::RacingLine;
use crate::track::Track;

/// A drone state as a flight stack reported it, refused: each error names the field as the
/// caller named it.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum ReportedStateError {
    /// A field has the wrong number of values.
    #[error("{field} has {got} numbers; it needs {expected}")]
    Length {
        /// The field.
        field: &'static str,
        /// Numbers sent.
        got: usize,
        /// Numbers it needs.
        expected: usize,
    },
    /// A number is NaN or infinite.
    #[error("{field}[{index}] is {value}, not a finite number")]
    NotFinite {
        /// The field.
        field: &'static str,
        /// Index within it.
        index: usize,
        /// The number sent.
        value: f64,
    },
    /// A number beyond what a drone can report: a position beyond
    /// [`crate::track::MAX_COORDINATE`], a speed beyond [`MAX_REPORTED_SPEED`] or a body rate
    /// beyond [`MAX_REPORTED_BODY_RATE`] (each component).
    #[error("{field}[{index}] is {value}, beyond the ±{limit} a drone's state may have")]
    OutOfRange {
        /// The field.
        field: &'static str,
        /// Index within it.
        index: usize,
        /// The number sent.
        value: f64,
        /// The bound of that field.
        limit: f64,
    },
    /// The orientation is not a unit quaternion (within 1e-3).
    #[error("{field} has norm {norm}; it must be a unit quaternion (w, x, y, z)")]
    NotUnitQuaternion {
        /// The field.
        field: &'static str,
        /// Its norm.
        norm: f64,
    },
}

/// Largest velocity component a reported state may have (m/s): racing drones fly below 50.
pub const MAX_REPORTED_SPEED: f64 = 100.0;
/// Largest body-rate component a reported state may have (rad/s): the rate controller's
/// commands stay within 10, and a tumbling airframe within a few tens.
pub const MAX_REPORTED_BODY_RATE: f64 = 100.0;

/// The body state of a reported drone state — position (3, m, world), velocity (3, m/s, world),
/// orientation (4: w, x, y, z; body to world) and angular velocity (3, rad/s, body), under the
/// caller's field `names` in that order — or the first thing wrong with it. The quaternion is
/// taken as sent (not renormalised), so a state read off the simulator observes exactly as the
/// simulator does.
pub fn reported_body_state(values: [&[f64]; 4], names: [&'static str; 4]) -> Result<BodyState, ReportedStateError> {
    for (field, (values, expected)) in names.into_iter().zip(values.into_iter().zip([3, 3, 4, 3])) {
        if values.len() != expected {
            return Err(ReportedStateError::Length { field, got: values.len(), expected });
        }
        if let Some(index) = values.iter().position(|v| !v.is_finite()) {
            return Err(ReportedStateError::NotFinite { field, index, value: values[index] });
        }
    }
    // The orientation is bounded by the unit-norm check below.
    let limits = [crate::track::MAX_COORDINATE, MAX_REPORTED_SPEED, f64::INFINITY, MAX_REPORTED_BODY_RATE];
    for (field, (values, limit)) in names.into_iter().zip(values.into_iter().zip(limits)) {
        if let Some(index) = values.iter().position(|v| v.abs() > limit) {
            return Err(ReportedStateError::OutOfRange { field, index, value: values[index], limit });
        }
    }
    let [p, v, q, w] = values;
    let norm = q.iter().map(|x| x * x).sum::<f64>().sqrt();
    if (norm - 1.0).abs() > 1e-3 {
        return Err(ReportedStateError::NotUnitQuaternion { field: names[2], norm });
    }
    let v3 = |v: &[f64]| Vector3::new(v[0], v[1], v[2]);
    Ok(BodyState { position: v3(p), attitude: Quaternion::new(q[0], q[1], q[2], q[3]), velocity: v3(v), body_rates: v3(w) })
}

/// One race on one track, fed the drone's state once per control step.
#[derive(Clone, Debug)]
pub struct Racer {
    track: Arc<Track>,
    layout: ObservationLayout,
    line: Option<Arc<RacingLine>>,
    target: usize,
    laps: u32,
    gate0_passed: bool,
    previous_action: [f64; 4],
    previous_position: Option<Vector3<f64>>,
}

impl Racer {
    /// A race on `track` from its start: target gate 0, no laps, no previous action; the
    /// observation in `layout` (the policy's).
    pub fn new(track: Arc<Track>, layout: ObservationLayout) -> Self {
        let line = (layout.line_points > 0).then(|| Arc::new(RacingLine::new(&track)));
        Self { track, layout, line, target: 0, laps: 0, gate0_passed: false, previous_action: [0.0; 4], previous_position: None }
    }

    /// Takes the drone's state at a control step (one step after the previous one): counts the
    /// target gate if the path since the previous state passed it, then returns the
    /// observation the policy acts on.
    pub fn observe(&mut self, body: &BodyState) -> Vec<f32> {
        if let Some(from) = self.previous_position
            && self.track.gates[self.target].crossing(&from, &body.position).is_some()
        {
            if self.target == 0 {
                // Targets advance strictly in order, so a repeat pass of gate 0 closes a lap.
                self.laps += u32::from(self.gate0_passed);
                self.gate0_passed = true;
            }
            self.target = self.track.next_index(self.target);
        }
        self.previous_position = Some(body.position);
        let mut out = vec![0.0; self.layout.dim()];
        write_state_observation(body, &self.previous_action, &self.track, self.line.as_deref(), self.target, self.layout, &mut out);
        out
    }

    /// Records the action flown from the state just observed (the next observation reads it).
    pub fn acted(&mut self, action: &[f32; 4]) {
        self.previous_action = action.map(|a| f64::from(a).clamp(-1.0, 1.0));
    }

    /// The gate the drone races to now.
    pub fn target_gate(&self) -> usize {
        self.target
    }

    /// Laps completed.
    pub fn laps(&self) -> u32 {
        self.laps
    }

    /// The track.
    pub fn track(&self) -> &Arc<Track> {
        &self.track
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::{Controller, EnvConfig, RaceEnv, ReferencePilot};

    #[test]
    fn a_reported_state_is_refused_naming_the_field_and_entry() {
        let names = ["p", "v", "q", "w"];
        let (ok, unit) = ([0.0; 3], [1.0, 0.0, 0.0, 0.0]);
        let body = reported_body_state([&[1.0, 2.0, 3.0], &ok, &unit, &[0.1, 0.2, 0.3]], names).unwrap();
        assert_eq!((body.position, body.body_rates), (Vector3::new(1.0, 2.0, 3.0), Vector3::new(0.1, 0.2, 0.3)));
        let short = reported_body_state([&[0.0, 1.0], &ok, &unit, &ok], names).unwrap_err();
        assert_eq!(short, ReportedStateError::Length { field: "p", got: 2, expected: 3 });
        let nan = reported_body_state([&ok, &ok, &unit, &[0.0, f64::NAN, 0.0]], names).unwrap_err();
        assert!(matches!(nan, ReportedStateError::NotFinite { field: "w", index: 1, .. }), "{nan}");
        let skewed = reported_body_state([&ok, &ok, &[2.0, 0.0, 0.0, 0.0], &ok], names).unwrap_err();
        assert_eq!(skewed, ReportedStateError::NotUnitQuaternion { field: "q", norm: 2.0 });
        // Finite but beyond any drone: 1e308 m made every observation −inf before.
        let far = reported_body_state([&[1e308, 0.0, 0.0], &ok, &unit, &ok], names).unwrap_err();
        assert!(matches!(far, ReportedStateError::OutOfRange { field: "p", index: 0, .. }), "{far}");
        let fast = reported_body_state([&ok, &[0.0, 0.0, -101.0], &unit, &ok], names).unwrap_err();
        assert!(matches!(fast, ReportedStateError::OutOfRange { field: "v", index: 2, limit: 100.0, .. }), "{fast}");
        let spinning = reported_body_state([&ok, &ok, &unit, &[0.0, 1e6, 0.0]], names).unwrap_err();
        assert!(matches!(spinning, ReportedStateError::OutOfRange { field: "w", index: 1, .. }), "{spinning}");
    }

    /// The reference pilot flies three laps of a library-like track; a racer fed only the
    /// drone's states sees every observation, target gate and lap count the environment has.
    #[test]
    fn a_racer_fed_the_drones_states_keeps_the_race_as_the_environment_does() {
        let gates = vec![
            crate::Gate::new(Vector3::new(6.0, 0.0, 2.0), std::f64::consts::FRAC_PI_2),
            crate::Gate::new(Vector3::new(0.0, 6.0, 2.0), std::f64::consts::PI),
            crate::Gate::new(Vector3::new(-6.0, 0.0, 2.0), -std::f64::consts::FRAC_PI_2),
            crate::Gate::new(Vector3::new(0.0, -6.0, 2.0), 0.0),
        ];
        let track = Arc::new(Track::new("square", gates, None, crate::Arena::default()).unwrap());
        let mut config = EnvConfig::evaluation();
        config.race.max_episode_steps = 2000;
        let mut env = RaceEnv::new(track.clone(), config, 0, 3);
        let layout = env.config().observation;
        let mut racer = Racer::new(track, layout);
        let mut pilot = ReferencePilot::default();
        pilot.reset(&env);
        let mut laps_seen = 0;
        for step in 0..1500 {
            let expected = env.observation_in(layout);
            assert_eq!(racer.observe(env.body()), expected, "step {step}");
            assert_eq!((racer.target_gate(), racer.laps()), (env.target_gate(), env.stats().laps), "step {step}");
            let action = pilot.act(&env);
            racer.acted(&action);
            let out = env.step(&action);
            laps_seen = env.stats().laps;
            if out.done() {
                break;
            }
        }
        assert!(laps_seen >= 2, "the pilot flew {laps_seen} laps: the lap counting was exercised");
    }
}
