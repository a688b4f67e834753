//! An imitation term in the PPO loss: the squared error between the policy's action means and
//! a teacher's actions on a fixed set of labelled states (the warm start's DAgger data set),
//! weighted by a coefficient the learner anneals. PPO fine-tuning from an imitation otherwise
//! drifts away from it before the critic can tell which changes pay (Rajeswaran et al. 2018,
//! DAPG, add the same term with a decaying weight).

use burn::tensor::{Device, Tensor, TensorData};
use policy::ObsNormalizer;
use rand_chacha::ChaCha8Rng;

/// Labelled states: raw observations (`n × obs_dim`) and the teacher's actions (`n × act_dim`).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct ImitationSet {
    states: Vec<f32>,
    labels: Vec<f32>,
    obs_dim: usize,
    action_dim: usize,
}

impl ImitationSet {
    /// The set of `states` rows of `obs_dim` numbers labelled with `labels` rows of
    /// `action_dim`; errors say what does not fit.
    pub fn new(states: Vec<f32>, labels: Vec<f32>, obs_dim: usize, action_dim: usize) -> Result<Self, String> {
        let n = states.len() / obs_dim.max(1);
        if obs_dim == 0 || action_dim == 0 || n == 0 || states.len() != n * obs_dim || labels.len() != n * action_dim {
            return Err(format!(
                "{} state numbers of width {obs_dim} and {} labels of width {action_dim} do not make whole, matching rows",
                states.len(),
                labels.len()
            ));
        }
        Ok(Self { states, labels, obs_dim, action_dim })
    }

    /// Labelled states held.
    pub fn len(&self) -> usize {
        self.states.len() / self.obs_dim.max(1)
    }

    /// True when the set holds nothing.
    pub fn is_empty(&self) -> bool {
        self.states.is_empty()
    }

    /// Width of a state row.
    pub fn obs_dim(&self) -> usize {
        self.obs_dim
    }

    /// `size` rows drawn at random (without replacement), their states normalised by
    /// `normalizer`: `[size, obs_dim]` states and `[size, action_dim]` labels on `device`.
    pub fn minibatch(&self, size: usize, normalizer: &ObsNormalizer, rng: &mut ChaCha8Rng, device: &Device) -> (Tensor<2>, Tensor<2>) {
        let size = size.min(self.len());
        let rows = rand::seq::index::sample(rng, self.len(), size);
        let (mut raw, mut labels) = (Vec::with_capacity(size * self.obs_dim), Vec::with_capacity(size * self.action_dim));
        for r in rows.iter() {
            raw.extend_from_slice(&self.states[r * self.obs_dim..(r + 1) * self.obs_dim]);
            labels.extend_from_slice(&self.labels[r * self.action_dim..(r + 1) * self.action_dim]);
        }
        let mut states = vec![0.0; raw.len()];
        normalizer.normalize(&raw, &mut states);
        (
            Tensor::from_data(TensorData::new(states, [size, self.obs_dim]), device),
            Tensor::from_data(TensorData::new(labels, [size, self.action_dim]), device),
        )
    }
}

/// What one update needs to add the term: the set, the normaliser the policy reads its states
/// with, and this update's weight.
#[derive(Clone, Copy, Debug)]
pub struct ImitationTerm<'a> {
    /// The labelled states.
    pub set: &'a ImitationSet,
    /// The policy's normaliser.
    pub normalizer: &'a ObsNormalizer,
    /// Weight of the squared error in the loss.
    pub weight: f64,
}
