//! Per-step reward (SPEC §5, §12.4–§12.5, §12.10; thesis Table 2.1).

use serde::{Deserialize, Serialize};

use nalgebra::Vector3;

use crate::track::{GATE_HALF_OPENING, Gate};

/// How far behind a gate's centre the [`ProgressDistance::Approach`] detour point lies (m):
/// room to turn round into the gate after flying past or through it the wrong way.
pub const APPROACH_DEPTH: f64 = 1.5;

/// Which formulas the progress and pass terms use.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum RewardVariant {
    /// State-based: `λ_prog Δd` and `λ_pass (1 - e/w_g)`.
    StateBased,
    /// Vision-based: progress weighted by camera–gate alignment, `λ_pass + λ_error e`.
    VisionBased,
}

/// The distance to the target gate that progress `d_{t-1} - d_t` is measured by.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ProgressDistance {
    /// Straight to the gate centre (SPEC §5).
    #[default]
    Centre,
    /// Straight to the centre from behind the gate plane; from in front of it (the side a
    /// pass leaves by), by way of a point [`APPROACH_DEPTH`] behind the centre. With
    /// `centre`, a gate that must be flown round (the next gate faces the drone, 18 % of the
    /// test set's gates) pays the detour as negative progress; here the detour is progress.
    /// Beyond the thesis.
    Approach,
}

impl ProgressDistance {
    /// The distance from `p` to `gate` under this measure (m).
    pub fn to_gate(self, gate: &Gate, p: &Vector3<f64>) -> f64 {
        let offset = p - gate.position;
        let normal = gate.normal();
        match self {
            ProgressDistance::Approach if offset.dot(&normal) >= 0.0 => (offset + normal * APPROACH_DEPTH).norm() + APPROACH_DEPTH,
            _ => offset.norm(),
        }
    }
}

/// Reward weights; `Default` is the state-based column of SPEC §5.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct RewardParams {
    /// Formula family of the progress and pass terms.
    pub variant: RewardVariant,
    /// λ_prog, per metre of progress towards the target gate centre.
    pub progress: f64,
    /// The distance progress is measured by: `centre` in both of SPEC §5's columns; training's
    /// state-based default (`EnvConfig::default`) is `approach`.
    pub progress_distance: ProgressDistance,
    /// λ_pass, on passing the target gate.
    pub pass: f64,
    /// λ_error, per metre of traversal error (vision-based only).
    pub pass_error: f64,
    /// λ_crash, once on a crash.
    pub crash: f64,
    /// λ_rate, times ‖w_xy / w_xy_max‖².
    pub rate: f64,
    /// λ_diff for the thrust command.
    pub command_thrust: f64,
    /// λ_diff for each of the roll and pitch rate commands.
    pub command_xy: f64,
    /// λ_diff for the yaw rate command.
    pub command_z: f64,
    /// λ_linear, weight of |Δa| next to Δa².
    pub command_linear: f64,
    /// Cut-off of the action low-pass filter (Hz).
    pub command_filter_hz: f64,
}

impl Default for RewardParams {
    fn default() -> Self {
        Self::state_based()
    }
}

impl RewardParams {
    /// State-based (SB) weights.
    pub fn state_based() -> Self {
        Self {
            variant: RewardVariant::StateBased,
            progress: 1.0,
            progress_distance: ProgressDistance::Centre,
            pass: 1.0,
            pass_error: 0.0,
            crash: -4.0,
            rate: -0.001,
            command_thrust: -0.0001,
            command_xy: -0.0002,
            command_z: -0.0002,
            command_linear: 0.01,
            command_filter_hz: 6.0,
        }
    }

    /// Vision-based (VB) weights.
    pub fn vision_based() -> Self {
        Self {
            variant: RewardVariant::VisionBased,
            progress: 0.8,
            progress_distance: ProgressDistance::Centre,
            pass: 4.0,
            pass_error: -1.0,
            crash: -4.0,
            rate: -0.01,
            command_thrust: -0.05,
            command_xy: -0.01,
            command_z: -0.01,
            command_linear: 0.01,
            command_filter_hz: 6.0,
        }
    }

    /// Low-pass coefficient α = dt / (dt + 1/(2π f_c)).
    pub fn filter_alpha(&self, dt: f64) -> f64 {
        dt / (dt + 1.0 / (2.0 * std::f64::consts::PI * self.command_filter_hz))
    }
}

/// First-order low-pass of the action, ã (SPEC §12.5); starts at 0.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct ActionFilter {
    filtered: [f64; 4],
}

impl ActionFilter {
    /// Updates ã with `action` and returns Δa = a − ã (after the update).
    pub fn update(&mut self, action: &[f64; 4], alpha: f64) -> [f64; 4] {
        std::array::from_fn(|i| {
            self.filtered[i] += alpha * (action[i] - self.filtered[i]);
            action[i] - self.filtered[i]
        })
    }
}

/// What happened in one step, as far as the reward needs to know.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct StepFacts {
    /// Distance to the step's target gate at the start of the step (m; [`ProgressDistance`]).
    pub distance_before: f64,
    /// Distance to the same gate at the end of the step (m; to its centre when the step passed it).
    pub distance_after: f64,
    /// Traversal error e_t when the target gate was passed (m).
    pub pass_error: Option<f64>,
    /// Whether the step ended in a crash.
    pub crashed: bool,
    /// Roll and pitch rates at the end of the step (rad/s).
    pub body_rates_xy: [f64; 2],
    /// Roll and pitch rate limits (rad/s).
    pub rate_limits_xy: [f64; 2],
    /// Δa of the command filter.
    pub action_change: [f64; 4],
    /// ρ_t = max(0, camera axis · gate normal); only the vision-based progress uses it.
    pub view_alignment: f64,
}

/// The five reward terms of one step.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct RewardTerms {
    /// r_prog.
    pub progress: f64,
    /// r_pass.
    pub pass: f64,
    /// r_crash.
    pub crash: f64,
    /// r_rate.
    pub rate: f64,
    /// r_cmd.
    pub command: f64,
}

impl RewardTerms {
    /// The step reward r = r_prog + r_pass + r_crash + r_rate + r_cmd.
    pub fn total(&self) -> f64 {
        self.progress + self.pass + self.crash + self.rate + self.command
    }
}

impl RewardParams {
    /// Evaluates every term for one step.
    pub fn terms(&self, f: &StepFacts) -> RewardTerms {
        let delta = f.distance_before - f.distance_after;
        let progress = match self.variant {
            RewardVariant::StateBased => self.progress * delta,
            RewardVariant::VisionBased => self.progress * (delta.max(0.0) * f.view_alignment + delta.min(0.0)),
        };
        // Not clamped: a pass near a corner may earn less than nothing (SPEC §12.10).
        let pass = f.pass_error.map_or(0.0, |e| match self.variant {
            RewardVariant::StateBased => self.pass * (1.0 - e / GATE_HALF_OPENING),
            RewardVariant::VisionBased => self.pass + self.pass_error * e,
        });
        let crash = if f.crashed { self.crash } else { 0.0 };
        let [wx, wy] = f.body_rates_xy;
        let [lx, ly] = f.rate_limits_xy;
        let rate = self.rate * ((wx / lx).powi(2) + (wy / ly).powi(2));
        let weights = [self.command_thrust, self.command_xy, self.command_xy, self.command_z];
        let command = weights.iter().zip(f.action_change).map(|(w, d)| w * (self.command_linear * d.abs() + d * d)).sum();
        RewardTerms { progress, pass, crash, rate, command }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn facts() -> StepFacts {
        StepFacts {
            distance_before: 5.0,
            distance_after: 4.8,
            pass_error: None,
            crashed: false,
            body_rates_xy: [0.0, 0.0],
            rate_limits_xy: [10.0, 10.0],
            action_change: [0.0; 4],
            view_alignment: 1.0,
        }
    }

    fn close(a: f64, b: f64) -> bool {
        (a - b).abs() < 1e-12
    }

    #[test]
    fn state_based_terms_match_hand_computed_values() {
        let p = RewardParams::state_based();
        let t = p.terms(&facts());
        assert!(close(t.progress, 0.2));
        assert_eq!((t.pass, t.crash, t.rate, t.command), (0.0, 0.0, 0.0, 0.0));

        let t = p.terms(&StepFacts { pass_error: Some(0.3), ..facts() });
        assert!(close(t.pass, 1.0 - 0.3 / 0.75));
        // Not clamped near a corner: e = 1.0 > w_g.
        let t = p.terms(&StepFacts { pass_error: Some(1.0), ..facts() });
        assert!(close(t.pass, 1.0 - 1.0 / 0.75));

        let t = p.terms(&StepFacts { crashed: true, ..facts() });
        assert_eq!(t.crash, -4.0);

        let t = p.terms(&StepFacts { body_rates_xy: [3.0, -4.0], ..facts() });
        assert!(close(t.rate, -0.001 * (0.09 + 0.16)));

        let da = [0.5, -0.2, 0.1, 0.4];
        let t = p.terms(&StepFacts { action_change: da, ..facts() });
        let expected =
            -0.0001 * (0.01 * 0.5 + 0.25) - 0.0002 * (0.01 * 0.2 + 0.04) - 0.0002 * (0.01 * 0.1 + 0.01) - 0.0002 * (0.01 * 0.4 + 0.16);
        assert!(close(t.command, expected), "{} vs {expected}", t.command);
        assert!(close(t.total(), t.progress + t.command));
    }

    #[test]
    fn vision_based_terms_weight_progress_by_view_and_pass_by_error() {
        let p = RewardParams::vision_based();
        let t = p.terms(&StepFacts { view_alignment: 0.5, ..facts() });
        assert!(close(t.progress, 0.8 * 0.2 * 0.5));
        // Moving away is penalised in full whatever the view.
        let t = p.terms(&StepFacts { distance_after: 5.3, view_alignment: 0.0, ..facts() });
        assert!(close(t.progress, 0.8 * -0.3));
        let t = p.terms(&StepFacts { pass_error: Some(0.3), ..facts() });
        assert!(close(t.pass, 4.0 - 0.3));
    }

    #[test]
    fn the_approach_distance_makes_flying_round_a_gate_progress() {
        // A gate at the origin facing +x (passes go from x < 0 to x >= 0); left is +y.
        let gate = Gate::new(Vector3::zeros(), 0.0);
        let behind = Vector3::new(-2.0, 1.0, 0.5);
        let (centre, approach) = (ProgressDistance::Centre, ProgressDistance::Approach);
        assert_eq!(approach.to_gate(&gate, &behind), centre.to_gate(&gate, &behind), "behind the plane: straight to the centre");
        // Beside the frame, first in front of the gate, then behind it: no progress to the
        // centre, but round the gate towards its back side under the approach distance.
        let (front, back) = (Vector3::new(2.0, 2.0, 0.0), Vector3::new(-2.0, 2.0, 0.0));
        assert!(close(centre.to_gate(&gate, &front), centre.to_gate(&gate, &back)));
        let via = (front - Vector3::new(-APPROACH_DEPTH, 0.0, 0.0)).norm() + APPROACH_DEPTH;
        assert!(close(approach.to_gate(&gate, &front), via));
        assert!(approach.to_gate(&gate, &front) - approach.to_gate(&gate, &back) > 2.5);
        // Never shorter than the straight line.
        for p in [front, Vector3::new(0.1, 0.0, 0.0), Vector3::new(5.0, -3.0, 1.0)] {
            assert!(approach.to_gate(&gate, &p) >= centre.to_gate(&gate, &p));
        }
    }

    #[test]
    fn action_filter_follows_the_six_hertz_low_pass() {
        let p = RewardParams::state_based();
        let alpha = p.filter_alpha(0.02);
        assert!(close(alpha, 0.02 / (0.02 + 1.0 / (2.0 * std::f64::consts::PI * 6.0))));
        let mut f = ActionFilter::default();
        let d = f.update(&[1.0, 0.0, -1.0, 0.5], alpha);
        // ã = α a first, then Δa = a − ã.
        assert!(close(d[0], 1.0 - alpha));
        assert!(close(d[2], -1.0 + alpha));
        let d = f.update(&[1.0, 0.0, -1.0, 0.5], alpha);
        assert!(close(d[0], (1.0 - alpha) * (1.0 - alpha)));
    }
}
