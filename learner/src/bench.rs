//! Micro-benchmark of one PPO gradient step: forward, backward and the Adam step on a batch,
//! for choosing a backend and a profile on this machine.

use std::time::Instant;

use burn::module::{Module, ParamId};
use burn::optim::GradientsParams;
use burn::tensor::Device;
use burn::tensor::Tensor;
use policy::vision::IMAGE_SIDE;
use policy::{ActorCritic, VisionActorCritic};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;

use crate::config::{LearnerConfig, PpoConfig};
use crate::learner::adam;
use crate::ppo::update::{PpoNetwork, TrainingBatch, clip_grad_norm, flat_gradients, minibatch_loss};

/// Median times of the three stages (seconds) and the implied rate.
#[derive(Clone, Copy, Debug)]
pub struct StepTiming {
    /// Forward pass through actor and critic, and the loss.
    pub forward: f64,
    /// Backward pass.
    pub backward: f64,
    /// Gradient extraction, gradient-norm clipping and the Adam step.
    pub optimizer: f64,
    /// Multiply-adds ×2 ×3 (forward + backward) per second of forward + backward.
    pub gflops: f64,
}

/// A backend this build does not have.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
#[error("backend {0:?} is not in this build (flex; ndarray with --features ndarray or openblas)")]
pub struct UnknownBackend(pub String);

/// The autodiff device of a backend this build has: `flex`, or `ndarray` with the `ndarray`
/// (or `openblas`) feature.
pub fn device(backend: &str) -> Result<Device, UnknownBackend> {
    match backend {
        "flex" => Ok(Device::flex().autodiff()),
        #[cfg(feature = "ndarray")]
        #[allow(deprecated)] // measured for the record; flex is the backend we use
        "ndarray" => Ok(Device::ndarray().autodiff()),
        other => Err(UnknownBackend(other.to_owned())),
    }
}

/// Gaussian training data of `samples` rows with `observation_dim`-long observations, as
/// normalised observations are: activations then change sign at random, as in training. (A
/// regular pattern let the branch predictor hide the cost of burn's branchy masking kernels,
/// so this benchmark once reported ~30 % less time than training spent.)
fn gaussian_batch(samples: usize, observation_dim: usize, action_dim: usize, rng: &mut ChaCha8Rng) -> TrainingBatch {
    let mut data = |n: usize| (0..n).map(|_| rng.sample::<f32, _>(StandardNormal)).collect::<Vec<f32>>();
    TrainingBatch {
        observations: data(samples * observation_dim),
        actions: data(samples * action_dim),
        old_log_probs: data(samples),
        advantages: data(samples),
        returns: data(samples),
        old_values: data(samples),
        images: Vec::new(),
    }
}

/// `samples` random 84×84 images as the renderer makes them: mostly background, gate pixels in
/// three grey levels.
fn rendered_like_images(samples: usize, rng: &mut ChaCha8Rng) -> Vec<u8> {
    let levels = [0, 0, 0, 0, 55, 155, 255];
    (0..samples * IMAGE_SIDE * IMAGE_SIDE).map(|_| levels[rng.random_range(0..levels.len())]).collect()
}

/// Runs one warm-up and `repeats` timed gradient steps of `model`: `loss` is the forward pass
/// and the loss, then backward, gradient-norm clipping over `ids`, Adam
/// with the learner's settings, and `force`, which reads a parameter so that the lazy update
/// runs inside the timing. Returns median (forward, backward, optimiser) seconds.
fn time_steps<M: Module>(
    learner: &LearnerConfig,
    mut model: M,
    ids: &[(ParamId, usize)],
    repeats: usize,
    loss: impl Fn(&M) -> Tensor<1>,
    force: impl Fn(&M),
) -> (f64, f64, f64) {
    let mut optimizer = adam(learner);
    let config = &learner.ppo;
    let (mut f, mut b, mut o) = (Vec::new(), Vec::new(), Vec::new());
    for round in 0..=repeats {
        let t0 = Instant::now();
        let loss = loss(&model);
        let _ = loss.clone().into_data(); // force the forward pass
        let t1 = Instant::now();
        let grads = loss.backward();
        let t2 = Instant::now();
        let mut grads = GradientsParams::from_grads(grads, &model);
        clip_grad_norm(&mut grads, ids, config.max_grad_norm);
        model = optimizer.step(config.learning_rate_start, model, grads);
        force(&model);
        let t3 = Instant::now();
        if round > 0 {
            f.push((t1 - t0).as_secs_f64());
            b.push((t2 - t1).as_secs_f64());
            o.push((t3 - t2).as_secs_f64());
        }
    }
    let median = |v: &mut Vec<f64>| {
        v.sort_by(f64::total_cmp);
        v[v.len() / 2]
    };
    (median(&mut f), median(&mut b), median(&mut o))
}

/// Times `repeats` gradient steps on `samples` random samples (after one warm-up step): the
/// step training takes (`minibatch_loss`, backward, gradient-norm clipping, Adam with the
/// learner's settings).
pub fn time_gradient_step(learner: &LearnerConfig, samples: usize, repeats: usize, device: &Device) -> StepTiming {
    let arch = &learner.architecture;
    let config = &learner.ppo;
    let model = ActorCritic::new(arch, config.initial_log_std, 0, device);
    let batch = gaussian_batch(samples, arch.observation_dim, arch.action_dim, &mut ChaCha8Rng::seed_from_u64(0));
    let rows: Vec<usize> = (0..samples).collect();
    let ids = model.param_ids();
    let loss = |model: &ActorCritic| minibatch_loss(model, batch.minibatch(&rows, None, device), config).0;
    let force = |model: &ActorCritic| drop(model.log_std.val().into_data());
    let (forward, backward, optimizer) = time_steps(learner, model, &ids, repeats, loss, force);
    let mut dims = vec![arch.observation_dim];
    dims.extend(&arch.hidden);
    let macs_per_sample: usize = dims.windows(2).map(|w| w[0] * w[1]).sum::<usize>() * 2
        + arch.hidden.last().copied().unwrap_or(arch.observation_dim) * (arch.action_dim + 1);
    let flops = 2.0 * 3.0 * (macs_per_sample * samples) as f64;
    StepTiming { forward, backward, optimizer, gflops: flops / (forward + backward) / 1e9 }
}

/// [`time_gradient_step`] for the vision agent (SPEC §5): the CNN actor on random 84×84
/// images and the state's proprioceptive part, the MLP critic on the state, the same PPO loss and optimiser.
pub fn time_vision_gradient_step(learner: &LearnerConfig, samples: usize, repeats: usize, device: &Device) -> StepTiming {
    let arch = &learner.architecture;
    let config = &learner.ppo;
    let model = VisionActorCritic::new(arch, config.initial_log_std, 0, device);
    let mut rng = ChaCha8Rng::seed_from_u64(0);
    let mut batch = gaussian_batch(samples, arch.observation_dim, arch.action_dim, &mut rng);
    batch.images = rendered_like_images(samples, &mut rng);
    let rows: Vec<usize> = (0..samples).collect();
    let ids = model.param_ids();
    let loss = |model: &VisionActorCritic| minibatch_loss(model, batch.minibatch(&rows, None, device), config).0;
    let force = |model: &VisionActorCritic| drop(model.log_std.val().into_data());
    let (forward, backward, optimizer) = time_steps(learner, model, &ids, repeats, loss, force);
    let flops = 2.0 * 3.0 * (VisionActorCritic::macs_per_sample(arch) * samples) as f64;
    StepTiming { forward, backward, optimizer, gflops: flops / (forward + backward) / 1e9 }
}

/// The gradient of one minibatch loss on `samples` random samples — the MLP agent's, or with
/// `vision` the CNN agent's on random images — every parameter's values in order: what the
/// matrix kernels this CPU runs compute, for comparing them with another CPU's (tests/kernels.rs).
pub fn gradient(learner: &LearnerConfig, samples: usize, vision: bool, device: &Device) -> Vec<f32> {
    let arch = &learner.architecture;
    let config = &learner.ppo;
    let mut rng = ChaCha8Rng::seed_from_u64(0);
    let mut batch = gaussian_batch(samples, arch.observation_dim, arch.action_dim, &mut rng);
    let rows: Vec<usize> = (0..samples).collect();
    fn of<N: PpoNetwork + Module>(model: &N, batch: &TrainingBatch, rows: &[usize], config: &PpoConfig, device: &Device) -> Vec<f32> {
        let grads = minibatch_loss(model, batch.minibatch(rows, None, device), config).0.backward();
        flat_gradients(&GradientsParams::from_grads(grads, model), &model.param_ids())
    }
    if vision {
        batch.images = rendered_like_images(samples, &mut rng);
        of(&VisionActorCritic::new(arch, config.initial_log_std, 0, device), &batch, &rows, config, device)
    } else {
        of(&ActorCritic::new(arch, config.initial_log_std, 0, device), &batch, &rows, config, device)
    }
}
