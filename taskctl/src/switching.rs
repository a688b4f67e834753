//! Task switching by reward-curve flatness (SPEC §8, thesis §2.2.4): Spearman's ρ between an
//! environment's recent cumulative rollout rewards and time, scored `q = 1 / (1 + α ρ²)`.

use serde::{Deserialize, Serialize};
use sim::seed::mix;

/// When an environment gets a new track.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum SwitchPolicy {
    /// With probability q once the window is full (the thesis' method).
    #[default]
    Adaptive,
    /// With a fixed probability after every rollout (the ablation).
    Random,
    /// Never: every environment keeps its first track.
    None,
}

/// Switching parameters; `Default` is the state-based column of SPEC §8.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SwitchParams {
    /// Policy.
    pub policy: SwitchPolicy,
    /// Window length l: rollouts whose rewards enter ρ. Default 600.
    pub window: usize,
    /// Sensitivity α of the score. Default 1000 (SB); the vision profile uses 100.
    pub alpha: f64,
    /// Switch probability per rollout of the random policy. Default 1.616e-3.
    pub random_probability: f64,
}

impl Default for SwitchParams {
    fn default() -> Self {
        Self { policy: SwitchPolicy::Adaptive, window: 600, alpha: 1000.0, random_probability: 1.616e-3 }
    }
}

/// A switching parameter outside its range, named as in a run config (`switching.window`, …).
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
#[error("switching.{field}: {reason}")]
pub struct InvalidSwitchParams {
    /// The parameter.
    pub field: &'static str,
    /// What is wrong with its value.
    pub reason: String,
}

impl SwitchParams {
    /// Every value in its range, or the first that is not.
    pub fn check(&self) -> Result<(), InvalidSwitchParams> {
        let invalid = |field, reason| Err(InvalidSwitchParams { field, reason });
        if self.window < 2 {
            return invalid("window", format!("{} rollouts; ρ needs at least 2", self.window));
        }
        if !(self.alpha.is_finite() && self.alpha >= 0.0) {
            return invalid("alpha", format!("{} must be a finite sensitivity ≥ 0", self.alpha));
        }
        if !(0.0..=1.0).contains(&self.random_probability) {
            return invalid("random_probability", format!("{} is not a probability", self.random_probability));
        }
        Ok(())
    }
}

/// Ranks 1..=n of `values`, ties sharing the average of their ranks.
pub fn average_ranks(values: &[f64]) -> Vec<f64> {
    let mut order: Vec<usize> = (0..values.len()).collect();
    order.sort_by(|&a, &b| values[a].total_cmp(&values[b]));
    let mut ranks = vec![0.0; values.len()];
    let mut i = 0;
    while i < order.len() {
        let mut j = i;
        while j + 1 < order.len() && values[order[j + 1]] == values[order[i]] {
            j += 1;
        }
        // Positions i..=j (0-based) share ranks i+1 ..= j+1.
        let rank = (i + j) as f64 / 2.0 + 1.0;
        for &k in &order[i..=j] {
            ranks[k] = rank;
        }
        i = j + 1;
    }
    ranks
}

/// Spearman's ρ between `values` (in time order) and their positions in time, as
/// `scipy.stats.spearmanr`; 0 where it is undefined (fewer than two values, or all equal).
pub fn spearman_over_time(values: &[f64]) -> f64 {
    let n = values.len();
    if n < 2 {
        return 0.0;
    }
    let ranks = average_ranks(values);
    let mean = (n as f64 + 1.0) / 2.0;
    let (mut cov, mut var_r, mut var_t) = (0.0, 0.0, 0.0);
    for (i, r) in ranks.iter().enumerate() {
        let (dr, dt) = (r - mean, (i + 1) as f64 - mean);
        cov += dr * dt;
        var_r += dr * dr;
        var_t += dt * dt;
    }
    if var_r == 0.0 { 0.0 } else { cov / (var_r * var_t).sqrt() }
}

/// The flatness score `q = 1 / (1 + α ρ²)`: 1 for a flat curve, towards 0 for a trend.
pub fn flatness_score(rho: f64, alpha: f64) -> f64 {
    1.0 / (1.0 + alpha * rho * rho)
}

/// A uniform number in [0, 1) determined by `(seed, a, b)` alone.
pub fn uniform(seed: u64, a: u64, b: u64) -> f64 {
    let h = mix(mix(mix(seed) ^ a) ^ b);
    (h >> 11) as f64 / (1u64 << 53) as f64
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn spearman_matches_hand_computed_values() {
        assert_eq!(spearman_over_time(&[1.0, 2.0, 3.0, 4.0, 5.0]), 1.0);
        assert_eq!(spearman_over_time(&[9.0, 4.0, 3.0, 2.0, -1.0]), -1.0);
        // One swap among four: 1 − 6·2 / (4·15) = 0.8.
        assert!((spearman_over_time(&[1.0, 3.0, 2.0, 4.0]) - 0.8).abs() < 1e-15);
        // Ties take average ranks: [1, 2.5, 2.5, 4]; scipy.stats.spearmanr gives 0.9486832980505138.
        assert!((spearman_over_time(&[1.0, 2.0, 2.0, 3.0]) - 0.948_683_298_050_513_8).abs() < 1e-15);
        assert_eq!(average_ranks(&[5.0, 1.0, 5.0, 5.0, 0.0]), vec![4.0, 2.0, 4.0, 4.0, 1.0]);
        // Undefined cases count as flat.
        assert_eq!(spearman_over_time(&[3.0; 10]), 0.0);
        assert_eq!(spearman_over_time(&[3.0]), 0.0);
        assert_eq!(spearman_over_time(&[]), 0.0);
    }

    #[test]
    fn flatness_score_follows_the_formula() {
        assert_eq!(flatness_score(0.0, 1000.0), 1.0);
        assert!((flatness_score(0.1, 1000.0) - 1.0 / 11.0).abs() < 1e-15);
        assert!((flatness_score(-0.5, 100.0) - 1.0 / 26.0).abs() < 1e-15);
    }

    #[test]
    fn uniform_draws_are_deterministic_and_spread() {
        assert_eq!(uniform(1, 2, 3), uniform(1, 2, 3));
        let draws: Vec<f64> = (0..10_000).map(|i| uniform(42, 7, i)).collect();
        assert!(draws.iter().all(|u| (0.0..1.0).contains(u)));
        let mean = draws.iter().sum::<f64>() / draws.len() as f64;
        assert!((mean - 0.5).abs() < 0.02, "{mean}");
    }
}
