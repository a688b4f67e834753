//! Disturbances beyond the thesis (SPEC §13): wind with gusts acting through the drag model,
//! noise and dropout on the state estimate the controller flies on, extra control latency and
//! lost thrust. All off by default; an environment with none keeps no state for them and steps
//! exactly as before.

use std::collections::VecDeque;

use nalgebra::{UnitQuaternion, Vector3, Vector4};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;
use serde::{Deserialize, Serialize};

use crate::quadrotor::{BodyState, Command};

/// The disturbances an environment flies in (`[env.disturbance]`, `dronerace eval --wind …`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Disturbances {
    /// Mean wind speed (m/s), horizontal. 0: no wind.
    pub wind_speed: f64,
    /// Where the mean wind blows to, in degrees from +x; unset: drawn uniformly per deployment.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub wind_direction_deg: Option<f64>,
    /// Gust standard deviation (m/s) horizontally per axis; unset: 0.2 × `wind_speed` (Dryden,
    /// light turbulence at 2.5 m). The vertical gust's is half of it.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub gust_intensity: Option<f64>,
    /// State-estimate noise in multiples of a motion-capture estimate's ([`ESTIMATE_SIGMA`]).
    pub noise: f64,
    /// Probability per policy step that the estimate is not updated (the controller sees the
    /// previous step's).
    pub dropout: f64,
    /// Control latency (ms) added to the command delay.
    pub latency_ms: f64,
    /// Fraction of thrust lost, in [0, 1).
    pub thrust_loss: f64,
    /// The one motor that loses it (0–3, rotor order fr, bl, br, fl); unset: every motor.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub thrust_loss_motor: Option<usize>,
}

/// A motion-capture state estimate's 1σ errors: position 1 cm, velocity 5 cm/s, attitude 0.5°
/// about each axis, body rates 0.05 rad/s (a gyro's).
pub const ESTIMATE_SIGMA: EstimateSigma = EstimateSigma { position: 0.01, velocity: 0.05, attitude: 0.5, body_rates: 0.05 };

/// The 1σ of each part of the state estimate.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct EstimateSigma {
    /// Position (m).
    pub position: f64,
    /// Velocity (m/s).
    pub velocity: f64,
    /// Attitude, about each body axis (degrees).
    pub attitude: f64,
    /// Body rates (rad/s).
    pub body_rates: f64,
}

/// Length scales of the gusts (m) at racing altitude, horizontal and vertical (Dryden low
/// altitude, 2.5 m); at [`GUST_AIRSPEED`] they give the gusts' correlation times.
const GUST_LENGTH: [f64; 2] = [19.0, 2.5];
/// Airspeed the gusts' correlation times are taken at (m/s), a typical racing speed.
const GUST_AIRSPEED: f64 = 5.0;

/// A setting outside its range.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
#[error("env.disturbance.{field}: {reason}")]
pub struct InvalidDisturbance {
    /// The setting.
    pub field: &'static str,
    /// What is wrong.
    pub reason: String,
}

impl Disturbances {
    /// True when at least one disturbance is on.
    pub fn any(&self) -> bool {
        *self != Self::default()
    }

    /// True when none is (the default, left out of config files).
    pub fn is_off(&self) -> bool {
        !self.any()
    }

    /// Every value in its range, or the first that is not.
    pub fn check(&self) -> Result<(), InvalidDisturbance> {
        let invalid = |field, reason: String| Err(InvalidDisturbance { field, reason });
        let ranges = [
            ("wind_speed", self.wind_speed, 0.0, 50.0),
            ("gust_intensity", self.gust_intensity.unwrap_or(0.0), 0.0, 50.0),
            ("wind_direction_deg", self.wind_direction_deg.unwrap_or(0.0), -360.0, 360.0),
            ("noise", self.noise, 0.0, 1000.0),
            ("dropout", self.dropout, 0.0, 0.999),
            ("latency_ms", self.latency_ms, 0.0, 1000.0),
            ("thrust_loss", self.thrust_loss, 0.0, 0.999),
        ];
        for (field, value, low, high) in ranges {
            if !(value.is_finite() && (low..=high).contains(&value)) {
                return invalid(field, format!("{value} is outside {low}..={high}"));
            }
        }
        if let Some(motor) = self.thrust_loss_motor.filter(|&m| m > 3) {
            return invalid("thrust_loss_motor", format!("{motor}: motors are 0–3 (fr, bl, br, fl)"));
        }
        Ok(())
    }

    /// One line for a report: what this environment flew in (`nominal` for nothing).
    pub fn describe(&self) -> String {
        let mut parts = Vec::new();
        if self.wind_speed > 0.0 || self.gust_intensity.is_some_and(|g| g > 0.0) {
            let direction = self.wind_direction_deg.map_or("random direction".to_string(), |d| format!("to {d}°"));
            parts.push(format!("wind {} m/s {direction}, gusts σ {:.2} m/s", self.wind_speed, self.gust_sigma()));
        }
        if self.noise > 0.0 {
            parts.push(format!("estimate noise ×{}", self.noise));
        }
        if self.dropout > 0.0 {
            parts.push(format!("estimate dropout {} %", self.dropout * 100.0));
        }
        if self.latency_ms > 0.0 {
            parts.push(format!("latency +{} ms", self.latency_ms));
        }
        if self.thrust_loss > 0.0 {
            let which = self.thrust_loss_motor.map_or("every motor".to_string(), |m| format!("motor {m}"));
            parts.push(format!("thrust −{} % ({which})", self.thrust_loss * 100.0));
        }
        if parts.is_empty() { "nominal".into() } else { parts.join(", ") }
    }

    /// Horizontal gust standard deviation (m/s).
    fn gust_sigma(&self) -> f64 {
        self.gust_intensity.unwrap_or(0.2 * self.wind_speed)
    }

    /// Substeps of extra latency, rounded to whole substeps of length `h`.
    fn latency_substeps(&self, h: f64) -> u32 {
        (self.latency_ms / 1000.0 / h).round() as u32
    }

    /// Motor thrust factors: 1 − loss on the motor (or motors) that lose it.
    pub fn thrust_factors(&self) -> Vector4<f64> {
        match self.thrust_loss_motor {
            _ if self.thrust_loss == 0.0 => Vector4::repeat(1.0),
            None => Vector4::repeat(1.0 - self.thrust_loss),
            Some(m) => {
                let mut f = Vector4::repeat(1.0);
                f[m] = 1.0 - self.thrust_loss;
                f
            }
        }
    }
}

/// What an environment with disturbances carries from step to step: its own random stream (the
/// nominal draws stay as they were), the episode's mean wind, the gust state, the estimate the
/// controller sees and the commands still in flight.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct DisturbanceState {
    rng: ChaCha8Rng,
    mean_wind: Vector3<f64>,
    gust: Vector3<f64>,
    estimate: Option<BodyState>,
    /// Commands of the last steps, newest last, for latency beyond one step.
    history: VecDeque<Command>,
}

/// What the flight controller holds before the first command arrives: a hover.
fn before_first_command() -> Command {
    Command::hover()
}

impl DisturbanceState {
    /// A state on its own stream (`seed`, `stream`); [`DisturbanceState::reset`] draws the
    /// first episode's.
    pub fn new(seed: u64, stream: u64) -> Self {
        let mut rng = ChaCha8Rng::seed_from_u64(seed ^ 0xD157_0B5E_D157_0B5E);
        rng.set_stream(stream);
        Self { rng, mean_wind: Vector3::zeros(), gust: Vector3::zeros(), estimate: None, history: VecDeque::new() }
    }

    /// A new episode: a wind direction (when not given), gusts from their stationary spread, a
    /// fresh estimate, no commands in flight.
    pub fn reset(&mut self, d: &Disturbances, body: &BodyState) {
        let direction = d.wind_direction_deg.map_or_else(|| self.rng.random_range(0.0..std::f64::consts::TAU), f64::to_radians);
        self.mean_wind = Vector3::new(direction.cos(), direction.sin(), 0.0) * d.wind_speed;
        let sigma = gust_sigmas(d);
        self.gust = Vector3::from_fn(|k, _| sigma[k] * self.rng.sample::<f64, _>(StandardNormal));
        self.history.clear();
        self.estimate = None;
        self.observe(d, body);
    }

    /// The wind at this step (m/s, world), then the gusts moved on by one policy step of `dt`
    /// (first-order Gauss–Markov: the Dryden spectrum's shaping filter of first order).
    pub fn wind(&mut self, d: &Disturbances, dt: f64) -> Vector3<f64> {
        let wind = self.mean_wind + self.gust;
        let sigma = gust_sigmas(d);
        for k in 0..3 {
            let tau = GUST_LENGTH[usize::from(k == 2)] / GUST_AIRSPEED;
            let a = (-dt / tau).exp();
            self.gust[k] = a * self.gust[k] + sigma[k] * (1.0 - a * a).sqrt() * self.rng.sample::<f64, _>(StandardNormal);
        }
        wind
    }

    /// Records the command issued this step (at `j == 0`); returns the one in force at substep
    /// `j` of it with `delay` substeps of command delay, `d`'s latency on top and `substeps` per
    /// step: the newest command old enough, or the hover held before the first one.
    pub fn applied(&mut self, d: &Disturbances, command: &Command, delay: u32, j: u32, substeps: u32, h: f64) -> Command {
        if j == 0 {
            self.history.push_back(*command);
            let keep = ((delay + d.latency_substeps(h)) / substeps + 2) as usize;
            while self.history.len() > keep {
                self.history.pop_front();
            }
        }
        let total = delay + d.latency_substeps(h);
        if j >= total {
            return *command;
        }
        // The newest command issued at least `total` substeps before this substep.
        let steps_back = (total - j).div_ceil(substeps) as usize;
        let n = self.history.len();
        if steps_back < n { self.history[n - 1 - steps_back] } else { before_first_command() }
    }

    /// Updates the estimate from the true state: unchanged with probability `dropout`, else
    /// the state with independent Gaussian errors of `noise` × [`ESTIMATE_SIGMA`].
    pub fn observe(&mut self, d: &Disturbances, body: &BodyState) {
        if d.noise == 0.0 && d.dropout == 0.0 {
            return;
        }
        if self.estimate.is_some() && d.dropout > 0.0 && self.rng.random::<f64>() < d.dropout {
            return;
        }
        let s = ESTIMATE_SIGMA;
        let mut normal = |sigma: f64| Vector3::from_fn(|_, _| sigma * d.noise * self.rng.sample::<f64, _>(StandardNormal));
        let position = body.position + normal(s.position);
        let velocity = body.velocity + normal(s.velocity);
        let tilt = normal(s.attitude.to_radians());
        let body_rates = body.body_rates + normal(s.body_rates);
        let attitude = (UnitQuaternion::from_quaternion(body.attitude) * UnitQuaternion::from_scaled_axis(tilt)).into_inner();
        self.estimate = Some(BodyState { position, attitude, velocity, body_rates });
    }

    /// The state the controller sees, when it is not the true one.
    pub fn estimate(&self) -> Option<&BodyState> {
        self.estimate.as_ref()
    }
}

/// Gust standard deviations (m/s) along x, y (horizontal) and z (half the horizontal one).
fn gust_sigmas(d: &Disturbances) -> [f64; 3] {
    let h = d.gust_sigma();
    [h, h, h / 2.0]
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn settings_out_of_range_are_refused_by_name_and_nothing_is_off() {
        assert!(!Disturbances::default().any());
        assert_eq!(Disturbances::default().describe(), "nominal");
        let bad = Disturbances { thrust_loss: 1.0, ..Disturbances::default() };
        assert_eq!(bad.check().unwrap_err().field, "thrust_loss");
        let bad = Disturbances { thrust_loss_motor: Some(4), thrust_loss: 0.1, ..Disturbances::default() };
        assert_eq!(bad.check().unwrap_err().field, "thrust_loss_motor");
        assert_eq!(Disturbances { wind_speed: f64::NAN, ..Disturbances::default() }.check().unwrap_err().field, "wind_speed");
        let one = Disturbances { thrust_loss: 0.2, thrust_loss_motor: Some(2), ..Disturbances::default() };
        assert_eq!(one.thrust_factors(), Vector4::new(1.0, 1.0, 0.8, 1.0));
    }

    #[test]
    fn gusts_keep_their_stationary_spread_and_the_mean_wind_its_speed() {
        let d = Disturbances { wind_speed: 3.0, ..Disturbances::default() };
        let body = BodyState::at_rest(Vector3::new(0.0, 0.0, 2.0), 0.0);
        let mut state = DisturbanceState::new(7, 0);
        state.reset(&d, &body);
        let n = 100_000;
        let (mut sum, mut squares) = (Vector3::zeros(), Vector3::zeros());
        for _ in 0..n {
            let w = state.wind(&d, 0.02) - state.mean_wind;
            sum += w;
            squares += w.component_mul(&w);
        }
        assert!((state.mean_wind.norm() - 3.0).abs() < 1e-12);
        let sd = (squares / n as f64 - (sum / n as f64).map(|m| m * m)).map(f64::sqrt);
        // Correlated samples: a few percent of spread over 2,000 s of gusts.
        assert!((sd.x - 0.6).abs() < 0.1 && (sd.y - 0.6).abs() < 0.1 && (sd.z - 0.3).abs() < 0.03, "{sd:?}");
    }

    #[test]
    fn latency_delivers_each_command_the_given_substeps_late() {
        let d = Disturbances { latency_ms: 20.0, ..Disturbances::default() };
        let body = BodyState::at_rest(Vector3::zeros(), 0.0);
        let mut state = DisturbanceState::new(1, 0);
        state.reset(&d, &body);
        let command = |c: f64| Command { collective_thrust: c, body_rates: Vector3::zeros() };
        let hover = Command::hover().collective_thrust;
        let h = 0.0025; // 8 substeps a 20 ms step: 20 ms is 8 substeps, with 2 of delay 10 in all
        let mut applied = Vec::new();
        for step in 0..4 {
            for j in 0..8 {
                applied.push(state.applied(&d, &command(f64::from(step + 1)), 2, j, 8, h).collective_thrust);
            }
        }
        let expected: Vec<f64> = (0..32).map(|k: i32| if k < 10 { hover } else { f64::from((k - 10) / 8 + 1) }).collect();
        assert_eq!(applied, expected);
    }

    #[test]
    fn the_estimate_is_the_truth_with_noise_of_the_stated_spread_and_dropout_holds_it() {
        let d = Disturbances { noise: 2.0, ..Disturbances::default() };
        let body = BodyState::at_rest(Vector3::new(1.0, 2.0, 3.0), 0.5);
        let mut state = DisturbanceState::new(3, 1);
        state.reset(&d, &body);
        let n = 20_000;
        let mut squares = 0.0;
        for _ in 0..n {
            state.observe(&d, &body);
            squares += (state.estimate().unwrap().position - body.position).norm_squared();
        }
        let sigma = (squares / (3.0 * n as f64)).sqrt();
        assert!((sigma - 0.02).abs() < 0.001, "{sigma}");
        let held = Disturbances { dropout: 0.5, ..Disturbances::default() };
        let mut state = DisturbanceState::new(3, 1);
        state.reset(&held, &body);
        let first = *state.estimate().unwrap();
        let moved = BodyState::at_rest(Vector3::new(5.0, 5.0, 5.0), 0.0);
        let updates = (0..10_000)
            .filter(|_| {
                let before = *state.estimate().unwrap();
                state.observe(&held, &moved);
                *state.estimate().unwrap() != before
            })
            .count();
        assert_eq!(first.position, body.position, "no noise: the first estimate is the truth");
        assert_eq!(updates, 1, "held while dropped, then the moved state, which then stays");
    }
}
