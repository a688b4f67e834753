//! The 40-dimensional state observation (SPEC §5, §12.9), in a choice of reference frames.
//!
//! Observations are written raw (un-normalised) into caller-owned f32 rows; normalisation
//! belongs to the policy, which owns the running statistics.

use nalgebra::{Matrix3, Rotation3, Vector3};
use serde::{Deserialize, Serialize};

use crate::quadrotor::BodyState;
use crate::track::Track;

/// Length of the state observation.
pub const STATE_OBS_DIM: usize = 40;

/// The frame in which the observation's vectors (attitude columns, v, δp1, δp2) are written.
///
/// SPEC §5 writes them in the world frame (the thesis does not say which). A generalist flies
/// tracks in every orientation, so in the world frame the same manoeuvre looks different on a
/// track rotated about z; the other two frames remove that symmetry from what it must learn.
/// Body rates and the previous action are body quantities in every frame.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ObservationFrame {
    /// World frame, as SPEC §5 states it.
    #[default]
    World,
    /// Yaw-aligned: rotated about world z by the drone's heading, so z stays up and the body x
    /// axis projects onto +x. Attitude columns are those of `R_z(-ψ) R_WB` (roll and pitch).
    Heading,
    /// Body frame: v, δp1 and δp2 in body axes; attitude columns as in `Heading` (gravity's
    /// direction is what the body frame needs from the attitude).
    Body,
}

impl ObservationFrame {
    /// The frame's name as run configs spell it: `world`, `heading` or `body`.
    pub fn name(self) -> &'static str {
        match self {
            ObservationFrame::World => "world",
            ObservationFrame::Heading => "heading",
            ObservationFrame::Body => "body",
        }
    }

    /// The rotation that takes world vectors into this frame for a drone with attitude `body`.
    fn rotation_from_world(self, body: &BodyState) -> Matrix3<f64> {
        match self {
            ObservationFrame::World => Matrix3::identity(),
            ObservationFrame::Heading => heading_from_world(body),
            ObservationFrame::Body => body.rotation().transpose(),
        }
    }
}

/// `R_z(-ψ)`: world vectors into the yaw-aligned frame of the drone's heading ψ.
fn heading_from_world(body: &BodyState) -> Matrix3<f64> {
    Rotation3::from_axis_angle(&Vector3::z_axis(), -body.yaw()).into_inner()
}

/// Writes `[R col 0, col 1, v, w, a_prev, δp1, δp2]` into `out` (length [`STATE_OBS_DIM`]),
/// with R, v and the δp vectors in `frame`.
pub fn write_state_observation(
    body: &BodyState,
    previous_action: &[f64; 4],
    track: &Track,
    target: usize,
    frame: ObservationFrame,
    out: &mut [f32],
) {
    assert_eq!(out.len(), STATE_OBS_DIM, "state observation row has the wrong length");
    let to_frame = frame.rotation_from_world(body);
    let attitude = match frame {
        ObservationFrame::World => body.rotation(),
        ObservationFrame::Heading | ObservationFrame::Body => heading_from_world(body) * body.rotation(),
    };
    let target_corners = track.gates[target].corners();
    let next_corners = track.gates[track.next_index(target)].corners();
    let mut values = [0f64; STATE_OBS_DIM];
    values[0..3].copy_from_slice(attitude.column(0).as_slice());
    values[3..6].copy_from_slice(attitude.column(1).as_slice());
    values[6..9].copy_from_slice((to_frame * body.velocity).as_slice());
    values[9..12].copy_from_slice(body.body_rates.as_slice());
    values[12..16].copy_from_slice(previous_action);
    for c in 0..4 {
        let to_target = to_frame * (target_corners[c] - body.position);
        let between = to_frame * (next_corners[c] - target_corners[c]);
        values[16 + 3 * c..19 + 3 * c].copy_from_slice(to_target.as_slice());
        values[28 + 3 * c..31 + 3 * c].copy_from_slice(between.as_slice());
    }
    for (o, v) in out.iter_mut().zip(values) {
        *o = v as f32;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::track::{Arena, Gate};
    use nalgebra::Vector3;

    #[test]
    fn layout_follows_the_spec_order() {
        let gates = vec![Gate::new(Vector3::new(4.0, 0.0, 2.0), 0.0), Gate::new(Vector3::new(8.0, 3.0, 3.0), std::f64::consts::FRAC_PI_2)];
        let track = Track::new("t", gates, None, Arena::default()).unwrap();
        let mut body = BodyState::at_rest(Vector3::new(1.0, 0.0, 2.0), std::f64::consts::FRAC_PI_2);
        body.velocity = Vector3::new(0.1, 0.2, 0.3);
        body.body_rates = Vector3::new(-1.0, -2.0, -3.0);
        let mut out = [0f32; STATE_OBS_DIM];
        write_state_observation(&body, &[0.5, 0.6, 0.7, 0.8], &track, 1, ObservationFrame::World, &mut out);
        // Yaw 90°: body x points to world +y, body y to world -x.
        let expect_prefix = [0.0, 1.0, 0.0, -1.0, 0.0, 0.0, 0.1, 0.2, 0.3, -1.0, -2.0, -3.0, 0.5, 0.6, 0.7, 0.8];
        for (i, e) in expect_prefix.iter().enumerate() {
            assert!((f64::from(out[i]) - e).abs() < 1e-6, "index {i}: {} vs {e}", out[i]);
        }
        // Target gate 1 (yaw 90°): corner 0 is local (y, z) = (+0.75, +0.75) → world (-0.75, 0, +0.75).
        let c0 = Vector3::new(8.0 - 0.75, 3.0, 3.75) - body.position;
        for k in 0..3 {
            assert!((f64::from(out[16 + k]) - c0[k]).abs() < 1e-6);
        }
        // The gate after the last is gate 0: δp2 corner 0 = gate 0 corner 0 − gate 1 corner 0.
        let g0c0 = Vector3::new(4.0, 0.75, 2.75);
        let d = g0c0 - Vector3::new(8.0 - 0.75, 3.0, 3.75);
        for k in 0..3 {
            assert!((f64::from(out[28 + k]) - d[k]).abs() < 1e-6);
        }
    }

    /// The same scene rotated about world z by any angle gives the same heading- and
    /// body-frame observation; the world-frame one changes.
    #[test]
    fn heading_and_body_frames_are_invariant_to_rotating_the_whole_scene_about_z() {
        let rotate = |angle: f64, v: Vector3<f64>| Rotation3::from_axis_angle(&Vector3::z_axis(), angle) * v;
        let observe = |angle: f64, frame: ObservationFrame| {
            let gates = vec![
                Gate::new(rotate(angle, Vector3::new(4.0, 1.0, 2.0)), 0.3 + angle),
                Gate::new(rotate(angle, Vector3::new(8.0, 5.0, 3.0)), 1.2 + angle),
            ];
            let arena = Arena { min: Vector3::new(-20.0, -20.0, 0.0), max: Vector3::new(20.0, 20.0, 6.0) };
            let track = Track::new("t", gates, None, arena).unwrap();
            let tilt = nalgebra::UnitQuaternion::from_euler_angles(0.2, -0.1, 0.7 + angle);
            let body = BodyState {
                position: rotate(angle, Vector3::new(1.0, -1.0, 2.0)),
                attitude: *tilt.quaternion(),
                velocity: rotate(angle, Vector3::new(2.0, 0.5, -0.3)),
                body_rates: Vector3::new(0.1, 0.2, 0.3),
            };
            let mut out = [0f32; STATE_OBS_DIM];
            write_state_observation(&body, &[0.1, 0.2, 0.3, 0.4], &track, 0, frame, &mut out);
            out
        };
        for frame in [ObservationFrame::Heading, ObservationFrame::Body] {
            let (a, b) = (observe(0.0, frame), observe(2.1, frame));
            for i in 0..STATE_OBS_DIM {
                assert!((a[i] - b[i]).abs() < 1e-5, "{frame:?} index {i}: {} vs {}", a[i], b[i]);
            }
        }
        let (a, b) = (observe(0.0, ObservationFrame::World), observe(2.1, ObservationFrame::World));
        assert!((a[6] - b[6]).abs() > 0.1, "world-frame velocity turns with the scene");
    }

    #[test]
    fn body_frame_puts_a_gate_ahead_of_a_level_drone_on_body_x() {
        let gates = vec![Gate::new(Vector3::new(0.0, 5.0, 2.0), std::f64::consts::FRAC_PI_2), Gate::new(Vector3::new(5.0, 5.0, 2.0), 0.0)];
        let track = Track::new("t", gates, None, Arena::default()).unwrap();
        // Facing +y (yaw 90°), 5 m before gate 0: its centre is 5 m along body x.
        let body = BodyState::at_rest(Vector3::new(0.0, 0.0, 2.0), std::f64::consts::FRAC_PI_2);
        let mut out = [0f32; STATE_OBS_DIM];
        write_state_observation(&body, &[0.0; 4], &track, 0, ObservationFrame::Body, &mut out);
        let centre: Vec<f32> = (0..3).map(|k| (0..4).map(|c| out[16 + 3 * c + k]).sum::<f32>() / 4.0).collect();
        assert!((centre[0] - 5.0).abs() < 1e-5 && centre[1].abs() < 1e-5 && centre[2].abs() < 1e-5, "{centre:?}");
        // Level and heading-aligned: attitude columns are the identity's.
        assert!((out[0] - 1.0).abs() < 1e-6 && (out[4] - 1.0).abs() < 1e-6);
    }
}
