//! Acting with a policy: batched sampling for actors, the deterministic mean for evaluation
//! (state-based, and vision-based with the camera rendered every step).

use std::sync::Arc;

use burn::module::Module;
use burn::tensor::{Device, Tensor, TensorData};
use rand::Rng;
use rand_distr::StandardNormal;
use sim::camera::IMAGE_PIXELS;
use sim::{Controller, RaceEnv};

use policyfile::{BlobError, ObsNormalizer, WeightsBlob};

use crate::models::NetworkBlob;
use crate::network::ActorCritic;
use crate::vision::{VisionActorCritic, image_tensor};

/// ln(2π) / 2, the normalising constant of a Gaussian log-density per dimension.
pub const HALF_LN_2PI: f64 = 0.918_938_533_204_672_8;

/// Log-density of `action` under a diagonal Gaussian (summed over dimensions).
pub fn gaussian_log_prob(action: &[f32], mean: &[f32], log_std: &[f32]) -> f32 {
    action
        .iter()
        .zip(mean)
        .zip(log_std)
        .map(|((a, m), s)| {
            let z = (a - m) / s.exp();
            -0.5 * z * z - s - HALF_LN_2PI as f32
        })
        .sum()
}

/// What an actor needs from one batched inference.
#[derive(Clone, Debug, PartialEq)]
pub struct Acting {
    /// Sampled actions, unclipped (`n × action_dim`); the environment clips them.
    pub actions: Vec<f32>,
    /// Log-probabilities of the unclipped samples.
    pub log_probs: Vec<f32>,
    /// State values.
    pub values: Vec<f32>,
}

/// A policy ready for inference: network in validation mode, frozen normaliser, version.
#[derive(Debug)]
pub struct Policy {
    model: ActorCritic,
    normalizer: ObsNormalizer,
    log_std: Vec<f32>,
    version: u64,
    layout: sim::ObservationLayout,
    device: Device,
}

impl Policy {
    /// Loads a blob onto the CPU device.
    pub fn from_blob(blob: &WeightsBlob) -> Result<Self, BlobError> {
        let device = Device::flex();
        let model = blob.model(&device)?.valid();
        let log_std = blob.params.last().map(|p| p.values.clone()).unwrap_or_default();
        let layout = blob.architecture.observation;
        Ok(Self { model, normalizer: blob.normalizer.clone(), log_std, version: blob.version, layout, device })
    }

    /// Policy version this was built from.
    pub fn version(&self) -> u64 {
        self.version
    }

    /// What the observations this policy reads hold, and in which frame.
    pub fn observation_layout(&self) -> sim::ObservationLayout {
        self.layout
    }

    /// Length of a raw observation.
    pub fn observation_dim(&self) -> usize {
        self.normalizer.dim()
    }

    /// Action dimension.
    pub fn action_dim(&self) -> usize {
        self.log_std.len()
    }

    /// Action means and values of raw observations (`n × obs_dim`).
    pub fn means_and_values(&self, raw: &[f32]) -> (Vec<f32>, Vec<f32>) {
        let (mean, value) = self.model.forward(self.normalized(raw));
        (float_values(mean.into_data()), float_values(value.into_data()))
    }

    /// The deterministic actions evaluation takes for raw observations (`n × obs_dim`): the
    /// action means clipped to [-1, 1]. The actor alone: flying needs no value, and the critic
    /// was half of every evaluation step's products.
    pub fn deterministic_actions(&self, raw: &[f32]) -> Vec<f32> {
        let means = float_values(self.model.action_means(self.normalized(raw)).into_data());
        means.into_iter().map(|a| a.clamp(-1.0, 1.0)).collect()
    }

    /// Raw observations (`n × obs_dim`) normalised, as a tensor.
    fn normalized(&self, raw: &[f32]) -> Tensor<2> {
        normalized(&self.normalizer, raw, &self.device)
    }

    /// Samples actions for a batch, with their log-probabilities and the values.
    pub fn act(&self, raw: &[f32], rng: &mut impl Rng) -> Acting {
        let (means, values) = self.means_and_values(raw);
        sample(&means, values, &self.log_std, rng)
    }
}

/// Raw observations (rows of `normalizer.dim()`) normalised by `normalizer`, as a tensor on
/// `device`: what both kinds of policy feed their networks' state inputs.
fn normalized(normalizer: &ObsNormalizer, raw: &[f32], device: &Device) -> Tensor<2> {
    let dim = normalizer.dim();
    let mut normalized = vec![0.0; raw.len()];
    normalizer.normalize(raw, &mut normalized);
    Tensor::<2>::from_data(TensorData::new(normalized, [raw.len() / dim, dim]), device)
}

/// The values of an output tensor's data: the networks compute in f32.
#[allow(clippy::expect_used, reason = "the networks' outputs are f32")]
fn float_values(data: TensorData) -> Vec<f32> {
    data.try_into_vec::<f32>().expect("float outputs")
}

/// Samples around action means `means` (rows of `log_std.len()`) with the state-independent
/// standard deviation `exp(log_std)`: the unclipped actions and their log-probabilities.
fn sample(means: &[f32], values: Vec<f32>, log_std: &[f32], rng: &mut impl Rng) -> Acting {
    let dim = log_std.len();
    let mut actions = means.to_vec();
    for (i, a) in actions.iter_mut().enumerate() {
        let eps: f32 = rng.sample(StandardNormal);
        *a += log_std[i % dim].exp() * eps;
    }
    let log_probs = actions.chunks(dim).zip(means.chunks(dim)).map(|(a, m)| gaussian_log_prob(a, m, log_std)).collect();
    Acting { actions, log_probs, values }
}

/// Flies a [`RaceEnv`] with a policy's deterministic mean action (evaluation).
pub struct PolicyController {
    policy: Arc<Policy>,
}

impl PolicyController {
    /// A controller sharing `policy`.
    pub fn new(policy: Arc<Policy>) -> Self {
        Self { policy }
    }
}

impl Controller for PolicyController {
    fn reset(&mut self, _env: &RaceEnv) {}

    fn act(&mut self, env: &RaceEnv) -> [f32; 4] {
        let action = self.policy.deterministic_actions(&env.observation_in(self.policy.observation_layout()));
        std::array::from_fn(|i| action[i])
    }
}

/// A vision policy ready for evaluation: the CNN actor-critic in validation mode, the frozen
/// normaliser of its state observations, its frame and version.
#[derive(Debug)]
pub struct VisionPolicy {
    model: VisionActorCritic,
    normalizer: ObsNormalizer,
    log_std: Vec<f32>,
    layout: sim::ObservationLayout,
    version: u64,
    device: Device,
}

impl VisionPolicy {
    /// Loads a vision blob onto the CPU device (a state-based blob is refused).
    pub fn from_blob(blob: &WeightsBlob) -> Result<Self, BlobError> {
        let device = Device::flex();
        let model = blob.vision_model(&device)?.valid();
        let log_std = blob.params.last().map(|p| p.values.clone()).unwrap_or_default();
        let layout = blob.architecture.observation;
        Ok(Self { model, normalizer: blob.normalizer.clone(), log_std, layout, version: blob.version, device })
    }

    /// Policy version this was built from.
    pub fn version(&self) -> u64 {
        self.version
    }

    /// What the state observations this policy reads hold, and in which frame.
    pub fn observation_layout(&self) -> sim::ObservationLayout {
        self.layout
    }

    /// Action means of a batch: `n` camera images (`n × 84 × 84` bytes, as the renderer writes
    /// them) and their raw state observations (`n × 40`,
    /// in the policy's frame; their proprioceptive part feeds the actor), one row of means per
    /// observation.
    pub fn mean_actions(&self, images: &[u8], raw_states: &[f32]) -> Vec<f32> {
        let (images, states) = self.inputs(images, raw_states);
        float_values(self.model.actor_mean(images, states).into_data())
    }

    /// The deterministic actions evaluation takes (as [`Policy::deterministic_actions`]): the
    /// action means of [`VisionPolicy::mean_actions`] clipped to [-1, 1].
    pub fn deterministic_actions(&self, images: &[u8], raw_states: &[f32]) -> Vec<f32> {
        self.mean_actions(images, raw_states).into_iter().map(|a| a.clamp(-1.0, 1.0)).collect()
    }

    /// The critic's values of raw state observations (`n × 40`): it reads the state only.
    pub fn values(&self, raw_states: &[f32]) -> Vec<f32> {
        let states = self.states(raw_states);
        float_values(self.model.critic.forward(states).into_data())
    }

    /// Samples actions for a batch of images and raw states, with log-probabilities and values.
    pub fn act(&self, images: &[u8], raw_states: &[f32], rng: &mut impl Rng) -> Acting {
        let (images, states) = self.inputs(images, raw_states);
        let (means, values) = self.model.forward(images, states);
        let means = float_values(means.into_data());
        sample(&means, float_values(values.into_data()), &self.log_std, rng)
    }

    /// Normalised states `[n, 40]` of raw ones.
    fn states(&self, raw_states: &[f32]) -> Tensor<2> {
        normalized(&self.normalizer, raw_states, &self.device)
    }

    /// The network's inputs: images `[n, 1, 84, 84]` in [0, 1] and normalised states.
    fn inputs(&self, images: &[u8], raw_states: &[f32]) -> (Tensor<4>, Tensor<2>) {
        let n = raw_states.len() / self.normalizer.dim();
        assert_eq!(images.len(), n * IMAGE_PIXELS, "one camera image per state row");
        (image_tensor(images, &self.device), self.states(raw_states))
    }
}

/// The policy an actor samples from, whichever agent the weights hold: the state-based one
/// reads the state observation, the vision one the camera image and the state's
/// proprioceptive part; both critics read the state.
#[derive(Debug)]
pub enum ActingPolicy {
    /// State-based (boxed, as the vision one: the two differ much in size).
    State(Box<Policy>),
    /// Vision-based.
    Vision(Box<VisionPolicy>),
}

impl ActingPolicy {
    /// The policy of `blob`, by the agent it records.
    pub fn from_blob(blob: &WeightsBlob) -> Result<Self, BlobError> {
        Ok(match blob.architecture.agent {
            crate::Agent::State => Self::State(Box::new(Policy::from_blob(blob)?)),
            crate::Agent::Vision => Self::Vision(Box::new(VisionPolicy::from_blob(blob)?)),
        })
    }

    /// Policy version.
    pub fn version(&self) -> u64 {
        match self {
            Self::State(p) => p.version(),
            Self::Vision(p) => p.version(),
        }
    }

    /// What the state observations it reads hold, and in which frame.
    pub fn observation_layout(&self) -> sim::ObservationLayout {
        match self {
            Self::State(p) => p.observation_layout(),
            Self::Vision(p) => p.observation_layout(),
        }
    }

    /// True when it acts on camera images.
    pub fn sees_images(&self) -> bool {
        matches!(self, Self::Vision(_))
    }

    /// Samples actions for raw state observations (`n × 40`) and, for a vision policy, their
    /// camera images (`n × 84 × 84`; ignored by a state-based one).
    pub fn act(&self, raw_states: &[f32], images: &[u8], rng: &mut impl Rng) -> Acting {
        match self {
            Self::State(p) => p.act(raw_states, rng),
            Self::Vision(p) => p.act(images, raw_states, rng),
        }
    }

    /// Deterministic actions (means clipped to [-1, 1], as in evaluation) for raw state
    /// observations and, for a vision policy, their camera images.
    pub fn deterministic_actions(&self, raw_states: &[f32], images: &[u8]) -> Vec<f32> {
        match self {
            Self::State(p) => p.deterministic_actions(raw_states),
            Self::Vision(p) => p.deterministic_actions(images, raw_states),
        }
    }

    /// The critic's values of raw state observations.
    pub fn values(&self, raw_states: &[f32]) -> Vec<f32> {
        match self {
            Self::State(p) => p.means_and_values(raw_states).1,
            Self::Vision(p) => p.values(raw_states),
        }
    }
}

/// Flies a [`RaceEnv`] with a vision policy's deterministic mean action: renders the camera
/// every step (SPEC §5), as evaluation of a vision agent needs.
pub struct VisionPolicyController {
    policy: Arc<VisionPolicy>,
    image: Vec<u8>,
}

impl VisionPolicyController {
    /// A controller sharing `policy`.
    pub fn new(policy: Arc<VisionPolicy>) -> Self {
        Self { policy, image: vec![0; IMAGE_PIXELS] }
    }
}

impl Controller for VisionPolicyController {
    fn reset(&mut self, _: &RaceEnv) {}

    fn act(&mut self, env: &RaceEnv) -> [f32; 4] {
        env.render_camera(&mut self.image);
        let action = self.policy.deterministic_actions(&self.image, &env.observation_in(self.policy.layout));
        std::array::from_fn(|i| action[i])
    }
}

/// Makes a fresh evaluation controller per deployment (evaluation runs them in parallel).
pub type ControllerFactory = Box<dyn Fn() -> Box<dyn Controller> + Sync>;

/// Controllers flying `blob`'s deterministic policy, whichever agent it holds: the state-based
/// one reads the state observation, the vision-based one renders its camera every step.
pub fn controller_factory(blob: &WeightsBlob) -> Result<ControllerFactory, BlobError> {
    Ok(match blob.architecture.agent {
        crate::Agent::State => {
            let policy = Arc::new(Policy::from_blob(blob)?);
            Box::new(move || Box::new(PolicyController::new(policy.clone())))
        }
        crate::Agent::Vision => {
            let policy = Arc::new(VisionPolicy::from_blob(blob)?);
            Box::new(move || Box::new(VisionPolicyController::new(policy.clone())))
        }
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use policyfile::architecture::Architecture;
    use rand::SeedableRng;

    #[test]
    fn gaussian_log_prob_matches_the_closed_form() {
        // One dimension, σ = e^{-0.5}: log N(0.3; 0.1, σ) by hand.
        let sigma = (-0.5f64).exp();
        let z = (0.3 - 0.1) / sigma;
        let expected = -0.5 * z * z - (-0.5) - 0.5 * (2.0 * std::f64::consts::PI).ln();
        let got = gaussian_log_prob(&[0.3], &[0.1], &[-0.5]);
        assert!((f64::from(got) - expected).abs() < 1e-6);
    }

    #[test]
    fn acting_is_seeded_and_centred_on_the_mean() {
        let arch = Architecture { hidden: vec![16, 16], ..Architecture::paper() };
        let blob = WeightsBlob::from_model(3, &arch, &ObsNormalizer::new(40), &ActorCritic::new(&arch, -0.5, 1, &Device::flex()));
        let policy = Policy::from_blob(&blob).unwrap();
        let obs = vec![0.2f32; 40 * 64];
        let a = policy.act(&obs, &mut rand_chacha::ChaCha8Rng::seed_from_u64(1));
        let b = policy.act(&obs, &mut rand_chacha::ChaCha8Rng::seed_from_u64(1));
        assert_eq!(a, b);
        let (means, values) = policy.means_and_values(&obs);
        assert_eq!((a.actions.len(), a.log_probs.len(), values.len()), (256, 64, 64));
        let spread: f32 = a.actions.iter().zip(&means).map(|(x, m)| (x - m).powi(2)).sum::<f32>() / 256.0;
        // Sample variance of N(0, e^{-1}) over 256 draws: within a loose band of e^{-1} ≈ 0.37.
        assert!((0.25..0.5).contains(&spread), "{spread}");
        assert_eq!(policy.version(), 3);
    }
}
