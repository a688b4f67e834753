//! Physical and timing parameters; every `Default` equals SPEC §1–§2.

use nalgebra::{Matrix4, Vector3, Vector4};
use serde::{Deserialize, Serialize};

/// Gravitational acceleration (m/s²), acting along world -z.
pub const GRAVITY: f64 = 9.8066;

/// Quadrotor model: rigid body, rotors, motors, drag and the low-level body-rate controller.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct QuadrotorParams {
    /// Mass (kg). Default 0.752.
    pub mass: f64,
    /// Diagonal of the inertia tensor (kg m²). Default [0.0025, 0.0021, 0.0043].
    pub inertia: [f64; 3],
    /// Rotor positions (x, y) in the body frame (m), in rotor order fr, bl, br, fl.
    pub rotor_positions: [[f64; 2]; 4],
    /// Rotor yaw torque per unit thrust, kappa (m). Default 0.022.
    pub yaw_torque_per_thrust: f64,
    /// Sign of each rotor's yaw torque, rotor order fr, bl, br, fl. Default [-1, -1, 1, 1].
    pub spin_signs: [f64; 4],
    /// Thrust map coefficient: thrust = k w² (N s²/rad²). Default 1.562522e-6.
    pub thrust_coefficient: f64,
    /// Lowest motor speed (rad/s). Default 150.
    pub motor_speed_min: f64,
    /// Highest motor speed (rad/s). Default 2333.
    pub motor_speed_max: f64,
    /// Largest commanded thrust of one motor (N). Default 8.5.
    pub motor_thrust_max: f64,
    /// Motor first-order lag time constant (s). Default 0.033.
    pub motor_time_constant: f64,
    /// Linear drag coefficients in the body frame (N s/m). Default [0.26, 0.28, 0.42].
    pub drag: [f64; 3],
    /// Body-rate command limits for roll, pitch, yaw (rad/s). Default [10, 10, 4].
    pub rate_limits: [f64; 3],
    /// Proportional gains K of the body-rate controller (1/s). Default [20, 20, 40].
    pub rate_gains: [f64; 3],
    /// Radius of the collision sphere at the centre of mass (m). Default 0.15.
    pub collision_radius: f64,
}

impl Default for QuadrotorParams {
    fn default() -> Self {
        Self {
            mass: 0.752,
            inertia: [0.0025, 0.0021, 0.0043],
            rotor_positions: [[0.075, -0.10], [-0.075, 0.10], [-0.075, -0.10], [0.075, 0.10]],
            yaw_torque_per_thrust: 0.022,
            spin_signs: [-1.0, -1.0, 1.0, 1.0],
            thrust_coefficient: 1.562522e-6,
            motor_speed_min: 150.0,
            motor_speed_max: 2333.0,
            motor_thrust_max: 8.5,
            motor_time_constant: 0.033,
            drag: [0.26, 0.28, 0.42],
            rate_limits: [10.0, 10.0, 4.0],
            rate_gains: [20.0, 20.0, 40.0],
            collision_radius: 0.15,
        }
    }
}

impl QuadrotorParams {
    /// Allocation matrix B: `[F, tau_x, tau_y, tau_z] = B * [T_fr, T_bl, T_br, T_fl]`.
    pub fn allocation(&self) -> Matrix4<f64> {
        let mut b = Matrix4::zeros();
        for (i, [x, y]) in self.rotor_positions.iter().enumerate() {
            // Thrust along +z at (x, y, 0): torque r × F = (y T, -x T, 0).
            b[(0, i)] = 1.0;
            b[(1, i)] = *y;
            b[(2, i)] = -*x;
            b[(3, i)] = self.yaw_torque_per_thrust * self.spin_signs[i];
        }
        b
    }

    /// Inverse of the allocation matrix; panics only for a degenerate rotor layout.
    #[allow(clippy::expect_used, reason = "rotor layout gives a singular allocation matrix")]
    pub fn allocation_inverse(&self) -> Matrix4<f64> {
        self.allocation().try_inverse().expect("rotor layout gives a singular allocation matrix")
    }

    /// Thrust of one motor at the given speed (N).
    pub fn motor_thrust(&self, speed: f64) -> f64 {
        self.thrust_coefficient * speed * speed
    }

    /// Smallest commanded motor thrust: the thrust at the lowest motor speed (N).
    pub fn motor_thrust_min(&self) -> f64 {
        self.motor_thrust(self.motor_speed_min)
    }

    /// Motor speed that makes every motor carry a quarter of the weight (rad/s).
    pub fn hover_motor_speed(&self) -> f64 {
        (self.mass * GRAVITY / 4.0 / self.thrust_coefficient).sqrt()
    }

    /// Largest mass-normalised collective thrust the action can ask for, `4 T_max / m` (m/s²).
    pub fn collective_thrust_max(&self) -> f64 {
        4.0 * self.motor_thrust_max / self.mass
    }

    /// Inertia as a vector.
    pub fn inertia_vec(&self) -> Vector3<f64> {
        Vector3::from(self.inertia)
    }

    /// Per-motor yaw-torque signs as a vector.
    pub fn spin_vec(&self) -> Vector4<f64> {
        Vector4::from(self.spin_signs)
    }
}

/// Timing of the race environment (SPEC §1, §4).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct RaceParams {
    /// Policy step (s). Default 0.02 (50 Hz).
    pub dt: f64,
    /// RK4 substeps per policy step. Default 8 (2.5 ms each).
    pub substeps: u32,
    /// Steps after which an episode is truncated. Default 1500 (training); evaluation uses 1000.
    pub max_episode_steps: u32,
}

impl Default for RaceParams {
    fn default() -> Self {
        Self { dt: 0.02, substeps: 8, max_episode_steps: 1500 }
    }
}

impl RaceParams {
    /// Length of one physics substep (s).
    pub fn substep(&self) -> f64 {
        self.dt / f64::from(self.substeps)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn allocation_of_hover_thrusts_gives_weight_and_no_torque() {
        let p = QuadrotorParams::default();
        let t = p.mass * GRAVITY / 4.0;
        let wrench = p.allocation() * Vector4::repeat(t);
        assert!((wrench[0] - p.mass * GRAVITY).abs() < 1e-12);
        assert!(wrench.rows(1, 3).norm() < 1e-12);
        let back = p.allocation_inverse() * wrench;
        assert!((back - Vector4::repeat(t)).norm() < 1e-12);
    }

    #[test]
    fn thrust_clip_acts_before_speed_clip() {
        // SPEC §12.12: the speed limit gives 8.5047 N, so 8.5 N is the binding limit.
        let p = QuadrotorParams::default();
        assert!(p.motor_thrust(p.motor_speed_max) > p.motor_thrust_max);
        assert!((p.motor_thrust(p.motor_speed_max) - 8.5047).abs() < 1e-3);
    }
}
