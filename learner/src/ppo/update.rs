//! The PPO update: epochs × shuffled minibatches of the clipped-surrogate and value losses,
//! global gradient-norm clipping, Adam with L2 weight decay (SB3 semantics).

use burn::module::ParamId;
use burn::optim::{GradientsParams, ModuleOptimizer};
use burn::tensor::{Device, Tensor, TensorData};
use policy::ActorCritic;
use rand::seq::SliceRandom;
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

use super::loss::{clipped_surrogate, log_prob, normalize_advantages, value_loss};
use crate::config::PpoConfig;

/// The samples of one rollout, flattened (`n` rows).
#[derive(Clone, Debug, Default)]
pub struct TrainingBatch {
    /// Normalised observations, `n × obs_dim`.
    pub observations: Vec<f32>,
    /// Actions taken (unclipped samples), `n × action_dim`.
    pub actions: Vec<f32>,
    /// Their log-probabilities when taken.
    pub old_log_probs: Vec<f32>,
    /// GAE advantages.
    pub advantages: Vec<f32>,
    /// Value targets.
    pub returns: Vec<f32>,
    /// Values when taken (for explained variance).
    pub old_values: Vec<f32>,
}

impl TrainingBatch {
    /// Number of samples.
    pub fn len(&self) -> usize {
        self.returns.len()
    }

    /// True when there are no samples.
    pub fn is_empty(&self) -> bool {
        self.returns.is_empty()
    }
}

/// Averages over an update, named as CleanRL logs them.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct UpdateStats {
    /// `losses/policy_loss`.
    pub policy_loss: f64,
    /// `losses/value_loss`.
    pub value_loss: f64,
    /// `losses/approx_kl`: mean of (r − 1) − ln r.
    pub approx_kl: f64,
    /// `losses/clipfrac`: fraction of samples with |r − 1| > ε.
    pub clip_fraction: f64,
    /// `losses/explained_variance` of the old values.
    pub explained_variance: f64,
    /// Global gradient norm before clipping, averaged.
    pub grad_norm: f64,
    /// Gradient steps taken.
    pub gradient_steps: usize,
}

/// One PPO update of `model` on `batch`; returns the updated model and its statistics.
pub fn update(
    mut model: ActorCritic,
    optimizer: &mut ModuleOptimizer,
    batch: &TrainingBatch,
    config: &PpoConfig,
    learning_rate: f64,
    rng: &mut ChaCha8Rng,
    device: &Device,
) -> (ActorCritic, UpdateStats) {
    let n = batch.len();
    let obs_dim = batch.observations.len() / n;
    let act_dim = batch.actions.len() / n;
    let minibatch = config.batch_size.min(n);
    let mut stats = UpdateStats::default();
    let mut indices: Vec<usize> = (0..n).collect();
    let ids = model.param_ids();
    for _ in 0..config.n_epochs {
        indices.shuffle(rng);
        for chunk in indices.chunks(minibatch) {
            let rows = |data: &[f32], width: usize| -> Vec<f32> {
                chunk.iter().flat_map(|&i| data[i * width..(i + 1) * width].iter().copied()).collect()
            };
            let b = chunk.len();
            let mut advantages = rows(&batch.advantages, 1);
            normalize_advantages(&mut advantages);
            let obs = Tensor::<2>::from_data(TensorData::new(rows(&batch.observations, obs_dim), [b, obs_dim]), device);
            let actions = Tensor::<2>::from_data(TensorData::new(rows(&batch.actions, act_dim), [b, act_dim]), device);
            let old_log_probs = Tensor::<1>::from_data(TensorData::new(rows(&batch.old_log_probs, 1), [b]), device);
            let advantages = Tensor::<1>::from_data(TensorData::new(advantages, [b]), device);
            let returns = Tensor::<1>::from_data(TensorData::new(rows(&batch.returns, 1), [b]), device);

            let (mean, values) = model.forward(obs);
            let new_log_probs = log_prob(actions, mean, model.log_std.val());
            let log_ratio = new_log_probs - old_log_probs;
            let ratio = log_ratio.clone().exp();
            let policy_loss = clipped_surrogate(ratio.clone(), advantages, config.clip_range);
            let value_loss = value_loss(values, returns);
            // The entropy of a state-independent Gaussian does not depend on the data; with
            // SPEC's ent_coef = 0 it contributes nothing and is left out of the graph.
            let loss = policy_loss.clone() + value_loss.clone().mul_scalar(config.vf_coef);

            let mut grads = GradientsParams::from_grads(loss.backward(), &model);
            let norm = clip_global_norm(&mut grads, &ids, config.max_grad_norm);
            model = optimizer.step(learning_rate, model, grads);

            let ratios = ratio.into_data().try_into_vec::<f32>().expect("float ratios");
            let log_ratios = log_ratio.into_data().try_into_vec::<f32>().expect("float log ratios");
            stats.approx_kl += ratios.iter().zip(&log_ratios).map(|(r, l)| f64::from((r - 1.0) - l)).sum::<f64>() / b as f64;
            stats.clip_fraction +=
                ratios.iter().filter(|r| (f64::from(**r) - 1.0).abs() > config.clip_range).count() as f64 / b as f64;
            stats.policy_loss += f64::from(scalar(policy_loss));
            stats.value_loss += f64::from(scalar(value_loss));
            stats.grad_norm += norm;
            stats.gradient_steps += 1;
        }
    }
    let steps = stats.gradient_steps.max(1) as f64;
    for x in [&mut stats.policy_loss, &mut stats.value_loss, &mut stats.approx_kl, &mut stats.clip_fraction, &mut stats.grad_norm] {
        *x /= steps;
    }
    stats.explained_variance = explained_variance(&batch.old_values, &batch.returns);
    (model, stats)
}

/// Scales every gradient by `max / (norm + 1e-6)` when the global norm exceeds `max`
/// (torch `clip_grad_norm_`); returns the norm before clipping.
pub fn clip_global_norm(grads: &mut GradientsParams, ids: &[(ParamId, usize)], max: f64) -> f64 {
    let mut squares = 0.0f64;
    for &(id, rank) in ids {
        let sum = match rank {
            1 => grads.get::<1>(id).map(|g| scalar(g.powf_scalar(2.0).sum())),
            _ => grads.get::<2>(id).map(|g| scalar(g.powf_scalar(2.0).sum())),
        };
        squares += f64::from(sum.unwrap_or(0.0));
    }
    let norm = squares.sqrt();
    let coefficient = max / (norm + 1e-6);
    if coefficient < 1.0 {
        for &(id, rank) in ids {
            match rank {
                1 => {
                    if let Some(g) = grads.remove::<1>(id) {
                        grads.register(id, g.mul_scalar(coefficient));
                    }
                }
                _ => {
                    if let Some(g) = grads.remove::<2>(id) {
                        grads.register(id, g.mul_scalar(coefficient));
                    }
                }
            }
        }
    }
    norm
}

/// 1 − Var(returns − values) / Var(returns); NaN when the returns do not vary (SB3).
pub fn explained_variance(values: &[f32], returns: &[f32]) -> f64 {
    let var = |x: &mut dyn Iterator<Item = f64>| {
        let v: Vec<f64> = x.collect();
        let m = v.iter().sum::<f64>() / v.len() as f64;
        v.iter().map(|a| (a - m).powi(2)).sum::<f64>() / v.len() as f64
    };
    let var_returns = var(&mut returns.iter().map(|&r| f64::from(r)));
    if var_returns == 0.0 {
        return f64::NAN;
    }
    let var_residual = var(&mut returns.iter().zip(values).map(|(&r, &v)| f64::from(r - v)));
    1.0 - var_residual / var_returns
}

fn scalar(t: Tensor<1>) -> f32 {
    t.into_data().try_into_vec::<f32>().expect("float scalar")[0]
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::tensor::Device;

    /// Gradients of `sum(w ⊙ c)` are `c`: known norms to clip.
    #[test]
    fn global_norm_clipping_scales_all_gradients_together() {
        let device = Device::flex().autodiff();
        let arch = policy::Architecture { hidden: vec![3], ..policy::Architecture::paper() };
        let model = ActorCritic::new(&arch, -0.5, 1, &device);
        let ids = model.param_ids();
        // loss = 3 Σ log_std: its gradient is 3 per element, every other parameter has none.
        let loss = model.log_std.val().sum().mul_scalar(3.0);
        let mut grads = GradientsParams::from_grads(loss.backward(), &model);
        // Only log_std has a gradient: norm = 3·√4 = 6.
        let norm = clip_global_norm(&mut grads, &ids, 0.5);
        assert!((norm - 6.0).abs() < 1e-5, "{norm}");
        let (log_std_id, _) = *ids.last().unwrap();
        let clipped = grads.get::<1>(log_std_id).unwrap().into_data().try_into_vec::<f32>().unwrap();
        for g in clipped {
            assert!((f64::from(g) - 3.0 * 0.5 / (6.0 + 1e-6)).abs() < 1e-6);
        }
        // Below the limit nothing changes.
        let loss = model.log_std.val().sum().mul_scalar(0.1);
        let mut grads = GradientsParams::from_grads(loss.backward(), &model);
        let norm = clip_global_norm(&mut grads, &ids, 0.5);
        assert!((norm - 0.2).abs() < 1e-6);
        let g = grads.get::<1>(log_std_id).unwrap().into_data().try_into_vec::<f32>().unwrap();
        assert!(g.iter().all(|x| (x - 0.1).abs() < 1e-7));
    }

    #[test]
    fn explained_variance_follows_the_definition() {
        assert!((explained_variance(&[1.0, 2.0, 3.0], &[1.0, 2.0, 3.0]) - 1.0).abs() < 1e-12);
        assert!(explained_variance(&[0.0; 3], &[1.0, 2.0, 3.0]).abs() < 1e-12);
        assert!(explained_variance(&[0.0; 3], &[2.0; 3]).is_nan());
    }
}
