//! The PPO update, in CleanRL's order: epochs × shuffled minibatches → `minibatch_loss`
//! (clipped surrogate and value loss) → backward → gradient-norm clipping → Adam with L2 weight
//! decay (SB3 semantics), with named statistics (`UpdateStats`).

use burn::module::{Module, ParamId};
use burn::optim::{GradientsParams, ModuleOptimizer};
use burn::tensor::{Device, Tensor, TensorData};
use policy::vision::{IMAGE_SIDE, image_tensor};
use policy::{ActorCritic, VisionActorCritic};
use rand::seq::SliceRandom;
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

use super::loss::{clipped_surrogate, gaussian_entropy, log_prob, normalize_advantages, value_loss};
use super::mirror::MirrorTerm;
use crate::config::{Frozen, PpoConfig};

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
    /// Camera images, `n × 84 × 84` bytes, for a vision agent; empty otherwise.
    pub images: Vec<u8>,
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
    /// The policy's part of it (actor network and log std), averaged.
    pub actor_grad_norm: f64,
    /// The value function's part of it (critic network), averaged.
    pub critic_grad_norm: f64,
    /// Mean of the policy's log standard deviation after the update (`policy/log_std`).
    pub log_std: f64,
    /// The mirror term's divergence before its weight, averaged (`losses/mirror`; NaN without
    /// the term).
    pub mirror_loss: f64,
    /// Gradient steps taken.
    pub gradient_steps: usize,
}

/// One minibatch on the device: rows of a [`TrainingBatch`], advantages normalised over it.
pub struct Minibatch {
    images: Option<Tensor<4>>,
    frozen_outputs: Option<(Frozen, Tensor<2>)>,
    observations: Tensor<2>,
    actions: Tensor<2>,
    old_log_probs: Tensor<1>,
    advantages: Tensor<1>,
    returns: Tensor<1>,
}

impl Minibatch {
    /// Its normalised observations (the state-based networks' input, the vision critic's).
    pub fn observations(&self) -> Tensor<2> {
        self.observations.clone()
    }

    /// Its camera images `[b, 1, 84, 84]` in [0, 1], when the batch has images and they
    /// do not pass through frozen layers.
    pub fn images(&self) -> Option<Tensor<4>> {
        self.images.clone()
    }

    /// Which layers are frozen, and their outputs on its images (`[b, width]`, constants of
    /// the graph), when some are.
    pub fn frozen_outputs(&self) -> Option<(Frozen, Tensor<2>)> {
        self.frozen_outputs.clone()
    }
}

/// What the PPO update needs of a network, whichever agent it is.
pub trait PpoNetwork: Module {
    /// Action means `[b, action_dim]` and values `[b]` on a minibatch.
    fn outputs(&self, m: &Minibatch) -> (Tensor<2>, Tensor<1>);
    /// The log standard deviation parameter.
    fn log_std(&self) -> Tensor<1>;
    /// Every parameter's id and rank, in export order.
    fn param_ids(&self) -> Vec<(ParamId, usize)>;
    /// Number of the critic's parameters, which come last before the log std in that order.
    fn critic_param_count(&self) -> usize;
    /// Action means `[b, action_dim]` of normalised state observations alone, for the
    /// mirror term; `None` for a network that needs more (the vision agent's images).
    fn state_action_means(&self, states: Tensor<2>) -> Option<Tensor<2>>;
    /// The outputs of the `frozen` layers on every image of `batch` (`n × width`), without a
    /// graph, for an update that leaves those layers as they are; `None` for a network without
    /// such layers.
    fn frozen_outputs(&self, _batch: &TrainingBatch, _frozen: Frozen, _device: &Device) -> Option<Vec<f32>> {
        None
    }
}

impl PpoNetwork for ActorCritic {
    fn outputs(&self, m: &Minibatch) -> (Tensor<2>, Tensor<1>) {
        self.forward(m.observations())
    }

    fn log_std(&self) -> Tensor<1> {
        self.log_std.val()
    }

    fn param_ids(&self) -> Vec<(ParamId, usize)> {
        ActorCritic::param_ids(self)
    }

    fn critic_param_count(&self) -> usize {
        self.critic.param_ids().len()
    }

    fn state_action_means(&self, states: Tensor<2>) -> Option<Tensor<2>> {
        Some(self.action_means(states))
    }
}

impl PpoNetwork for VisionActorCritic {
    #[allow(clippy::expect_used, reason = "the learner admits a vision agent's chunks only with their images")]
    fn outputs(&self, m: &Minibatch) -> (Tensor<2>, Tensor<1>) {
        let embeddings = match m.frozen_outputs() {
            Some((Frozen::Encoder, embeddings)) => embeddings,
            Some((Frozen::Convolutions, convolved)) => self.embed_convolved(convolved),
            _ => return self.forward(m.images().expect("a vision agent's minibatch has images"), m.observations()),
        };
        (self.actor_mean_of(embeddings, m.observations()), self.critic.forward(m.observations()).squeeze_dim(1))
    }

    fn log_std(&self) -> Tensor<1> {
        self.log_std.val()
    }

    fn param_ids(&self) -> Vec<(ParamId, usize)> {
        VisionActorCritic::param_ids(self)
    }

    fn critic_param_count(&self) -> usize {
        self.critic.param_ids().len()
    }

    fn state_action_means(&self, _states: Tensor<2>) -> Option<Tensor<2>> {
        None
    }

    #[allow(clippy::expect_used, reason = "float outputs")]
    fn frozen_outputs(&self, batch: &TrainingBatch, frozen: Frozen, device: &Device) -> Option<Vec<f32>> {
        let width = frozen.output_width()?;
        // On the inner backend: no graph is recorded, as none would be differentiated.
        let (network, device) = (self.valid(), device.clone().without_autodiff());
        let mut outputs = Vec::with_capacity(batch.len() * width);
        for images in batch.images.chunks(FROZEN_ROWS * IMAGE_SIDE * IMAGE_SIDE) {
            let convolved = network.convolve(image_tensor(images, &device));
            let output = if frozen == Frozen::Encoder { network.embed_convolved(convolved) } else { convolved };
            outputs.extend(output.into_data().try_into_vec::<f32>().expect("float outputs"));
        }
        Some(outputs)
    }
}

/// Images passed through the frozen layers at a time: a bounded working set of activations.
const FROZEN_ROWS: usize = 512;

impl TrainingBatch {
    /// The rows `rows` as a [`Minibatch`] on `device`; with `frozen` layers and their outputs
    /// on the batch ([`PpoNetwork::frozen_outputs`]) the minibatch carries those rows instead
    /// of its images.
    pub fn minibatch(&self, rows: &[usize], frozen: Option<(Frozen, &[f32])>, device: &Device) -> Minibatch {
        let n = self.len();
        let (obs_dim, act_dim) = (self.observations.len() / n, self.actions.len() / n);
        let take = |data: &[f32], width: usize| gather_rows(data, rows, width);
        let b = rows.len();
        let mut advantages = take(&self.advantages, 1);
        normalize_advantages(&mut advantages);
        let pixels = IMAGE_SIDE * IMAGE_SIDE;
        let frozen_outputs = frozen.and_then(|(frozen, outputs)| {
            let width = frozen.output_width()?;
            Some((frozen, Tensor::<2>::from_data(TensorData::new(take(outputs, width), [b, width]), device)))
        });
        let images = (frozen_outputs.is_none() && !self.images.is_empty()).then(|| {
            let bytes = gather_rows(&self.images, rows, pixels);
            Tensor::<4>::from_data(TensorData::new(policy::pixels_to_unit(&bytes), [b, 1, IMAGE_SIDE, IMAGE_SIDE]), device)
        });
        Minibatch {
            images,
            frozen_outputs,
            observations: Tensor::<2>::from_data(TensorData::new(take(&self.observations, obs_dim), [b, obs_dim]), device),
            actions: Tensor::<2>::from_data(TensorData::new(take(&self.actions, act_dim), [b, act_dim]), device),
            old_log_probs: Tensor::<1>::from_data(TensorData::new(take(&self.old_log_probs, 1), [b]), device),
            advantages: Tensor::<1>::from_data(TensorData::new(advantages, [b]), device),
            returns: Tensor::<1>::from_data(TensorData::new(take(&self.returns, 1), [b]), device),
        }
    }
}

/// Rows `rows` of `data`, a row-major array of rows `width` wide, one after another. Whole rows
/// are copied: gathering element by element (a flattening iterator) ran on one thread while
/// the other waited, and the default run is 1.08× faster without it.
fn gather_rows<T: Copy>(data: &[T], rows: &[usize], width: usize) -> Vec<T> {
    let mut out = Vec::with_capacity(rows.len() * width);
    for &i in rows {
        out.extend_from_slice(&data[i * width..(i + 1) * width]);
    }
    out
}

/// The parts of a minibatch's loss the statistics read.
pub struct LossParts {
    /// The clipped-surrogate part.
    pub policy_loss: Tensor<1>,
    /// The value part (before vf_coef).
    pub value_loss: Tensor<1>,
    /// Probability ratios new/old per sample.
    pub ratio: Tensor<1>,
    /// Their logarithms.
    pub log_ratio: Tensor<1>,
}

/// Largest log-ratio of new to old action probability the loss takes (see [`ppo_loss`]).
pub const MAX_LOG_RATIO: f32 = 20.0;

/// PPO's loss on one minibatch — clipped surrogate + vf_coef × value loss − ent_coef ×
/// entropy, what is differentiated — and its parts (CleanRL's `ppo_continuous_action.py`). The
/// entropy of a state-independent Gaussian depends on the log std alone, so the term only
/// pushes the exploration noise up; with SPEC's ent_coef = 0 it is left out of the graph.
pub fn minibatch_loss<N: PpoNetwork>(model: &N, m: Minibatch, config: &PpoConfig) -> (Tensor<1>, LossParts) {
    let (mean, values) = model.outputs(&m);
    ppo_loss(mean, values, model.log_std(), m, config)
}

/// [`minibatch_loss`] from a network's outputs on the minibatch — action means, values and the
/// log std — whichever network produced them (the vision agent's reads images as well).
pub fn ppo_loss(mean: Tensor<2>, values: Tensor<1>, log_std: Tensor<1>, m: Minibatch, config: &PpoConfig) -> (Tensor<1>, LossParts) {
    let new_log_probs = log_prob(m.actions, mean, log_std.clone());
    // Clamped so that no rollout can make the ratio infinite (an old log-prob of −1e9 did, and
    // three such updates stopped a run). e^±20 is far outside any clip range, so the clipped
    // objective of every healthy sample is unchanged, bit for bit.
    let log_ratio = (new_log_probs - m.old_log_probs).clamp(-MAX_LOG_RATIO, MAX_LOG_RATIO);
    let ratio = log_ratio.clone().exp();
    let policy_loss = clipped_surrogate(ratio.clone(), m.advantages, config.clip_range);
    let value_loss = value_loss(values, m.returns);
    let mut loss = policy_loss.clone() + value_loss.clone().mul_scalar(config.vf_coef);
    if config.ent_coef != 0.0 {
        loss = loss - gaussian_entropy(log_std).mul_scalar(config.ent_coef);
    }
    (loss, LossParts { policy_loss, value_loss, ratio, log_ratio })
}

impl UpdateStats {
    /// Adds one gradient step's figures (sums; [`UpdateStats::average`] divides at the end).
    #[allow(clippy::expect_used, reason = "float ratios; float log ratios")]
    fn add_step(&mut self, loss: LossParts, squares: &[f64], critic: std::ops::Range<usize>, clip_range: f64) {
        let ratios = loss.ratio.into_data().try_into_vec::<f32>().expect("float ratios");
        let log_ratios = loss.log_ratio.into_data().try_into_vec::<f32>().expect("float log ratios");
        let b = ratios.len() as f64;
        self.approx_kl += ratios.iter().zip(&log_ratios).map(|(r, l)| f64::from((r - 1.0) - l)).sum::<f64>() / b;
        self.clip_fraction += ratios.iter().filter(|r| (f64::from(**r) - 1.0).abs() > clip_range).count() as f64 / b;
        self.policy_loss += f64::from(scalar(loss.policy_loss));
        self.value_loss += f64::from(scalar(loss.value_loss));
        let critic_square: f64 = squares[critic].iter().sum();
        let total_square: f64 = squares.iter().sum();
        self.grad_norm += total_square.sqrt();
        self.critic_grad_norm += critic_square.sqrt();
        self.actor_grad_norm += (total_square - critic_square).max(0.0).sqrt();
        self.gradient_steps += 1;
    }

    /// Turns the per-step sums into means.
    fn average(&mut self) {
        let steps = self.gradient_steps.max(1) as f64;
        for x in [
            &mut self.policy_loss,
            &mut self.value_loss,
            &mut self.approx_kl,
            &mut self.clip_fraction,
            &mut self.grad_norm,
            &mut self.actor_grad_norm,
            &mut self.critic_grad_norm,
        ] {
            *x /= steps;
        }
    }
}

/// What one update does beyond the PPO settings.
#[derive(Clone, Copy, Debug)]
pub struct UpdateStep<'a> {
    /// Adam's learning rate.
    pub learning_rate: f64,
    /// False: only the critic's parameters take the step (the policy's gradients are dropped
    /// before clipping, so neither Adam's moments nor weight decay touch them).
    pub train_policy: bool,
    /// The mirror-symmetry term added to every minibatch's loss, when the policy trains.
    pub mirror: Option<&'a MirrorTerm>,
}

/// One PPO update of `model` on `batch`: `n_epochs` × shuffled minibatches of
/// [`minibatch_loss`] (plus the mirror term) → backward → gradient-norm clipping → Adam
/// step, as `step` says. Returns the updated model and its statistics.
pub fn update<N: PpoNetwork>(
    mut model: N,
    optimizer: &mut ModuleOptimizer,
    batch: &TrainingBatch,
    config: &PpoConfig,
    step: &UpdateStep,
    rng: &mut ChaCha8Rng,
    device: &Device,
) -> (N, UpdateStats) {
    let mut stats = UpdateStats::default();
    let mut mirror_sum = 0.0;
    let mut indices: Vec<usize> = (0..batch.len()).collect();
    let ids = model.param_ids();
    let critic = critic_range(ids.len(), model.critic_param_count());
    // The mirror term moves the policy, so it is left out while only the critic trains.
    let mirror = step.mirror.filter(|_| step.train_policy);
    // Frozen layers take no step, so their outputs are the same in every epoch: computed once
    // here, they replace the images, and no gradient reaches those layers' parameters.
    let frozen_outputs = model.frozen_outputs(batch, config.frozen, device);
    let frozen = frozen_outputs.as_deref().map(|outputs| (config.frozen, outputs));
    for _ in 0..config.n_epochs {
        indices.shuffle(rng);
        for rows in indices.chunks(config.batch_size.min(batch.len())) {
            let minibatch = batch.minibatch(rows, frozen, device);
            let (means, values) = model.outputs(&minibatch);
            // The mirror term reads the same observations, so it is taken before the PPO loss consumes them.
            let mirrored = mirror.and_then(|term| {
                let sampled = term.sampled_rows(rows.len());
                let observations = first_rows(minibatch.observations(), sampled);
                model.state_action_means(term.mirrored(observations)).map(|m| (term, m, sampled))
            });
            let (mut loss, parts) = ppo_loss(means.clone(), values, model.log_std(), minibatch, config);
            if let Some((term, mirrored_means, sampled)) = mirrored {
                let divergence = term.divergence(first_rows(means, sampled), mirrored_means, model.log_std());
                mirror_sum += f64::from(scalar(divergence.clone()));
                loss = loss + divergence.mul_scalar(term.weight);
            }
            let mut grads = GradientsParams::from_grads(loss.backward(), &model);
            if !step.train_policy {
                drop_gradients(&mut grads, ids.iter().enumerate().filter(|(i, _)| !critic.contains(i)).map(|(_, id)| *id));
            }
            let squares = clip_grad_norm(&mut grads, &ids, config.max_grad_norm);
            model = optimizer.step(step.learning_rate, model, grads);
            stats.add_step(parts, &squares, critic.clone(), config.clip_range);
        }
    }
    stats.average();
    stats.mirror_loss = match mirror {
        Some(_) => mirror_sum / stats.gradient_steps.max(1) as f64,
        None => f64::NAN,
    };
    stats.explained_variance = explained_variance(&batch.old_values, &batch.returns);
    stats.log_std = f64::from(scalar(model.log_std().mean()));
    (model, stats)
}

/// The first `n` rows of `t`; `t` itself, with no op added to the graph, when that is all of it.
fn first_rows(t: Tensor<2>, n: usize) -> Tensor<2> {
    if n < t.dims()[0] { t.narrow(0, 0, n) } else { t }
}

/// The critic's parameters' index range among `params` in export order (the actor's, then the
/// critic's `critic_params`, then the log std).
pub fn critic_range(params: usize, critic_params: usize) -> std::ops::Range<usize> {
    params - 1 - critic_params..params - 1
}

/// Runs `$body` with `$D` bound to a parameter's rank as a constant: 1, 2, or 4 (convolution
/// kernels), the ranks burn's gradient store is read with.
macro_rules! with_rank {
    ($rank:expr, $D:ident => $body:expr) => {
        match $rank {
            1 => {
                const $D: usize = 1;
                $body
            }
            2 => {
                const $D: usize = 2;
                $body
            }
            _ => {
                const $D: usize = 4;
                $body
            }
        }
    };
}

/// Gradient-norm clipping over all parameters at once (torch `clip_grad_norm_`, SB3's global
/// clipping) for parameters of rank 1, 2 or 4 (convolution kernels): when the joint norm
/// exceeds `max`, every gradient is scaled by `max / (norm + 1e-6)`. Returns each parameter's
/// squared gradient norm before clipping, in `ids` order.
pub fn clip_grad_norm(grads: &mut GradientsParams, ids: &[(ParamId, usize)], max: f64) -> Vec<f64> {
    let squares: Vec<f64> = ids
        .iter()
        .map(|&(id, rank)| {
            let sum = with_rank!(rank, D => grads.get::<D>(id).map(|g| scalar(g.powf_scalar(2.0).sum())));
            f64::from(sum.unwrap_or(0.0))
        })
        .collect();
    // Summed in parameter order from 0, as the grouped clipping this replaced did: learning
    // stays the same bit for bit.
    let total = squares.iter().fold(0.0, |sum, square| sum + square);
    let coefficient = max / (total.sqrt() + 1e-6);
    if coefficient < 1.0 {
        for &(id, rank) in ids {
            with_rank!(rank, D => if let Some(g) = grads.remove::<D>(id) {
                grads.register(id, g.mul_scalar(coefficient));
            });
        }
    }
    squares
}

/// Every gradient's values in `ids` order, flattened (a parameter without a gradient adds
/// nothing): a step's result, to compare two kernels' steps value by value.
#[allow(clippy::expect_used, reason = "gradients of float parameters are f32")]
pub fn flat_gradients(grads: &GradientsParams, ids: &[(ParamId, usize)]) -> Vec<f32> {
    let mut out = Vec::new();
    for &(id, rank) in ids {
        with_rank!(rank, D => if let Some(g) = grads.get::<D>(id) {
            out.extend(g.into_data().try_into_vec::<f32>().expect("float gradients"));
        });
    }
    out
}

/// Removes the gradients of `params` (id and rank), so the optimiser leaves them as they are.
fn drop_gradients(grads: &mut GradientsParams, params: impl Iterator<Item = (ParamId, usize)>) {
    for (id, rank) in params {
        with_rank!(rank, D => drop(grads.remove::<D>(id)));
    }
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

/// The value of a one-element tensor.
#[allow(clippy::expect_used, reason = "float scalar")]
pub fn scalar(t: Tensor<1>) -> f32 {
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
        let norm = clip_grad_norm(&mut grads, &ids, 0.5).iter().sum::<f64>().sqrt();
        assert!((norm - 6.0).abs() < 1e-5, "{norm}");
        let (log_std_id, _) = *ids.last().unwrap();
        let clipped = grads.get::<1>(log_std_id).unwrap().into_data().try_into_vec::<f32>().unwrap();
        for g in clipped {
            assert!((f64::from(g) - 3.0 * 0.5 / (6.0 + 1e-6)).abs() < 1e-6);
        }
        // Below the limit nothing changes.
        let loss = model.log_std.val().sum().mul_scalar(0.1);
        let mut grads = GradientsParams::from_grads(loss.backward(), &model);
        let squares = clip_grad_norm(&mut grads, &ids, 0.5);
        assert!((squares.iter().sum::<f64>().sqrt() - 0.2).abs() < 1e-6);
        assert!(squares[..squares.len() - 1].iter().all(|&s| s == 0.0), "only log std has a gradient");
        let g = grads.get::<1>(log_std_id).unwrap().into_data().try_into_vec::<f32>().unwrap();
        assert!(g.iter().all(|x| (x - 0.1).abs() < 1e-7));
    }

    /// A batch of 40-number `states` whose advantages are all zero: the surrogate has no
    /// gradient there, so only the extra terms of the loss move the actor.
    fn zero_advantage_batch(states: &[f32]) -> TrainingBatch {
        let n = states.len() / 40;
        TrainingBatch {
            observations: states.to_vec(),
            actions: vec![0.0; n * 4],
            old_log_probs: vec![0.0; n],
            advantages: vec![0.0; n],
            returns: vec![0.0; n],
            old_values: vec![0.0; n],
            images: Vec::new(),
        }
    }

    /// Old log-probabilities of −1e9 made the ratio infinite and the loss NaN: three such
    /// rollouts in a row stopped a run. With the log-ratio clamped the loss and its gradient
    /// stay finite, and for a healthy sample nothing changes.
    #[test]
    fn an_old_log_prob_of_minus_1e9_leaves_the_loss_finite() {
        let device = Device::flex().autodiff();
        let arch = policy::Architecture { hidden: vec![8, 8], ..policy::Architecture::cpu() };
        let model = ActorCritic::new(&arch, -0.5, 3, &device);
        let mut batch = zero_advantage_batch(&vec![0.1; 4 * 40]);
        batch.advantages = vec![1.0, -1.0, 0.5, -0.5];
        let healthy = batch.clone();
        batch.old_log_probs = vec![-1.0e9, 1.0e9, -1.0e9, 0.0];
        let config = PpoConfig::default();
        let (loss, parts) = minibatch_loss(&model, batch.minibatch(&[0, 1, 2, 3], None, &device), &config);
        let ratios = parts.ratio.into_data().try_into_vec::<f32>().unwrap();
        assert!(ratios.iter().all(|r| r.is_finite()), "{ratios:?}");
        assert!(scalar(loss).is_finite());
        // The clamp is the identity for a healthy sample's log-ratio.
        let (_, parts) = minibatch_loss(&model, healthy.minibatch(&[0, 1, 2, 3], None, &device), &config);
        let log_ratios = parts.log_ratio.into_data().try_into_vec::<f32>().unwrap();
        assert!(log_ratios.iter().all(|l| l.abs() < MAX_LOG_RATIO), "{log_ratios:?}");
    }

    /// A minibatch holds the rows it is given, whole and in the order given.
    #[test]
    fn a_minibatch_holds_its_rows_in_the_order_given() {
        let device = Device::flex();
        let states: Vec<f32> = (0..4 * 40).map(|i| i as f32).collect();
        let mut batch = zero_advantage_batch(&states);
        batch.actions = (0..4 * 4).map(|i| -(i as f32)).collect();
        batch.returns = vec![10.0, 11.0, 12.0, 13.0];
        let m = batch.minibatch(&[3, 0, 2], None, &device);
        let values = |t: Tensor<2>| t.into_data().try_into_vec::<f32>().unwrap();
        let expected: Vec<f32> = [3, 0, 2].iter().flat_map(|&r| states[r * 40..(r + 1) * 40].to_vec()).collect();
        assert_eq!(values(m.observations()), expected);
        assert_eq!(values(m.actions.clone()), [-12.0, -13.0, -14.0, -15.0, -0.0, -1.0, -2.0, -3.0, -8.0, -9.0, -10.0, -11.0]);
        assert_eq!(m.returns.clone().into_data().try_into_vec::<f32>().unwrap(), [13.0, 10.0, 12.0]);
    }

    /// With zero advantages only the mirror term moves the actor, and it makes the policy's
    /// actions on mirrored states the mirrors of its actions (its divergence falls).
    #[test]
    fn the_mirror_term_makes_the_policy_commute_with_the_reflection() {
        let device = Device::flex().autodiff();
        let layout = sim::ObservationLayout::spec(sim::ObservationFrame::Heading);
        let arch = policy::Architecture { hidden: vec![16], ..policy::Architecture::paper() };
        let n = 64;
        let states: Vec<f32> = (0..n * 40).map(|i| ((i * 37 % 101) as f32 / 50.0) - 1.0).collect();
        let batch = zero_advantage_batch(&states);
        let term = MirrorTerm::new(&layout.mirror().unwrap(), &policy::ObsNormalizer::new(40), 1.0, &device);
        let config = PpoConfig { batch_size: 32, n_epochs: 20, ..PpoConfig::default() };
        let divergence = |model: &ActorCritic| {
            let observations = Tensor::<2>::from_data(TensorData::new(states.clone(), [n, 40]), &device);
            let means = model.action_means(observations.clone());
            f64::from(scalar(term.divergence(means, model.action_means(term.mirrored(observations)), model.log_std.val())))
        };
        let run = |mirror: Option<&MirrorTerm>| {
            let model = ActorCritic::new(&arch, -0.5, 1, &device);
            let before = divergence(&model);
            let mut optimizer = burn::optim::AdamConfig::new().init();
            let step = UpdateStep { learning_rate: 1e-2, train_policy: true, mirror };
            let mut rng = <ChaCha8Rng as rand::SeedableRng>::seed_from_u64(0);
            let (model, stats) = update(model, &mut optimizer, &batch, &config, &step, &mut rng, &device);
            (before, divergence(&model), stats.mirror_loss)
        };
        let (before, after, logged) = run(Some(&term));
        assert!(before > 1e-4, "a random network is not symmetric: {before}");
        assert!(after < 0.3 * before, "made symmetric: {before} → {after}");
        assert!(logged.is_finite() && logged > after, "the logged divergence averages along the way: {logged} > {after}");
        // Taken on a quarter of each minibatch's rows (8 of 32), it still makes the policy
        // symmetric on every state, the ones it was never taken on included.
        let quarter = MirrorTerm::new(&layout.mirror().unwrap(), &policy::ObsNormalizer::new(40), 1.0, &device).on_fraction(0.25);
        let (_, after_quarter, _) = run(Some(&quarter));
        assert!(after_quarter < 0.3 * before && after_quarter != after, "a quarter of the rows: {before} → {after_quarter}");
        let (before, after, logged) = run(None);
        assert!((after - before).abs() < 1e-3 * before && logged.is_nan(), "without the term nothing moves: {before} → {after}");
    }

    /// With zero advantages, an entropy coefficient widens the policy's noise; without one the
    /// log std stays where it was.
    #[test]
    fn the_entropy_term_raises_the_log_std() {
        let device = Device::flex().autodiff();
        let arch = policy::Architecture { hidden: vec![8], ..policy::Architecture::paper() };
        let n = 32;
        let batch = zero_advantage_batch(&(0..n * 40).map(|i| (i % 7) as f32 * 0.1).collect::<Vec<_>>());
        let log_std_after = |ent_coef: f64| {
            let model = ActorCritic::new(&arch, -1.0, 1, &device);
            let mut optimizer = burn::optim::AdamConfig::new().init();
            let config = PpoConfig { batch_size: n, n_epochs: 5, ent_coef, ..PpoConfig::default() };
            let step = UpdateStep { learning_rate: 1e-2, train_policy: true, mirror: None };
            let mut rng = <ChaCha8Rng as rand::SeedableRng>::seed_from_u64(0);
            update(model, &mut optimizer, &batch, &config, &step, &mut rng, &device).1.log_std
        };
        assert!((log_std_after(0.0) + 1.0).abs() < 1e-6, "no entropy term: {}", log_std_after(0.0));
        assert!(log_std_after(0.01) > -1.0 + 0.04, "widened: {}", log_std_after(0.01));
    }

    /// Frozen layers: a minibatch of their outputs gives the same outputs as the images, the
    /// update leaves those layers bit for bit and trains the rest; with nothing frozen the
    /// same update moves the convolutions too.
    #[test]
    fn frozen_layers_take_no_step_and_their_outputs_give_the_images_outputs() {
        let device = Device::flex().autodiff();
        let arch = policy::Architecture { hidden: vec![16], agent: policy::Agent::Vision, ..policy::Architecture::paper() };
        let n = 24;
        let pixels = IMAGE_SIDE * IMAGE_SIDE;
        let images: Vec<u8> = (0..n * pixels).map(|i| if (i * 7919 % 1013) < 150 { 255 } else { (i % 3 * 55) as u8 }).collect();
        let batch = TrainingBatch {
            observations: (0..n * 40).map(|i| ((i * 37 % 101) as f32 / 50.0) - 1.0).collect(),
            actions: (0..n * 4).map(|i| ((i * 13 % 17) as f32 / 8.0) - 1.0).collect(),
            old_log_probs: vec![-3.0; n],
            advantages: (0..n).map(|i| if i % 2 == 0 { 1.0 } else { -1.0 }).collect(),
            returns: vec![1.0; n],
            old_values: vec![0.0; n],
            images,
        };
        let model = VisionActorCritic::new(&arch, -0.5, 3, &device);
        let rows: Vec<usize> = (0..n).collect();
        let (from_images, values) = model.outputs(&batch.minibatch(&rows, None, &device));
        let largest_difference = |a: Tensor<2>, b: Tensor<2>| f64::from(scalar((a - b).abs().max()));
        assert!(model.frozen_outputs(&batch, Frozen::Nothing, &device).is_none());
        for (frozen, width) in [(Frozen::Convolutions, policy::vision::CONV_OUTPUT), (Frozen::Encoder, policy::vision::EMBEDDING)] {
            let outputs = model.frozen_outputs(&batch, frozen, &device).unwrap();
            assert_eq!(outputs.len(), n * width);
            let minibatch = batch.minibatch(&rows, Some((frozen, &outputs)), &device);
            assert!(minibatch.images().is_none(), "{frozen:?}: the frozen layers' outputs replace the images");
            let (means, frozen_values) = model.outputs(&minibatch);
            assert!(largest_difference(from_images.clone(), means) < 1e-6, "{frozen:?}");
            assert!(
                largest_difference(values.clone().unsqueeze_dim(1), frozen_values.unsqueeze_dim(1)) == 0.0,
                "the critic reads the state"
            );
        }
        // Export order: three convolutions (weight, bias each), the embedding layer, then the actor.
        let convolution_params = 2 * policyfile::shapes::CONVOLUTION_COUNT;
        let params = |m: &VisionActorCritic| m.export().into_iter().map(|p| p.values).collect::<Vec<_>>();
        let before = params(&model);
        let after = |frozen: Frozen| {
            let model = VisionActorCritic::new(&arch, -0.5, 3, &device);
            let mut optimizer = burn::optim::AdamConfig::new().init();
            let config = PpoConfig { batch_size: 12, n_epochs: 2, frozen, ..PpoConfig::default() };
            let step = UpdateStep { learning_rate: 1e-3, train_policy: true, mirror: None };
            let mut rng = <ChaCha8Rng as rand::SeedableRng>::seed_from_u64(0);
            let (model, stats) = update(model, &mut optimizer, &batch, &config, &step, &mut rng, &device);
            assert_eq!(stats.gradient_steps, 4);
            params(&model)
        };
        let (embedding, actor) = (convolution_params, convolution_params + 2);
        let encoder = after(Frozen::Encoder);
        assert!(encoder[..actor] == before[..actor], "the encoder is untouched");
        assert!(encoder[actor] != before[actor], "the actor trains");
        let convolutions = after(Frozen::Convolutions);
        assert!(convolutions[..embedding] == before[..embedding], "the convolutions are untouched");
        assert!(
            convolutions[embedding] != before[embedding] && convolutions[actor] != before[actor],
            "the embedding layer and actor train"
        );
        assert!(after(Frozen::Nothing)[0] != before[0], "with nothing frozen the same update moves the first convolution");
    }

    #[test]
    fn explained_variance_follows_the_definition() {
        assert!((explained_variance(&[1.0, 2.0, 3.0], &[1.0, 2.0, 3.0]) - 1.0).abs() < 1e-12);
        assert!(explained_variance(&[0.0; 3], &[1.0, 2.0, 3.0]).abs() < 1e-12);
        assert!(explained_variance(&[0.0; 3], &[2.0; 3]).is_nan());
    }
}
