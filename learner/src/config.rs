//! PPO hyperparameters (SPEC §10, Stable-Baselines3 names) and the named profiles.

use policy::Architecture;
use serde::{Deserialize, Serialize};

/// PPO hyperparameters; `Default` is the state-based column of SPEC §10.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct PpoConfig {
    /// Steps per environment per iteration (SB3 `n_steps`). 250.
    pub n_steps: usize,
    /// Minibatch size (SB3 `batch_size`); larger than the rollout means the whole rollout. 28000.
    pub batch_size: usize,
    /// Passes over the rollout per iteration. 10.
    pub n_epochs: usize,
    /// Discount γ. 0.995.
    pub gamma: f64,
    /// GAE λ. 0.95.
    pub gae_lambda: f64,
    /// Clip range ε of the surrogate. 0.2.
    pub clip_range: f64,
    /// Value-loss coefficient. 0.5.
    pub vf_coef: f64,
    /// Entropy coefficient: the loss subtracts this times the policy's entropy, which keeps the
    /// exploration noise from narrowing. 0.
    pub ent_coef: f64,
    /// Gradient-norm limit. 0.5.
    pub max_grad_norm: f64,
    /// Learning rate at the start of the run. 3e-4.
    pub learning_rate_start: f64,
    /// Learning rate at the end of the run (linear in between). 1e-5.
    pub learning_rate_end: f64,
    /// L2 weight decay added to the gradient (torch Adam style). 1e-5.
    pub weight_decay: f64,
    /// Adam ε. 1e-5.
    pub adam_epsilon: f64,
    /// Initial log standard deviation of the policy. -0.5.
    pub initial_log_std: f64,
    /// Iterations at the start of a run in which only the value function learns: the actor
    /// and log std take no step. For a run that starts from a distilled student with a fresh
    /// critic, whose first advantages would otherwise be noise that unlearns the imitation.
    /// Default 0.
    pub critic_warmup_iterations: u64,
    /// Weight of the mirror-symmetry term ([`crate::ppo::MirrorTerm`]): the KL divergence between
    /// the policy's actions on mirrored observations and its mirrored actions. Beyond the
    /// thesis: 0 (off) in SPEC's columns, 1 in the cpu profile (docs/notebook/generalist.md).
    pub mirror_coef: f64,
    /// Share of each minibatch's rows the mirror term is taken on, in (0, 1]: its extra actor
    /// pass costs this share of a full one. 1 (every row); 0.25 in the cpu profile.
    pub mirror_fraction: f64,
    /// Vision agent only: which of its image layers take no step in PPO (`nothing`, the
    /// `convolutions`, or the whole `encoder`: convolutions and embedding layer). Their outputs
    /// are computed once per iteration and the epochs train the rest on them — PPO on top of a
    /// distilled student's perception, at a fraction of the full CNN step's cost. Beyond the
    /// thesis; `nothing` by default, and left out of files then.
    #[serde(skip_serializing_if = "Frozen::is_nothing")]
    pub frozen: Frozen,
}

/// The vision agent's layers a PPO update leaves as they are ([`PpoConfig::frozen`]).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Frozen {
    /// Every layer trains (SPEC).
    #[default]
    Nothing,
    /// The three convolutions; the embedding layer, actor, critic and log std train.
    Convolutions,
    /// The convolutions and the embedding layer; actor, critic and log std train.
    Encoder,
}

impl Frozen {
    /// True for [`Frozen::Nothing`], the default.
    pub fn is_nothing(&self) -> bool {
        *self == Self::Nothing
    }

    /// Width of the frozen layers' output per sample, which the update computes once; `None`
    /// when nothing is frozen.
    pub fn output_width(&self) -> Option<usize> {
        match self {
            Self::Nothing => None,
            Self::Convolutions => Some(policy::vision::CONV_OUTPUT),
            Self::Encoder => Some(policy::vision::EMBEDDING),
        }
    }
}

impl Default for PpoConfig {
    fn default() -> Self {
        Self {
            n_steps: 250,
            batch_size: 28_000,
            n_epochs: 10,
            gamma: 0.995,
            gae_lambda: 0.95,
            clip_range: 0.2,
            vf_coef: 0.5,
            ent_coef: 0.0,
            max_grad_norm: 0.5,
            learning_rate_start: 3e-4,
            learning_rate_end: 1e-5,
            weight_decay: 1e-5,
            adam_epsilon: 1e-5,
            initial_log_std: -0.5,
            critic_warmup_iterations: 0,
            mirror_coef: 0.0,
            mirror_fraction: 1.0,
            frozen: Frozen::Nothing,
        }
    }
}

/// A PPO setting outside its range, named as in a run config (`ppo.gamma`, …).
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
#[error("ppo.{field}: {reason}")]
pub struct InvalidPpoConfig {
    /// The setting.
    pub field: &'static str,
    /// What is wrong with its value.
    pub reason: String,
}

impl PpoConfig {
    /// Every number in its range, or the first that is not: a value outside would panic or
    /// make every update non-finite.
    pub fn check(&self) -> Result<(), InvalidPpoConfig> {
        let ranges: [(&'static str, f64, f64, f64); 12] = [
            ("gamma", self.gamma, 0.0, 1.0),
            ("gae_lambda", self.gae_lambda, 0.0, 1.0),
            ("clip_range", self.clip_range, 1e-6, 1.0),
            ("vf_coef", self.vf_coef, 0.0, 1e6),
            ("ent_coef", self.ent_coef, 0.0, 1e6),
            ("max_grad_norm", self.max_grad_norm, 1e-9, 1e9),
            ("learning_rate_start", self.learning_rate_start, 0.0, 1.0),
            ("learning_rate_end", self.learning_rate_end, 0.0, 1.0),
            ("weight_decay", self.weight_decay, 0.0, 1.0),
            ("adam_epsilon", self.adam_epsilon, 1e-12, 1.0),
            ("initial_log_std", self.initial_log_std, -20.0, 5.0),
            ("mirror_fraction", self.mirror_fraction, 1e-6, 1.0),
        ];
        for (name, value, low, high) in ranges {
            if !(value.is_finite() && (low..=high).contains(&value)) {
                return Err(InvalidPpoConfig { field: name, reason: format!("{value} is outside {low}..={high}") });
            }
        }
        for (name, value) in [("n_steps", self.n_steps), ("batch_size", self.batch_size), ("n_epochs", self.n_epochs)] {
            if value == 0 {
                return Err(InvalidPpoConfig { field: name, reason: "must be ≥ 1".into() });
            }
        }
        Ok(())
    }

    /// The vision-based column of SPEC §10: initial log std 0, learning rate 2e-4 → 1e-5,
    /// minibatch 24,000, 4 epochs; the rest as the state-based column.
    pub fn vision_based() -> Self {
        Self { batch_size: 24_000, n_epochs: 4, learning_rate_start: 2e-4, initial_log_std: 0.0, ..Self::default() }
    }

    /// Learning rate once `progress` ∈ [0, 1] of the run's environment steps are done.
    pub fn learning_rate(&self, progress: f64) -> f64 {
        let p = progress.clamp(0.0, 1.0);
        self.learning_rate_start + (self.learning_rate_end - self.learning_rate_start) * p
    }
}

impl PpoConfig {
    /// The project's state-based recipe: SPEC's column with γ = 0.998 (a crash costs the ~8 s of
    /// progress after it, not ~4 s: SPEC §9 scores 20 s flights) and the mirror-symmetry term at
    /// weight 1 (every policy trained without it flies a manoeuvre and its mirror image
    /// differently; with it, unseen tracks are flown more often) taken on a quarter of each
    /// minibatch (the same validation score over four seeds, 1.24× the whole run's speed:
    /// experiments/mirror-fraction.toml). A run config's `[ppo]` table starts from it under
    /// every profile; the thesis as written sets `gamma = 0.995` and `mirror_coef = 0`.
    pub fn recipe() -> Self {
        Self { gamma: 0.998, mirror_coef: 1.0, mirror_fraction: 0.25, ..Self::default() }
    }
}

/// A named size of run: network widths, environments and how the rollout is cut into
/// minibatches. Only sizes: the algorithm (γ, the mirror term, learning rates) is the run
/// config's `[ppo]` table, the same under every profile.
#[derive(Clone, Debug, PartialEq)]
pub struct Profile {
    /// Name.
    pub name: &'static str,
    /// Network shape (hidden widths; the observation layout is the run's).
    pub architecture: Architecture,
    /// Parallel environments.
    pub envs: usize,
    /// Minibatch size.
    pub batch_size: usize,
    /// Passes over the rollout per iteration.
    pub n_epochs: usize,
}

impl Profile {
    /// The thesis' sizes: 512×512 networks, 96 environments, minibatches of 28,000 over 10
    /// epochs (SPEC §10).
    pub fn paper() -> Self {
        let spec = PpoConfig::default();
        Self { name: "paper", architecture: Architecture::paper(), envs: 96, batch_size: spec.batch_size, n_epochs: spec.n_epochs }
    }

    /// For a 2-core CPU: 256×256 networks and 4000-sample minibatches over 5 epochs (more,
    /// cheaper gradient steps per collected sample); the rest as the paper.
    pub fn cpu() -> Self {
        Self { name: "cpu", architecture: Architecture::cpu(), batch_size: 4000, n_epochs: 5, ..Self::paper() }
    }

    /// A profile by name.
    pub fn named(name: &str) -> Option<Self> {
        match name {
            "paper" => Some(Self::paper()),
            "cpu" => Some(Self::cpu()),
            _ => None,
        }
    }

    /// `ppo` cut into this profile's minibatches.
    pub fn sized(&self, ppo: PpoConfig) -> PpoConfig {
        PpoConfig { batch_size: self.batch_size, n_epochs: self.n_epochs, ..ppo }
    }

    /// The learner a run of this size trains by default: [`PpoConfig::recipe`] in this
    /// profile's minibatches.
    pub fn default_learner(&self) -> LearnerConfig {
        self.learner_config(self.sized(PpoConfig::recipe()))
    }

    /// What a learner of this size trains with `ppo` (already sized, or set by the run).
    pub fn learner_config(&self, ppo: PpoConfig) -> LearnerConfig {
        LearnerConfig { architecture: self.architecture.clone(), ppo, envs: self.envs }
    }
}

/// Everything a learner trains with: the network, the PPO settings and the environments whose
/// rollouts each iteration takes. Saved with every checkpoint.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct LearnerConfig {
    /// Network shape.
    pub architecture: Architecture,
    /// PPO settings.
    pub ppo: PpoConfig,
    /// Parallel environments.
    pub envs: usize,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn profiles_differ_in_sizes_only() {
        let (cpu, paper) = (Profile::cpu().sized(PpoConfig::recipe()), Profile::paper().sized(PpoConfig::recipe()));
        assert_eq!((cpu.batch_size, cpu.n_epochs, paper.batch_size, paper.n_epochs), (4000, 5, 28_000, 10));
        assert_eq!(PpoConfig { batch_size: 0, n_epochs: 0, ..cpu }, PpoConfig { batch_size: 0, n_epochs: 0, ..paper });
        assert_eq!(Profile::paper().sized(PpoConfig::default()), PpoConfig::default(), "the paper's sizes are SPEC's");
    }

    #[test]
    fn learning_rate_falls_linearly_from_start_to_end() {
        let c = PpoConfig::default();
        assert_eq!(c.learning_rate(0.0), 3e-4);
        assert!((c.learning_rate(0.5) - (3e-4 + 1e-5) / 2.0).abs() < 1e-15);
        assert!((c.learning_rate(1.0) - 1e-5).abs() < 1e-18);
        assert!((c.learning_rate(7.0) - 1e-5).abs() < 1e-18, "clamped after the end");
    }
}
