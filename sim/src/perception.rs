//! A camera's misjudgement of the gates, put into a state observation: trains a state-based
//! teacher whose vision student will see the gates less exactly than the teacher's observation
//! shows them (beyond SPEC; [`crate::RandomizationParams::gate_perception`]).
//!
//! A perception error is not jitter: a student misjudges the same gate in the same way over
//! consecutive frames. So each corner's error is a standard normal 3-vector that drifts (AR(1)
//! with [`GatePerception::RHO`] a step, about 0.2 s of memory at 50 Hz), scaled by the corner's
//! distance, since a pixel covers more metres further away.

use rand::Rng;
use rand_distr::StandardNormal;
use serde::{Deserialize, Serialize};

use crate::observation::{NEXT_CORNERS_RANGE, STATE_OBS_DIM, TARGET_CORNERS_RANGE};

/// The drifting error of the 8 corners an observation can show.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct GatePerception {
    /// A standard normal 3-vector per corner: the target gate's 4, then the next gate's 4.
    drift: [[f64; 3]; 8],
}

impl GatePerception {
    /// Step-to-step correlation of the error.
    pub const RHO: f64 = 0.9;

    /// A fresh error for a new episode.
    pub fn restart(&mut self, rng: &mut impl Rng) {
        self.drift.iter_mut().flatten().for_each(|d| *d = rng.sample(StandardNormal));
    }

    /// One step of drift; the error stays standard normal in distribution.
    pub fn advance(&mut self, rng: &mut impl Rng) {
        let innovation = (1.0 - Self::RHO * Self::RHO).sqrt();
        for d in self.drift.iter_mut().flatten() {
            let e: f64 = rng.sample(StandardNormal);
            *d = Self::RHO * *d + innovation * e;
        }
    }

    /// Moves every corner `observation` shows (those out of view are all zeros and stay so) by
    /// `hypot(sigma × its distance, floor)` × its drift. The next gate's corners are relative
    /// to the target's, so their distance is that of their sum.
    pub fn apply(&self, sigma: f64, floor: f64, observation: &mut [f32]) {
        assert!(observation.len() >= STATE_OBS_DIM, "a state observation");
        let corner = |o: &[f32], start: usize| -> [f64; 3] { std::array::from_fn(|k| f64::from(o[start + k])) };
        for c in 0..4 {
            let (target, next) = (TARGET_CORNERS_RANGE.start + 3 * c, NEXT_CORNERS_RANGE.start + 3 * c);
            let (to_target, between) = (corner(observation, target), corner(observation, next));
            let seen = |v: &[f64; 3]| v.iter().any(|x| *x != 0.0);
            let norm = |v: [f64; 3]| v.iter().map(|x| x * x).sum::<f64>().sqrt();
            if seen(&between) {
                let d = norm(std::array::from_fn(|k| to_target[k] + between[k]));
                for k in 0..3 {
                    observation[next + k] += ((sigma * d).hypot(floor) * self.drift[4 + c][k]) as f32;
                }
            }
            if seen(&to_target) {
                let d = norm(to_target);
                for k in 0..3 {
                    observation[target + k] += ((sigma * d).hypot(floor) * self.drift[c][k]) as f32;
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;

    #[test]
    fn the_error_scales_with_distance_spares_unseen_gates_and_drifts_slowly() {
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        let mut p = GatePerception::default();
        p.restart(&mut rng);
        let mut observation = [0f32; STATE_OBS_DIM];
        // Target corners 2 m and 8 m away along x; the next gate out of view.
        for c in 0..4 {
            observation[TARGET_CORNERS_RANGE.start + 3 * c] = if c < 2 { 2.0 } else { 8.0 };
        }
        let mut seen = observation;
        p.apply(0.05, 0.0, &mut seen);
        assert!(seen[NEXT_CORNERS_RANGE].iter().all(|v| *v == 0.0), "an unseen gate stays unseen");
        assert!(seen[..TARGET_CORNERS_RANGE.start] == observation[..TARGET_CORNERS_RANGE.start], "only the gates move");
        for c in 0..4 {
            let d = if c < 2 { 2.0 } else { 8.0 };
            for k in 0..3 {
                let moved = f64::from(seen[TARGET_CORNERS_RANGE.start + 3 * c + k] - observation[TARGET_CORNERS_RANGE.start + 3 * c + k]);
                assert!((moved - 0.05 * d * p.drift[c][k]).abs() < 1e-5, "corner {c}: {moved}");
            }
        }
        // A floor of 0.3 m dominates near (2 m: hypot(0.1, 0.3)) and fades far (8 m: hypot(0.4, 0.3)).
        let mut floored = observation;
        p.apply(0.05, 0.3, &mut floored);
        for c in 0..4 {
            let scale = if c < 2 { 0.1f64.hypot(0.3) } else { 0.4f64.hypot(0.3) };
            for k in 0..3 {
                let moved =
                    f64::from(floored[TARGET_CORNERS_RANGE.start + 3 * c + k] - observation[TARGET_CORNERS_RANGE.start + 3 * c + k]);
                assert!((moved - scale * p.drift[c][k]).abs() < 1e-5, "corner {c} with a floor: {moved}");
            }
        }
        assert!(floored[NEXT_CORNERS_RANGE].iter().all(|v| *v == 0.0), "an unseen gate stays unseen under a floor too");
        // Over many steps the drift keeps unit variance and a lag-1 correlation of ρ.
        let (mut sum_sq, mut lagged, mut n) = (0.0, 0.0, 0.0);
        for _ in 0..20_000 {
            let before = p.drift;
            p.advance(&mut rng);
            for (b, a) in before.iter().flatten().zip(p.drift.iter().flatten()) {
                sum_sq += a * a;
                lagged += a * b;
                n += 1.0;
            }
        }
        let (variance, correlation) = (sum_sq / n, lagged / sum_sq);
        assert!((variance - 1.0).abs() < 0.05, "variance {variance}");
        assert!((correlation - GatePerception::RHO).abs() < 0.02, "lag-1 correlation {correlation}");
    }
}
