//! The 40-dimensional state observation (SPEC §5, §12.9).
//!
//! Observations are written raw (un-normalised) into caller-owned f32 rows; normalisation
//! belongs to the policy, which owns the running statistics.

use crate::quadrotor::BodyState;
use crate::track::Track;

/// Length of the state observation.
pub const STATE_OBS_DIM: usize = 40;

/// Writes `[R_WB col 0, col 1, v, w, a_prev, δp1, δp2]` into `out` (length [`STATE_OBS_DIM`]).
pub fn write_state_observation(
    body: &BodyState,
    previous_action: &[f64; 4],
    track: &Track,
    target: usize,
    out: &mut [f32],
) {
    assert_eq!(out.len(), STATE_OBS_DIM, "state observation row has the wrong length");
    let r = body.rotation();
    let target_corners = track.gates[target].corners();
    let next_corners = track.gates[track.next_index(target)].corners();
    let mut values = [0f64; STATE_OBS_DIM];
    values[0..3].copy_from_slice(r.column(0).as_slice());
    values[3..6].copy_from_slice(r.column(1).as_slice());
    values[6..9].copy_from_slice(body.velocity.as_slice());
    values[9..12].copy_from_slice(body.body_rates.as_slice());
    values[12..16].copy_from_slice(previous_action);
    for c in 0..4 {
        let to_target = target_corners[c] - body.position;
        let between = next_corners[c] - target_corners[c];
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
        let gates = vec![
            Gate::new(Vector3::new(4.0, 0.0, 2.0), 0.0),
            Gate::new(Vector3::new(8.0, 3.0, 3.0), std::f64::consts::FRAC_PI_2),
        ];
        let track = Track::new("t", gates, None, Arena::default()).unwrap();
        let mut body = BodyState::at_rest(Vector3::new(1.0, 0.0, 2.0), std::f64::consts::FRAC_PI_2);
        body.velocity = Vector3::new(0.1, 0.2, 0.3);
        body.body_rates = Vector3::new(-1.0, -2.0, -3.0);
        let mut out = [0f32; STATE_OBS_DIM];
        write_state_observation(&body, &[0.5, 0.6, 0.7, 0.8], &track, 1, &mut out);
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
}
