//! Quadrotor dynamics (SPEC §2, §12.1): body-rate controller → motors → forces → RK4.
//!
//! Two parameter sets meet here: the *controller model* (what the flight controller believes:
//! nominal mass, inertia and thrust map) and the *plant* (the randomised vehicle that actually
//! flies). Keeping them apart is what makes domain randomisation a model mismatch, as on a real
//! drone whose flight controller was tuned for the nominal airframe.

use nalgebra::{Matrix3, Matrix4, Quaternion, UnitQuaternion, Vector3, Vector4};
use serde::{Deserialize, Serialize};

use crate::params::{GRAVITY, QuadrotorParams};

/// Rigid-body part of the state: the quantities RK4 integrates.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct BodyState {
    /// Position of the centre of mass in the world (m).
    pub position: Vector3<f64>,
    /// Attitude: rotates body vectors into the world (unit after every policy step).
    pub attitude: Quaternion<f64>,
    /// Velocity in the world frame (m/s).
    pub velocity: Vector3<f64>,
    /// Angular velocity in the body frame (rad/s).
    pub body_rates: Vector3<f64>,
}

impl BodyState {
    /// At rest at `position` with heading `yaw` (rad).
    pub fn at_rest(position: Vector3<f64>, yaw: f64) -> Self {
        Self {
            position,
            attitude: *UnitQuaternion::from_euler_angles(0.0, 0.0, yaw).quaternion(),
            velocity: Vector3::zeros(),
            body_rates: Vector3::zeros(),
        }
    }

    /// Rotation matrix R_WB of the attitude.
    pub fn rotation(&self) -> Matrix3<f64> {
        UnitQuaternion::new_unchecked(self.attitude).to_rotation_matrix().into_inner()
    }

    /// Heading of the body x axis projected on the ground (rad).
    pub fn yaw(&self) -> f64 {
        let r = self.rotation();
        r[(1, 0)].atan2(r[(0, 0)])
    }

    fn add_scaled(&self, d: &BodyDerivative, h: f64) -> Self {
        Self {
            position: self.position + d.position * h,
            attitude: self.attitude + d.attitude * h,
            velocity: self.velocity + d.velocity * h,
            body_rates: self.body_rates + d.body_rates * h,
        }
    }
}

/// Time derivative of a [`BodyState`].
#[derive(Clone, Copy, Debug)]
struct BodyDerivative {
    position: Vector3<f64>,
    attitude: Quaternion<f64>,
    velocity: Vector3<f64>,
    body_rates: Vector3<f64>,
}

impl BodyDerivative {
    fn rk4_combine(k1: &Self, k2: &Self, k3: &Self, k4: &Self) -> Self {
        let mix = |a: Vector3<f64>, b, c, d| (a + (b + c) * 2.0 + d) / 6.0;
        Self {
            position: mix(k1.position, k2.position, k3.position, k4.position),
            attitude: (k1.attitude + (k2.attitude + k3.attitude) * 2.0 + k4.attitude) / 6.0,
            velocity: mix(k1.velocity, k2.velocity, k3.velocity, k4.velocity),
            body_rates: mix(k1.body_rates, k2.body_rates, k3.body_rates, k4.body_rates),
        }
    }
}

/// Command of the low-level controller: mass-normalised collective thrust and body rates.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Command {
    /// Collective thrust divided by mass (m/s²).
    pub collective_thrust: f64,
    /// Body-rate set-point (rad/s).
    pub body_rates: Vector3<f64>,
}

impl Command {
    /// Maps a normalised action in [-1, 1]⁴ (clipped here) to a command (SPEC §2).
    pub fn from_action(action: &[f64; 4], model: &QuadrotorParams) -> Self {
        let a = action.map(|x| x.clamp(-1.0, 1.0));
        Self {
            collective_thrust: (a[0] + 1.0) / 2.0 * model.collective_thrust_max(),
            body_rates: Vector3::new(a[1] * model.rate_limits[0], a[2] * model.rate_limits[1], a[3] * model.rate_limits[2]),
        }
    }

    /// The command that holds a level hover.
    pub fn hover() -> Self {
        Self { collective_thrust: GRAVITY, body_rates: Vector3::zeros() }
    }

    /// The normalised action that produces this command (inverse of [`Command::from_action`]).
    pub fn to_action(&self, model: &QuadrotorParams) -> [f64; 4] {
        [
            2.0 * self.collective_thrust / model.collective_thrust_max() - 1.0,
            self.body_rates.x / model.rate_limits[0],
            self.body_rates.y / model.rate_limits[1],
            self.body_rates.z / model.rate_limits[2],
        ]
    }
}

/// One simulated quadrotor: state, controller model and plant.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct Quadrotor {
    /// Rigid-body state.
    pub body: BodyState,
    /// Actual motor speeds (rad/s), rotor order fr, bl, br, fl.
    pub motor_speeds: Vector4<f64>,
    model: QuadrotorParams,
    plant: QuadrotorParams,
    model_allocation_inverse: Matrix4<f64>,
    plant_allocation: Matrix4<f64>,
    /// Wind (m/s, world): drag acts on the velocity relative to it. Zero in still air.
    #[serde(default)]
    pub wind: Vector3<f64>,
    /// Share of its thrust map each motor delivers (SPEC §13's thrust loss); 1 when whole.
    #[serde(default = "whole_motors")]
    pub thrust_factors: Vector4<f64>,
}

/// Every motor delivering its whole thrust.
fn whole_motors() -> Vector4<f64> {
    Vector4::repeat(1.0)
}

impl Quadrotor {
    /// A quadrotor whose controller believes `model` and whose physics follow `plant`,
    /// with every motor at the plant's hover speed.
    pub fn new(model: QuadrotorParams, plant: QuadrotorParams, body: BodyState) -> Self {
        Self {
            body,
            motor_speeds: Vector4::repeat(plant.hover_motor_speed()),
            model_allocation_inverse: model.allocation_inverse(),
            plant_allocation: plant.allocation(),
            model,
            plant,
            wind: Vector3::zeros(),
            thrust_factors: whole_motors(),
        }
    }

    /// Parameters the low-level controller believes.
    pub fn model(&self) -> &QuadrotorParams {
        &self.model
    }

    /// Parameters of the simulated vehicle.
    pub fn plant(&self) -> &QuadrotorParams {
        &self.plant
    }

    /// Advances one physics substep of length `h` (SPEC §12.1): controller on the substep's
    /// start state → desired motor speeds → motor lag → forces held through RK4.
    pub fn substep(&mut self, command: &Command, h: f64) {
        let desired = self.desired_motor_speeds(command);
        let lag = 1.0 - (-h / self.plant.motor_time_constant).exp();
        self.motor_speeds += (desired - self.motor_speeds) * lag;
        let thrusts = self.motor_speeds.map(|w| self.plant.motor_thrust(w)).component_mul(&self.thrust_factors);
        let wrench = self.plant_allocation * thrusts;
        let thrust = wrench[0];
        let torque = Vector3::new(wrench[1], wrench[2], wrench[3]);
        self.body = rk4(&self.body, h, |s| self.derivative(s, thrust, &torque));
    }

    /// Re-normalises the attitude quaternion (done once per policy step, SPEC §2).
    pub fn normalize_attitude(&mut self) {
        self.body.attitude = self.body.attitude.normalize();
    }

    /// Low-level controller: `F = m c`, `tau = J K (w_cmd - w) + w × J w`, motor thrusts
    /// `B⁻¹ [F, tau]` clipped, then speeds from the believed thrust map, clipped.
    fn desired_motor_speeds(&self, command: &Command) -> Vector4<f64> {
        let m = &self.model;
        let w = self.body.body_rates;
        let inertia = m.inertia_vec();
        let gains = Vector3::from(m.rate_gains);
        let rate_error = command.body_rates - w;
        let torque = inertia.component_mul(&gains.component_mul(&rate_error)) + w.cross(&inertia.component_mul(&w));
        let wrench = Vector4::new(m.mass * command.collective_thrust, torque.x, torque.y, torque.z);
        let (t_min, t_max) = (m.motor_thrust_min(), m.motor_thrust_max);
        (self.model_allocation_inverse * wrench)
            .map(|t| (t.clamp(t_min, t_max) / m.thrust_coefficient).sqrt().clamp(m.motor_speed_min, m.motor_speed_max))
    }

    /// Rigid-body equations of motion with constant total thrust and torque.
    fn derivative(&self, s: &BodyState, thrust: f64, torque: &Vector3<f64>) -> BodyDerivative {
        let p = &self.plant;
        // The attitude at an RK4 stage is not exactly unit; the unit-quaternion rotation formula
        // is what step-for-step agreement with other implementations (SPEC §12) expects.
        let rot = UnitQuaternion::new_unchecked(s.attitude);
        let v_body = rot.inverse_transform_vector(&(s.velocity - self.wind));
        let drag_body = -Vector3::from(p.drag).component_mul(&v_body);
        let force_body = Vector3::new(0.0, 0.0, thrust) + drag_body;
        let velocity = rot.transform_vector(&force_body) / p.mass - Vector3::new(0.0, 0.0, GRAVITY);
        let inertia = p.inertia_vec();
        let w = s.body_rates;
        let body_rates = (torque - w.cross(&inertia.component_mul(&w))).component_div(&inertia);
        BodyDerivative { position: s.velocity, attitude: s.attitude * Quaternion::from_imag(w) * 0.5, velocity, body_rates }
    }
}

/// Classic fourth-order Runge–Kutta step of length `h`.
fn rk4(s: &BodyState, h: f64, f: impl Fn(&BodyState) -> BodyDerivative) -> BodyState {
    let k1 = f(s);
    let k2 = f(&s.add_scaled(&k1, h / 2.0));
    let k3 = f(&s.add_scaled(&k2, h / 2.0));
    let k4 = f(&s.add_scaled(&k3, h));
    s.add_scaled(&BodyDerivative::rk4_combine(&k1, &k2, &k3, &k4), h)
}

#[cfg(test)]
mod tests {
    use super::*;

    const H: f64 = 0.0025;

    fn nominal_at(z: f64) -> Quadrotor {
        let p = QuadrotorParams::default();
        Quadrotor::new(p, p, BodyState::at_rest(Vector3::new(0.0, 0.0, z), 0.0))
    }

    fn fly(quad: &mut Quadrotor, command: &Command, seconds: f64) {
        let steps = (seconds / H).round() as usize;
        for i in 0..steps {
            quad.substep(command, H);
            if i % 8 == 7 {
                quad.normalize_attitude();
            }
        }
    }

    #[test]
    fn hover_holds_altitude_for_five_seconds() {
        let mut quad = nominal_at(2.0);
        let action = Command::hover().to_action(quad.model());
        // Through the normalised action path, rounded to f32 as a policy would send it.
        let command = Command::from_action(&action.map(|a| f64::from(a as f32)), quad.model());
        fly(&mut quad, &command, 5.0);
        assert!((quad.body.position.z - 2.0).abs() < 0.01, "z = {}", quad.body.position.z);
        assert!(quad.body.position.xy().norm() < 1e-6);
    }

    #[test]
    fn zero_thrust_without_drag_falls_with_gravity_less_idle_thrust() {
        let p = QuadrotorParams { drag: [0.0; 3], ..QuadrotorParams::default() };
        let mut quad = Quadrotor::new(p, p, BodyState::at_rest(Vector3::new(0.0, 0.0, 10.0), 0.3));
        quad.motor_speeds = Vector4::repeat(p.motor_speed_min);
        let command = Command::from_action(&[-1.0, 0.0, 0.0, 0.0], &p);
        let t = 1.0;
        fly(&mut quad, &command, t);
        let idle = 4.0 * p.motor_thrust_min() / p.mass;
        let expected = 10.0 - (GRAVITY - idle) * t * t / 2.0;
        assert!((quad.body.position.z - expected).abs() < 1e-9, "{} vs {expected}", quad.body.position.z);
    }

    #[test]
    fn zero_thrust_falls_as_free_fall_within_drag_and_motor_spin_down() {
        let mut quad = nominal_at(10.0);
        let p = *quad.model();
        let command = Command::from_action(&[-1.0, 0.0, 0.0, 0.0], &p);
        let t = 1.0;
        fly(&mut quad, &command, t);
        let free_fall = 10.0 - GRAVITY * t * t / 2.0;
        let z = quad.body.position.z;
        // Drag and the motors spinning down from hover only slow the fall; bound them: drag
        // acceleration ≤ c_z g t / m, spin-down adds at most g·tau of upward velocity.
        let drag_bound = p.drag[2] * GRAVITY * t / p.mass * t * t / 2.0;
        let spin_down_bound = GRAVITY * p.motor_time_constant * t;
        let idle = 4.0 * p.motor_thrust_min() / p.mass * t * t / 2.0;
        assert!(z > free_fall, "falls slower than free fall: {z} vs {free_fall}");
        assert!(z - free_fall < drag_bound + spin_down_bound + idle, "{z} vs {free_fall}");
    }

    /// Time for the roll or pitch rate to first reach 90 % of a step command.
    fn rise_time_90(axis: usize) -> f64 {
        let mut quad = nominal_at(3.0);
        let mut rates = Vector3::zeros();
        rates[axis] = 2.0;
        let command = Command { collective_thrust: GRAVITY, body_rates: rates };
        for i in 1..=400 {
            quad.substep(&command, H);
            if quad.body.body_rates[axis] >= 0.9 * 2.0 {
                return i as f64 * H;
            }
        }
        f64::INFINITY
    }

    #[test]
    fn roll_and_pitch_rate_steps_reach_ninety_percent_within_a_tenth_of_a_second() {
        for axis in [0, 1] {
            let t = rise_time_90(axis);
            assert!(t <= 0.1, "axis {axis}: 90 % after {t} s");
        }
    }

    #[test]
    fn positive_yaw_rate_turns_the_nose_to_the_left() {
        let mut quad = nominal_at(3.0);
        let command = Command { collective_thrust: GRAVITY, body_rates: Vector3::new(0.0, 0.0, 1.0) };
        fly(&mut quad, &command, 0.5);
        assert!(quad.body.body_rates.z > 0.5);
        assert!(quad.body.yaw() > 0.1, "yaw {}", quad.body.yaw());
    }

    #[test]
    fn quaternion_stays_unit_through_aggressive_manoeuvres() {
        let mut quad = nominal_at(50.0);
        let command = Command { collective_thrust: 20.0, body_rates: Vector3::new(8.0, -6.0, 3.0) };
        for _ in 0..250 {
            for _ in 0..8 {
                quad.substep(&command, H);
            }
            // Even before the per-step normalisation, RK4 keeps the norm to high accuracy.
            assert!((quad.body.attitude.norm() - 1.0).abs() < 1e-6);
            quad.normalize_attitude();
            assert!((quad.body.attitude.norm() - 1.0).abs() < 1e-12);
        }
    }

    #[test]
    fn action_command_round_trip() {
        let p = QuadrotorParams::default();
        let a = [0.3, -0.5, 0.25, 1.0];
        let back = Command::from_action(&a, &p).to_action(&p);
        for i in 0..4 {
            assert!((a[i] - back[i]).abs() < 1e-12);
        }
        // Out-of-range actions are clipped before use.
        let c = Command::from_action(&[2.0, -3.0, 0.0, 0.0], &p);
        assert_eq!(c.collective_thrust, p.collective_thrust_max());
        assert_eq!(c.body_rates.x, -p.rate_limits[0]);
    }
}
