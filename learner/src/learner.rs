//! The learner: turns rollout chunks of its current policy version into the next version.

use burn::module::Module;
use burn::optim::ModuleOptimizer;
use burn::tensor::{Bytes, Device};
use policy::NetworkBlob;
use policy::{ActorCritic, Agent, Architecture, ObsNormalizer, VisionActorCritic, WeightsBlob};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rollout::RolloutChunk;
use serde::{Deserialize, Serialize};

use crate::adam::FusedAdam;
use crate::config::LearnerConfig;
use crate::ppo::{GaeInput, MirrorTerm, TrainingBatch, UpdateStats, UpdateStep, gae, update};

/// A batch of chunks the learner refuses.
#[derive(Debug, thiserror::Error)]
pub enum LearnerError {
    /// A chunk's arrays do not have the lengths its header promises, or hold numbers no
    /// healthy run makes.
    #[error("malformed rollout chunk: {0}")]
    Malformed(#[from] rollout::RolloutCheckError),
    /// No chunks.
    #[error("no rollout chunks to learn from")]
    Empty,
    /// Saved learner state could not be restored.
    #[error("learner state: {0}")]
    State(String),
    /// A checkpoint lacks a section or holds a malformed one.
    #[error(transparent)]
    Checkpoint(#[from] crate::checkpoint::CheckpointError),
}

/// What one iteration did.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct IterationReport {
    /// Policy version produced.
    pub version: u64,
    /// Environment steps learned from so far.
    pub env_steps: u64,
    /// Learning rate used.
    pub learning_rate: f64,
    /// Losses and diagnostics.
    pub stats: UpdateStats,
    /// Why the update was refused and rolled back (non-finite or exploding), if it was: the
    /// weights of this version are the previous version's, and the batch was not learned from.
    #[serde(default)]
    pub refused_update: Option<String>,
}

/// Counters and random state saved with a checkpoint.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
struct Counters {
    version: u64,
    env_steps: u64,
    total_env_steps: u64,
    /// Named `profile` in checkpoints written before the profile held only sizes.
    #[serde(alias = "profile")]
    config: LearnerConfig,
    normalizer: ObsNormalizer,
    rng: ChaCha8Rng,
}

/// The network being trained, whichever agent (by PPO here, by regression in the `distill`
/// crate). Cloning is cheap: burn's tensors are reference-counted and copied on write.
#[derive(Clone)]
pub enum Network {
    /// The state-based actor-critic.
    State(ActorCritic),
    /// The vision actor-critic.
    Vision(VisionActorCritic),
}

impl Network {
    /// A fresh network of `arch`'s agent (seeded, log std `initial_log_std`).
    pub fn new(arch: &Architecture, initial_log_std: f64, seed: u64, device: &Device) -> Self {
        match arch.agent {
            Agent::State => Self::State(ActorCritic::new(arch, initial_log_std, seed, device)),
            Agent::Vision => Self::Vision(VisionActorCritic::new(arch, initial_log_std, seed, device)),
        }
    }

    /// The network in `blob`, in training mode.
    pub fn from_blob(blob: &WeightsBlob, device: &Device) -> Result<Self, policy::BlobError> {
        Ok(match blob.architecture.agent {
            Agent::State => Self::State(blob.model(device)?.train()),
            Agent::Vision => Self::Vision(blob.vision_model(device)?.train()),
        })
    }

    /// The network as a weights blob of its agent.
    pub fn blob(&self, version: u64, arch: &Architecture, normalizer: &ObsNormalizer) -> WeightsBlob {
        match self {
            Network::State(m) => WeightsBlob::from_model(version, arch, normalizer, m),
            Network::Vision(m) => WeightsBlob::from_vision_model(version, arch, normalizer, m),
        }
    }
}

/// PPO learner state: network, optimiser, normaliser, counters.
pub struct Learner {
    counters: Counters,
    device: Device,
    /// Always `Some` between calls; taken while burn's optimiser consumes and returns it.
    model: Option<Network>,
    optimizer: ModuleOptimizer,
}

impl Learner {
    /// A fresh learner for a run of `total_env_steps` (the learning-rate schedule's length).
    pub fn new(config: LearnerConfig, total_env_steps: u64, seed: u64) -> Self {
        let device = Device::flex().autodiff();
        let model = Some(Network::new(&config.architecture, config.ppo.initial_log_std, seed, &device));
        let counters = Counters {
            version: 0,
            env_steps: 0,
            total_env_steps,
            normalizer: ObsNormalizer::new(config.architecture.observation_dim),
            rng: ChaCha8Rng::seed_from_u64(seed ^ 0x5050_4f00),
            config,
        };
        let optimizer = adam(&counters.config);
        Self { counters, device, model, optimizer }
    }

    /// A fresh learner (version 0, new optimiser) whose network and normaliser start from a
    /// trained policy: fine-tuning, e.g. the generalist on one track (thesis §3.4.4). The
    /// fine-tune may change `gate_sight`: the gate corners mean the same, only when they are
    /// shown changes. A vision actor that reads its previous action keeps reading it.
    pub fn from_policy(config: LearnerConfig, total_env_steps: u64, seed: u64, blob: &WeightsBlob) -> Result<Self, LearnerError> {
        // Whether a vision actor reads its previous action is the policy's own (a distilled
        // student's): the environments write that action either way.
        let mut config = config;
        config.architecture.vision_previous_action = blob.architecture.vision_previous_action;
        let mut expected = config.architecture.clone();
        expected.observation.gate_sight = blob.architecture.observation.gate_sight;
        blob.check_architecture(&expected).map_err(|e| LearnerError::State(e.to_string()))?;
        let mut learner = Self::new(config, total_env_steps, seed);
        learner.model = Some(Network::from_blob(blob, &learner.device).map_err(|e| LearnerError::State(e.to_string()))?);
        learner.counters.normalizer = blob.normalizer.clone();
        // `new`'s optimiser holds no moments yet, so it starts afresh for the imported ids.
        Ok(learner)
    }

    /// Current policy version (number of updates so far).
    pub fn version(&self) -> u64 {
        self.counters.version
    }

    /// Environment steps learned from.
    pub fn env_steps(&self) -> u64 {
        self.counters.env_steps
    }

    /// What this learner trains with.
    pub fn config(&self) -> &LearnerConfig {
        &self.counters.config
    }

    /// Weights of the current version, for actors and checkpoints.
    #[allow(clippy::expect_used, reason = "the model is present between calls")]
    pub fn weights(&self) -> WeightsBlob {
        let c = &self.counters;
        self.model.as_ref().expect("the model is present between calls").blob(c.version, &c.config.architecture, &c.normalizer)
    }

    /// One PPO iteration on admitted chunks (their versions were checked where they arrived,
    /// at the link; older versions are fine: the stored log-probabilities make the importance
    /// ratios right). Array lengths are checked here, since the batch is indexed by them.
    #[allow(clippy::expect_used, reason = "the model is present between calls")]
    pub fn train(&mut self, chunks: &[RolloutChunk]) -> Result<IterationReport, LearnerError> {
        if chunks.is_empty() {
            return Err(LearnerError::Empty);
        }
        let ppo = self.counters.config.ppo;
        let mut batch = TrainingBatch::default();
        let mut transitions = 0;
        for chunk in chunks {
            self.check(chunk)?;
            let advantages = gae(
                &GaeInput {
                    envs: chunk.envs,
                    rewards: &chunk.rewards,
                    values: &chunk.values,
                    terminated: &chunk.terminated,
                    truncated: &chunk.truncated,
                    truncation_values: &chunk.truncation_values,
                    last_values: &chunk.last_values,
                },
                ppo.gamma as f32,
                ppo.gae_lambda as f32,
            );
            // Normalise with the statistics the actors acted with (this version's).
            let mut normalized = vec![0.0; chunk.observations.len()];
            self.counters.normalizer.normalize(&chunk.observations, &mut normalized);
            batch.observations.extend(normalized);
            batch.actions.extend_from_slice(&chunk.actions);
            batch.old_log_probs.extend_from_slice(&chunk.log_probs);
            batch.old_values.extend_from_slice(&chunk.values);
            batch.advantages.extend(advantages.advantages);
            batch.returns.extend(advantages.returns);
            batch.images.extend_from_slice(&chunk.images);
            transitions += chunk.transitions();
        }
        let c = &mut self.counters;
        let progress = (c.env_steps + transitions as u64) as f64 / c.total_env_steps.max(1) as f64;
        let learning_rate = ppo.learning_rate(progress);
        let (optimizer, device) = (&mut self.optimizer, &self.device);
        // Built from this version's statistics, the ones the batch was normalised with.
        // The term off (the default) builds no mirror map at all.
        let mirror = (ppo.mirror_coef > 0.0)
            .then(|| c.config.architecture.observation.mirror())
            .flatten()
            .map(|m| MirrorTerm::new(&m, &c.normalizer, ppo.mirror_coef, &self.device).on_fraction(ppo.mirror_fraction));
        let step = UpdateStep { learning_rate, train_policy: c.version >= ppo.critic_warmup_iterations, mirror: mirror.as_ref() };
        // What a refused update rolls back to (cheap: the update copies what it writes instead
        // of writing in place while these are held).
        let kept = (self.model.clone(), optimizer.clone(), c.rng.clone());
        let (model, stats) = match self.model.take().expect("the model is present between calls") {
            Network::State(m) => {
                let (m, stats) = update(m, optimizer, &batch, &ppo, &step, &mut c.rng, device);
                (Network::State(m), stats)
            }
            Network::Vision(m) => {
                let (m, stats) = update(m, optimizer, &batch, &ppo, &step, &mut c.rng, device);
                (Network::Vision(m), stats)
            }
        };
        self.model = Some(model);
        if let Some(reason) = self.divergence(&stats) {
            (self.model, self.optimizer, self.counters.rng) = kept;
            // The same weights under the next version: synchronous actors collect again at once.
            let c = &mut self.counters;
            c.version += 1;
            return Ok(IterationReport { version: c.version, env_steps: c.env_steps, learning_rate, stats, refused_update: Some(reason) });
        }
        let c = &mut self.counters;
        for chunk in chunks {
            c.normalizer.update(&chunk.observations);
        }
        c.env_steps += transitions as u64;
        c.version += 1;
        Ok(IterationReport { version: c.version, env_steps: c.env_steps, learning_rate, stats, refused_update: None })
    }

    /// Why an update's result must not be used: a non-finite loss or gradient, or weights that
    /// are not finite or beyond [`policyfile::blob::MAX_WEIGHT`].
    fn divergence(&self, stats: &UpdateStats) -> Option<String> {
        let losses = [
            ("policy_loss", stats.policy_loss),
            ("value_loss", stats.value_loss),
            ("approx_kl", stats.approx_kl),
            ("grad_norm", stats.grad_norm),
        ];
        if let Some((name, value)) = losses.iter().find(|(_, v)| !v.is_finite()) {
            return Some(format!("{name} is {value}"));
        }
        self.weights().check_parameters().err().map(|e| e.to_string())
    }

    fn check(&self, chunk: &RolloutChunk) -> Result<(), LearnerError> {
        let arch = &self.counters.config.architecture;
        chunk.check(arch.observation_dim, arch.action_dim, arch.agent == Agent::Vision).map_err(LearnerError::Malformed)
    }

    /// A checkpoint holding [`Learner::save_state`] (sections `weights`, `optimizer`, `learner`).
    pub fn checkpoint(&self) -> crate::checkpoint::Checkpoint {
        let (weights, optimizer, learner) = self.save_state();
        let mut c = crate::checkpoint::Checkpoint::default();
        c.put("weights", weights);
        c.put("optimizer", optimizer);
        c.put("learner", learner);
        c
    }

    /// Restores a learner from a checkpoint written with [`Learner::checkpoint`].
    pub fn from_checkpoint(c: &crate::checkpoint::Checkpoint) -> Result<Self, LearnerError> {
        Self::restore_state(c.get("weights")?, c.get("optimizer")?, c.get("learner")?)
    }

    /// Restores a learner from a checkpoint of the run `config` and `total_env_steps` describe:
    /// the checkpoint must have trained the same network and PPO settings, and the learning-rate
    /// schedule follows the run's length (a run whose `total_env_steps` grew goes on decaying to
    /// the new end, which is also where the run stops).
    pub fn resume(c: &crate::checkpoint::Checkpoint, config: &LearnerConfig, total_env_steps: u64) -> Result<Self, LearnerError> {
        let mut learner = Self::from_checkpoint(c)?;
        let trained = &learner.counters.config;
        if trained.ppo != config.ppo || trained.envs != config.envs || trained.architecture.hidden != config.architecture.hidden {
            return Err(LearnerError::State(format!(
                "the checkpoint trained {:?} with {} environments and {:?}, and the run's config says {:?} with {} and {:?}: \
                 set config.toml back to the checkpoint's settings, or start a new run",
                trained.architecture.hidden, trained.envs, trained.ppo, config.architecture.hidden, config.envs, config.ppo
            )));
        }
        learner.counters.total_env_steps = total_env_steps;
        Ok(learner)
    }

    /// Everything needed to continue training exactly: weights, optimiser moments, counters.
    #[allow(clippy::expect_used, reason = "optimiser state serialises; counters serialise")]
    pub fn save_state(&self) -> (Vec<u8>, Vec<u8>, Vec<u8>) {
        let weights = self.weights().to_bytes();
        let optimizer = self.optimizer.into_bytes().expect("optimiser state serialises").to_vec();
        let counters = serde_json::to_vec(&self.counters).expect("counters serialise");
        (weights, optimizer, counters)
    }

    /// Restores [`Learner::save_state`]'s output.
    pub fn restore_state(weights: &[u8], optimizer: &[u8], counters: &[u8]) -> Result<Self, LearnerError> {
        let counters: Counters = serde_json::from_slice(counters).map_err(|e| LearnerError::State(e.to_string()))?;
        let blob = WeightsBlob::from_bytes(weights).map_err(|e| LearnerError::State(e.to_string()))?;
        blob.check_architecture(&counters.config.architecture).map_err(|e| LearnerError::State(e.to_string()))?;
        let device = Device::flex().autodiff();
        let model = Some(Network::from_blob(&blob, &device).map_err(|e| LearnerError::State(e.to_string()))?);
        let optimizer = adam(&counters.config)
            .from_bytes(Bytes::from_bytes_vec(optimizer.to_vec()))
            .map_err(|e| LearnerError::State(format!("optimiser: {e:?}")))?;
        Ok(Self { counters, device, model, optimizer })
    }
}

/// Adam with SPEC §10's ε and L2 weight decay added to the gradient (torch Adam semantics),
/// fused ([`FusedAdam`]).
pub(crate) fn adam(config: &LearnerConfig) -> ModuleOptimizer {
    let ppo = &config.ppo;
    let decay = (ppo.weight_decay > 0.0).then_some(ppo.weight_decay as f32);
    FusedAdam::new(ppo.adam_epsilon as f32, decay).init()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::{LearnerConfig, Profile};

    #[test]
    fn a_fine_tune_may_change_which_gate_corners_are_shown_and_nothing_else() {
        let mut camera = Architecture::cpu();
        camera.observation.gate_sight = sim::GateSight::Camera;
        let net = ActorCritic::new(&camera, -0.5, 7, &Device::flex());
        let blob = WeightsBlob::from_model(3, &camera, &ObsNormalizer::new(camera.observation_dim), &net);
        let profile = |architecture: Architecture| LearnerConfig { architecture, ..Profile::cpu().default_learner() };
        let mut all = camera.clone();
        all.observation.gate_sight = sim::GateSight::All;
        let learner = Learner::from_policy(profile(all.clone()), 1000, 0, &blob).unwrap();
        let tuned = learner.weights();
        assert_eq!((tuned.architecture, tuned.params.len()), (all, blob.params.len()), "the run's sight, the start's weights");
        assert!(tuned.params.iter().zip(&blob.params).all(|(a, b)| a.values == b.values));
        let wider = Architecture { hidden: vec![64, 64], ..camera };
        assert!(Learner::from_policy(profile(wider), 1000, 0, &blob).is_err(), "other shapes are still refused");
    }

    /// PPO from a distilled student: its actor keeps reading the previous action though the
    /// run's profile does not say so, and the log std it was given is the one it trains from.
    #[test]
    fn ppo_from_a_student_keeps_its_previous_action_input_and_the_log_std_it_is_given() {
        let vision = Architecture { agent: Agent::Vision, ..Architecture::cpu() };
        let net = policy::vision::VisionActorCritic::new(&vision, 0.0, 1, &Device::flex());
        let student = WeightsBlob::from_vision_model(7, &vision, &ObsNormalizer::new(vision.observation_dim), &net)
            .with_vision_previous_action()
            .unwrap()
            .with_log_std(-1.5)
            .unwrap();
        let profile = LearnerConfig { architecture: vision, ..Profile::cpu().default_learner() };
        let learner = Learner::from_policy(profile, 1000, 0, &student).unwrap();
        let weights = learner.weights();
        assert!(weights.architecture.vision_previous_action);
        assert_eq!(weights.params, student.params, "the student's parameters, its log std −1.5 among them");
        assert!(weights.params.last().unwrap().values.iter().all(|&v| v == -1.5));
        assert!(weights.vision_model(&Device::flex()).is_ok(), "the written blob reads back");
        let state_blob = WeightsBlob::from_model(
            1,
            &Architecture::cpu(),
            &ObsNormalizer::new(40),
            &ActorCritic::new(&Architecture::cpu(), -0.5, 1, &Device::flex()),
        );
        assert!(state_blob.with_log_std(-2.0).unwrap().params.last().unwrap().values == vec![-2.0; 4]);
    }

    /// A rollout whose log-probabilities made the importance ratios overflow is refused before
    /// the update, changing nothing. An update that diverges all the same (here: a learning rate
    /// of 1e7, which no config admits, blowing the weights past ±1e6) is refused: the weights,
    /// optimiser and normaliser stay the last good ones (under the next version), and training
    /// goes on from them.
    #[test]
    fn a_poisoned_update_is_rolled_back_and_training_continues_from_the_last_good_weights() {
        let profile = LearnerConfig {
            architecture: Architecture { hidden: vec![16, 16], ..Architecture::cpu() },
            ..Profile::cpu().default_learner()
        };
        let (obs, act) = (profile.architecture.observation_dim, profile.architecture.action_dim);
        let mut learner = Learner::new(profile, 100_000, 3);
        let chunk = |log_prob: f32| {
            let mut c = RolloutChunk::zeroed(0, 0, 4, 32, obs, act);
            c.observations.iter_mut().enumerate().for_each(|(i, x)| *x = ((i * 37) % 11) as f32 * 0.1 - 0.5);
            c.actions.iter_mut().enumerate().for_each(|(i, x)| *x = ((i * 13) % 7) as f32 * 0.2 - 0.6);
            c.rewards.iter_mut().enumerate().for_each(|(i, x)| *x = if i % 3 == 0 { 1.0 } else { -0.5 });
            c.log_probs.fill(log_prob);
            c
        };
        let good = learner.weights();
        let refused = learner.train(&[chunk(-1.0e9)]).unwrap_err().to_string();
        assert!(refused.contains("log_probs[0]"), "{refused}");
        assert_eq!((learner.version(), learner.weights()), (0, good.clone()), "a refused rollout changes nothing");
        let sane = learner.counters.config.ppo;
        learner.counters.config.ppo.learning_rate_start = 1e7;
        learner.counters.config.ppo.learning_rate_end = 1e7;
        let report = learner.train(&[chunk(-3.0)]).unwrap();
        let reason = report.refused_update.expect("the diverging update is refused");
        assert!(reason.contains("1e6") || reason.contains("not") || reason.contains("NaN") || reason.contains("inf"), "{reason}");
        let kept = learner.weights();
        assert_eq!(kept.params, good.params, "the weights are the last good ones");
        assert_eq!(kept.normalizer, good.normalizer, "the refused batch did not move the normaliser");
        assert_eq!((report.version, report.env_steps), (1, 0), "the next version, no steps learned");
        learner.counters.config.ppo = sane;
        let report = learner.train(&[chunk(-3.0)]).unwrap();
        assert_eq!(report.refused_update, None);
        assert_eq!((report.version, report.env_steps), (2, 128));
        assert_ne!(learner.weights().params, good.params, "training went on from them");
        assert!(learner.weights().check_parameters().is_ok());
    }
}
