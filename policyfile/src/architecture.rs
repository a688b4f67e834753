//! Network shapes and named profiles (SPEC §10).

use serde::{Deserialize, Serialize};

/// Which kind of agent a network is (SPEC §5): what its actor reads.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Agent {
    /// State-based: actor and critic read the 40-number state observation.
    #[default]
    State,
    /// Vision-based: the actor reads the camera image and proprioception through a CNN
    /// (the `policy` crate's `vision`); the critic reads the state observation.
    Vision,
}

impl std::str::FromStr for Agent {
    type Err = String;

    /// `state` or `vision`, as config files spell them.
    fn from_str(name: &str) -> Result<Self, String> {
        match name {
            "state" => Ok(Self::State),
            "vision" => Ok(Self::Vision),
            other => Err(format!("{other:?} is neither state nor vision")),
        }
    }
}

impl std::fmt::Display for Agent {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Agent::State => "state-based",
            Agent::Vision => "vision-based",
        })
    }
}

/// Shape of the actor-critic: what a weights blob must match to be loaded.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Architecture {
    /// Observation length.
    pub observation_dim: usize,
    /// Action length.
    pub action_dim: usize,
    /// Hidden layer widths, shared by actor and critic (separate networks).
    pub hidden: Vec<usize>,
    /// Negative slope of the LeakyReLU activations.
    pub negative_slope: f64,
    /// What the state observation holds; a policy is evaluated in the layout it learned.
    pub observation: sim::ObservationLayout,
    /// Kind of agent.
    pub agent: Agent,
    /// A vision actor reads its previous action after the proprioception (beyond SPEC §5): a
    /// student distilled from a state-based teacher needs it, because the teacher's labels
    /// depend on the previous action its observation holds. Left out of blobs when false.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub vision_previous_action: bool,
}

impl Architecture {
    /// The thesis' network: two hidden layers of 512 (the `paper` profile).
    pub fn paper() -> Self {
        Self {
            observation_dim: sim::STATE_OBS_DIM,
            action_dim: sim::ACTION_DIM,
            hidden: vec![512, 512],
            negative_slope: 0.01,
            observation: sim::ObservationLayout::default(),
            agent: Agent::State,
            vision_previous_action: false,
        }
    }

    /// Two hidden layers of 256: the `cpu` profile, about 4× fewer multiply-adds than the
    /// paper's. Chosen on the validation set over 128×128
    /// (docs/notebook/generalist.md, "Network size, and the 2-hour generalist at 256×256").
    pub fn cpu() -> Self {
        Self { hidden: vec![256, 256], ..Self::paper() }
    }

    /// Makes the network read observations of `layout` (`observation_dim` follows).
    pub fn set_observation_layout(&mut self, layout: sim::ObservationLayout) {
        self.observation = layout;
        self.observation_dim = layout.dim();
    }

    /// Layer widths of an MLP of this architecture's hidden layers: `inputs`, hidden…, `outputs`.
    pub fn layer_dims(&self, inputs: usize, outputs: usize) -> Vec<usize> {
        [vec![inputs], self.hidden.clone(), vec![outputs]].concat()
    }

    /// Layer widths of the state-based actor (`inputs`, hidden…, actions) and critic (…, 1).
    pub fn mlp_dims(&self) -> (Vec<usize>, Vec<usize>) {
        (self.layer_dims(self.observation_dim, self.action_dim), self.layer_dims(self.observation_dim, 1))
    }

    /// Number of trainable scalars (actor, critic and the log std).
    pub fn parameter_count(&self) -> usize {
        let mlp = |dims: Vec<usize>| dims.windows(2).map(|w| w[0] * w[1] + w[1]).sum::<usize>();
        let (actor, critic) = self.mlp_dims();
        mlp(actor) + mlp(critic) + self.action_dim
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn setting_the_layout_sets_the_observation_length() {
        let mut arch = Architecture { observation: sim::ObservationLayout::spec(sim::ObservationFrame::Heading), ..Architecture::cpu() };
        assert_eq!(arch.observation.describe(), "raw 40-number state observation in the heading frame");
        arch.set_observation_layout(sim::ObservationLayout { line_points: 4, ..arch.observation });
        let line = ", then 4 points of the reference pilot's racing line every 2.5 m of arc from its nearest point";
        assert_eq!(arch.observation.describe(), format!("raw 52-number state observation in the heading frame{line}"));
        assert_eq!(arch.observation_dim, 52);
    }

    #[test]
    fn parameter_count_of_the_paper_network() {
        // Actor 40·512+512 + 512·512+512 + 512·4+4, critic the same with one output, log std 4.
        let actor = 40 * 512 + 512 + 512 * 512 + 512 + 512 * 4 + 4;
        let critic = 40 * 512 + 512 + 512 * 512 + 512 + 512 + 1;
        assert_eq!(Architecture::paper().parameter_count(), actor + critic + 4);
    }
}
