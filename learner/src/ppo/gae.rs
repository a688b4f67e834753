//! Generalised advantage estimation, keeping termination and truncation apart.

/// Advantages and returns of one rollout, laid out step-major (`[step][env]`).
#[derive(Clone, Debug, PartialEq)]
pub struct Advantages {
    /// GAE(γ, λ) advantages.
    pub advantages: Vec<f32>,
    /// Value targets: advantages + values.
    pub returns: Vec<f32>,
}

/// One rollout's per-step data as GAE needs it, step-major `[step][env]`.
pub struct GaeInput<'a> {
    /// Environments per step.
    pub envs: usize,
    /// Rewards r_t.
    pub rewards: &'a [f32],
    /// Value estimates V(s_t).
    pub values: &'a [f32],
    /// The step ended in a crash: nothing follows it.
    pub terminated: &'a [bool],
    /// The step hit the time limit: the episode would have gone on.
    pub truncated: &'a [bool],
    /// V(final observation) of truncated steps (ignored elsewhere).
    pub truncation_values: &'a [f32],
    /// V(s) after the rollout's last step, per environment.
    pub last_values: &'a [f32],
}

/// GAE as Stable-Baselines3 computes it: a truncated step is bootstrapped by adding
/// γ·V(final observation) to its reward, then — like a termination — cuts the recursion,
/// because the next stored observation belongs to a new episode.
// `e` indexes the per-environment carry and, with `t`, the flat rollout arrays.
#[allow(clippy::needless_range_loop)]
pub fn gae(input: &GaeInput<'_>, gamma: f32, lambda: f32) -> Advantages {
    let n = input.envs;
    let steps = input.rewards.len() / n;
    let mut advantages = vec![0.0f32; input.rewards.len()];
    let mut next_advantage = vec![0.0f32; n];
    for t in (0..steps).rev() {
        for e in 0..n {
            let i = t * n + e;
            let ended = input.terminated[i] || input.truncated[i];
            let mut reward = input.rewards[i];
            if input.truncated[i] {
                reward += gamma * input.truncation_values[i];
            }
            let next_value = if t + 1 == steps { input.last_values[e] } else { input.values[i + n] };
            let carry = if ended { 0.0 } else { 1.0 };
            let delta = reward + gamma * next_value * carry - input.values[i];
            next_advantage[e] = delta + gamma * lambda * carry * next_advantage[e];
            advantages[i] = next_advantage[e];
        }
    }
    let returns = advantages.iter().zip(input.values).map(|(a, v)| a + v).collect();
    Advantages { advantages, returns }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn matches_hand_computed_values_with_a_termination_and_a_truncation() {
        // One environment, 5 steps: step 1 crashes, step 3 is truncated (V(final) = 2.0).
        let (g, l) = (0.9f32, 0.8f32);
        let rewards = [1.0, 2.0, 0.5, 1.0, 3.0];
        let values = [0.5, 1.0, 0.2, 0.4, 1.5];
        let terminated = [false, true, false, false, false];
        let truncated = [false, false, false, true, false];
        let truncation_values = [0.0, 0.0, 0.0, 2.0, 0.0];
        let out = gae(
            &GaeInput {
                envs: 1,
                rewards: &rewards,
                values: &values,
                terminated: &terminated,
                truncated: &truncated,
                truncation_values: &truncation_values,
                last_values: &[0.7],
            },
            g,
            l,
        );
        // By hand, backwards:
        let a4 = 3.0 + g * 0.7 - 1.5; // bootstrap with the last value
        let a3 = (1.0 + g * 2.0) - 0.4; // truncated: reward + γV(final), chain cut
        let a2 = (0.5 + g * 0.4 - 0.2) + g * l * a3;
        let a1 = 2.0 - 1.0; // terminated: no bootstrap
        let a0 = (1.0 + g * 1.0 - 0.5) + g * l * a1;
        let expected = [a0, a1, a2, a3, a4];
        for (got, want) in out.advantages.iter().zip(expected) {
            assert!((got - want).abs() < 1e-6, "{:?} vs {expected:?}", out.advantages);
        }
        for i in 0..5 {
            assert!((out.returns[i] - (expected[i] + values[i])).abs() < 1e-6);
        }
    }

    #[test]
    fn environments_are_independent() {
        // Two environments interleaved step-major give each its own single-env result.
        let one = |r: [f32; 3], v: [f32; 3], last: f32| {
            gae(
                &GaeInput {
                    envs: 1,
                    rewards: &r,
                    values: &v,
                    terminated: &[false; 3],
                    truncated: &[false; 3],
                    truncation_values: &[0.0; 3],
                    last_values: &[last],
                },
                0.99,
                0.95,
            )
            .advantages
        };
        let a = one([1.0, 0.0, 2.0], [0.1, 0.2, 0.3], 0.4);
        let b = one([-1.0, 3.0, 0.5], [1.0, 0.0, -0.5], 2.0);
        let both = gae(
            &GaeInput {
                envs: 2,
                rewards: &[1.0, -1.0, 0.0, 3.0, 2.0, 0.5],
                values: &[0.1, 1.0, 0.2, 0.0, 0.3, -0.5],
                terminated: &[false; 6],
                truncated: &[false; 6],
                truncation_values: &[0.0; 6],
                last_values: &[0.4, 2.0],
            },
            0.99,
            0.95,
        );
        for t in 0..3 {
            assert_eq!(both.advantages[2 * t], a[t]);
            assert_eq!(both.advantages[2 * t + 1], b[t]);
        }
    }
}
