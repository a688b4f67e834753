//! Domain randomisation at every episode start (SPEC §3, thesis Table A.2).

use nalgebra::{UnitQuaternion, Vector3, Vector4};
use rand::Rng;
use serde::{Deserialize, Serialize};

use crate::params::QuadrotorParams;
use crate::quadrotor::BodyState;
use crate::track::Pose;

/// Ranges of the per-episode randomisation. Relative factors draw `nominal · U(1-r, 1+r)`;
/// absolute ones draw `U(-r, r)` (delay: `U(0, r)`).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct RandomizationParams {
    /// Relative range of the mass. SB 0.05.
    pub mass: f64,
    /// Relative range of each inertia axis (drawn per axis). SB 0.2.
    pub inertia: f64,
    /// Relative range of the drag coefficients (one factor for all axes). SB 0.5.
    pub drag: f64,
    /// Relative range of the thrust map coefficient. SB 0.2.
    pub thrust_map: f64,
    /// Largest command delay (s), rounded to whole substeps. SB 0.02.
    pub command_delay: f64,
    /// Start position offset in x and y (m). SB 0.8.
    pub start_xy: f64,
    /// Start position offset in z (m). SB 0.6.
    pub start_z: f64,
    /// Start velocity per axis (m/s). SB 0.8.
    pub start_velocity: f64,
    /// Start roll, pitch and yaw about the start attitude (rad). SB 20°.
    pub start_attitude: f64,
    /// Start body rates per axis (rad/s). SB 45°/s.
    pub start_body_rates: f64,
    /// Largest share of its thrust each motor may lose, drawn per motor `U(0, r)` (a weak or
    /// damaged motor, SPEC §13). Beyond the thesis: 0 in SPEC's profiles.
    pub motor_thrust: f64,
}

impl Default for RandomizationParams {
    fn default() -> Self {
        Self::state_based()
    }
}

impl RandomizationParams {
    /// The state-based (SB) training profile.
    pub fn state_based() -> Self {
        Self {
            mass: 0.05,
            inertia: 0.2,
            drag: 0.5,
            thrust_map: 0.2,
            command_delay: 0.02,
            start_xy: 0.8,
            start_z: 0.6,
            start_velocity: 0.8,
            start_attitude: 20f64.to_radians(),
            start_body_rates: 45f64.to_radians(),
            motor_thrust: 0.0,
        }
    }

    /// The vision-based (VB) training profile.
    pub fn vision_based() -> Self {
        Self {
            mass: 0.05,
            inertia: 0.2,
            drag: 0.2,
            thrust_map: 0.2,
            command_delay: 0.01,
            start_xy: 0.4,
            start_z: 0.3,
            start_velocity: 0.4,
            start_attitude: 10f64.to_radians(),
            start_body_rates: 25f64.to_radians(),
            motor_thrust: 0.0,
        }
    }

    /// Evaluation (SPEC §9): nominal dynamics, only the start position perturbed.
    pub fn evaluation() -> Self {
        Self { start_xy: 0.8, start_z: 0.6, ..Self::none() }
    }

    /// No randomisation at all.
    pub fn none() -> Self {
        Self {
            mass: 0.0,
            inertia: 0.0,
            drag: 0.0,
            thrust_map: 0.0,
            command_delay: 0.0,
            start_xy: 0.0,
            start_z: 0.0,
            start_velocity: 0.0,
            start_attitude: 0.0,
            start_body_rates: 0.0,
            motor_thrust: 0.0,
        }
    }
}

/// One episode's draw: the vehicle, its command delay and its start state.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct EpisodeDraw {
    /// Parameters of the simulated vehicle.
    pub plant: QuadrotorParams,
    /// Command delay in whole substeps.
    pub delay_substeps: u32,
    /// Start state.
    pub start: BodyState,
    /// Share of its thrust map each motor delivers (1 unless `motor_thrust` is set).
    pub thrust_factors: Vector4<f64>,
}

/// `U(-r, r)`, or exactly 0 without a draw when `r = 0`.
fn symmetric(rng: &mut impl Rng, r: f64) -> f64 {
    if r > 0.0 { rng.random_range(-r..=r) } else { 0.0 }
}

impl RandomizationParams {
    /// Draws one episode around `nominal` and the track's start pose.
    ///
    /// Factors are drawn in a fixed order (so a seed fixes the episode); a zero range draws
    /// nothing and leaves the nominal value exactly.
    pub fn sample(&self, nominal: &QuadrotorParams, start: &Pose, substep: f64, rng: &mut impl Rng) -> EpisodeDraw {
        let mut scale = |r: f64| 1.0 + symmetric(rng, r);
        let mut plant = *nominal;
        plant.mass *= scale(self.mass);
        for axis in &mut plant.inertia {
            *axis *= scale(self.inertia);
        }
        let drag = scale(self.drag);
        plant.drag = plant.drag.map(|d| d * drag);
        plant.thrust_coefficient *= scale(self.thrust_map);
        let delay = if self.command_delay > 0.0 { rng.random_range(0.0..=self.command_delay) } else { 0.0 };
        let delay_substeps = (delay / substep).round() as u32;

        let position =
            start.position + Vector3::new(symmetric(rng, self.start_xy), symmetric(rng, self.start_xy), symmetric(rng, self.start_z));
        let velocity = Vector3::from_fn(|_, _| symmetric(rng, self.start_velocity));
        let (roll, pitch, yaw) =
            (symmetric(rng, self.start_attitude), symmetric(rng, self.start_attitude), symmetric(rng, self.start_attitude));
        let body_rates = Vector3::from_fn(|_, _| symmetric(rng, self.start_body_rates));
        let attitude = UnitQuaternion::from_euler_angles(0.0, 0.0, start.yaw) * UnitQuaternion::from_euler_angles(roll, pitch, yaw);
        // Drawn last, and only when set, so that every earlier draw stays as it was.
        let thrust_factors =
            Vector4::from_fn(|_, _| if self.motor_thrust > 0.0 { 1.0 - rng.random_range(0.0..=self.motor_thrust) } else { 1.0 });
        let start = BodyState { position, attitude: *attitude.quaternion(), velocity, body_rates };
        EpisodeDraw { plant, delay_substeps, start, thrust_factors }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;

    fn within(x: f64, lo: f64, hi: f64) -> bool {
        x >= lo - 1e-12 && x <= hi + 1e-12
    }

    #[test]
    fn randomised_values_stay_inside_their_ranges_and_cover_them() {
        let r = RandomizationParams::state_based();
        let nominal = QuadrotorParams::default();
        let start = Pose { position: Vector3::new(1.0, 2.0, 3.0), yaw: 0.7 };
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        let mut max_delay = 0;
        let mut mass_span = (f64::INFINITY, f64::NEG_INFINITY);
        for _ in 0..5000 {
            let d = r.sample(&nominal, &start, 0.0025, &mut rng);
            let m = d.plant.mass / nominal.mass;
            mass_span = (mass_span.0.min(m), mass_span.1.max(m));
            assert!(within(m, 0.95, 1.05));
            for i in 0..3 {
                assert!(within(d.plant.inertia[i] / nominal.inertia[i], 0.8, 1.2));
                assert!(within(d.plant.drag[i] / nominal.drag[i], 0.5, 1.5));
                assert!(within(d.start.velocity[i], -0.8, 0.8));
                assert!(within(d.start.body_rates[i], -45f64.to_radians(), 45f64.to_radians()));
            }
            // One drag factor for all three axes.
            assert!((d.plant.drag[0] / nominal.drag[0] - d.plant.drag[2] / nominal.drag[2]).abs() < 1e-12);
            assert!(within(d.plant.thrust_coefficient / nominal.thrust_coefficient, 0.8, 1.2));
            assert!(d.delay_substeps <= 8);
            max_delay = max_delay.max(d.delay_substeps);
            let off = d.start.position - start.position;
            assert!(within(off.x, -0.8, 0.8) && within(off.y, -0.8, 0.8) && within(off.z, -0.6, 0.6));
            // Attitude: the relative rotation to the start yaw has each Euler angle within 20°.
            let rel = UnitQuaternion::from_euler_angles(0.0, 0.0, -start.yaw) * UnitQuaternion::new_unchecked(d.start.attitude);
            let (roll, pitch, yaw) = rel.euler_angles();
            for a in [roll, pitch, yaw] {
                assert!(within(a, -20f64.to_radians(), 20f64.to_radians()), "{a}");
            }
        }
        assert_eq!(max_delay, 8);
        assert!(mass_span.0 < 0.951 && mass_span.1 > 1.049, "covers the range: {mass_span:?}");
    }

    #[test]
    fn evaluation_profile_keeps_nominal_dynamics() {
        let r = RandomizationParams::evaluation();
        let nominal = QuadrotorParams::default();
        let start = Pose { position: Vector3::new(0.0, 0.0, 2.0), yaw: 0.0 };
        let d = r.sample(&nominal, &start, 0.0025, &mut ChaCha8Rng::seed_from_u64(1));
        assert_eq!(d.plant, nominal);
        assert_eq!(d.delay_substeps, 0);
        assert_eq!(d.start.velocity, Vector3::zeros());
        assert_eq!(d.start.body_rates, Vector3::zeros());
        assert!((d.start.position - start.position).norm() > 0.0);
    }

    #[test]
    fn weak_motors_are_drawn_last_and_within_their_range() {
        use rand::SeedableRng;
        let (nominal, start) = (QuadrotorParams::default(), Pose { position: Vector3::new(0.0, 0.0, 2.0), yaw: 0.0 });
        let draw = |p: &RandomizationParams| p.sample(&nominal, &start, 0.0025, &mut rand_chacha::ChaCha8Rng::seed_from_u64(4));
        let plain = draw(&RandomizationParams::state_based());
        assert_eq!(plain.thrust_factors, Vector4::repeat(1.0));
        let weak = draw(&RandomizationParams { motor_thrust: 0.15, ..RandomizationParams::state_based() });
        assert_eq!(
            (weak.plant, weak.start, weak.delay_substeps),
            (plain.plant, plain.start, plain.delay_substeps),
            "earlier draws unchanged"
        );
        assert!(weak.thrust_factors.iter().all(|f| (0.85..=1.0).contains(f)) && weak.thrust_factors != Vector4::repeat(1.0));
    }
}
