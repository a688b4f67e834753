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
    /// (`crate::vision`); the critic reads the state observation.
    Vision,
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
    /// Frame the observations were written in; a policy is evaluated in the frame it learned.
    /// Blobs written before this field existed were world-frame.
    #[serde(default)]
    pub observation_frame: sim::ObservationFrame,
    /// Other gates the observation shows after SPEC §5's 40 numbers
    /// ([`sim::ObservationLayout`]); blobs written before this field existed show none.
    #[serde(default)]
    pub obstacle_gates: usize,
    /// Which other gates those are; blobs written before this field existed show the nearest.
    #[serde(default)]
    pub obstacle_order: sim::ObstacleOrder,
    /// Proximity readings the observation ends with; blobs written before this field existed
    /// have none.
    #[serde(default)]
    pub proximity_gates: usize,
    /// Range (m) of those readings.
    #[serde(default = "default_proximity_range")]
    pub proximity_range: f64,
    /// Racing-line points the observation ends with; blobs written before this field existed
    /// have none (and blobs without any are written without the field).
    #[serde(default, skip_serializing_if = "is_zero")]
    pub line_points: usize,
    /// Arc length (m) between those points (left out of blobs when it is the default).
    #[serde(default = "default_line_spacing", skip_serializing_if = "is_default_line_spacing")]
    pub line_spacing: f64,
    /// Which of the target and next gates the observation shows (left out of blobs, and all
    /// for blobs written before this field existed, when it is SPEC's `all`).
    #[serde(default, skip_serializing_if = "is_all_gates")]
    pub gate_sight: sim::GateSight,
    /// Kind of agent; blobs written before this field existed were state-based.
    #[serde(default)]
    pub agent: Agent,
    /// The numbers after SPEC §5's 40 (obstacle gates, proximity readings) are read by the
    /// critic only: an asymmetric actor–critic whose actor flies on SPEC's observation. Blobs
    /// written before this field existed fed both networks the whole observation (and blobs
    /// without one are written without the field, readable by those versions).
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub privileged_critic: bool,
    /// A vision actor reads its previous action after the proprioception (beyond SPEC §5): a
    /// student distilled from a state-based teacher needs it, because the teacher's labels
    /// depend on the previous action its observation holds. Left out of blobs when false.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub vision_previous_action: bool,
    /// The camera frames a vision actor sees (beyond SPEC §5's one: earlier frames too, so it
    /// remembers gates that left the image). Left out of blobs when it is the single frame.
    #[serde(default, skip_serializing_if = "sim::FrameStack::is_single")]
    pub frame_stack: sim::FrameStack,
}

/// True for SPEC's gate sight, which blobs leave out.
fn is_all_gates(sight: &sim::GateSight) -> bool {
    *sight == sim::GateSight::All
}

/// Serde's default for [`Architecture::line_spacing`].
fn default_line_spacing() -> f64 {
    sim::DEFAULT_LINE_SPACING
}

/// Whether a spacing is the default one.
fn is_default_line_spacing(spacing: &f64) -> bool {
    *spacing == sim::DEFAULT_LINE_SPACING
}

/// Whether a count is zero (fields that older blob readers do not know are left out then).
fn is_zero(n: &usize) -> bool {
    *n == 0
}

/// Serde's default for [`Architecture::proximity_range`].
fn default_proximity_range() -> f64 {
    sim::DEFAULT_PROXIMITY_RANGE
}

impl Architecture {
    /// The thesis' network: two hidden layers of 512 (the `paper` profile).
    pub fn paper() -> Self {
        Self {
            observation_dim: sim::STATE_OBS_DIM,
            action_dim: sim::ACTION_DIM,
            hidden: vec![512, 512],
            negative_slope: 0.01,
            observation_frame: sim::ObservationFrame::World,
            obstacle_gates: 0,
            obstacle_order: sim::ObstacleOrder::Nearest,
            proximity_gates: 0,
            proximity_range: sim::DEFAULT_PROXIMITY_RANGE,
            line_points: 0,
            line_spacing: sim::DEFAULT_LINE_SPACING,
            gate_sight: sim::GateSight::All,
            agent: Agent::State,
            privileged_critic: false,
            vision_previous_action: false,
            frame_stack: sim::FrameStack::default(),
        }
    }

    /// Two hidden layers of 256: the `cpu` profile, about 4× fewer multiply-adds than the
    /// paper's. Chosen on the validation set over 128×128
    /// (docs/notebook/generalist.md, "Network size, and the 2-hour generalist at 256×256").
    pub fn cpu() -> Self {
        Self { hidden: vec![256, 256], ..Self::paper() }
    }

    /// What the policy's state observations hold; their length is `observation_dim`.
    pub fn observation_layout(&self) -> sim::ObservationLayout {
        sim::ObservationLayout {
            frame: self.observation_frame,
            obstacle_gates: self.obstacle_gates,
            obstacle_order: self.obstacle_order,
            proximity_gates: self.proximity_gates,
            proximity_range: self.proximity_range,
            line_points: self.line_points,
            line_spacing: self.line_spacing,
            gate_sight: self.gate_sight,
        }
    }

    /// Makes the network read observations of `layout`: the inverse of `observation_layout`,
    /// `observation_dim` included.
    pub fn set_observation_layout(&mut self, layout: sim::ObservationLayout) {
        self.observation_frame = layout.frame;
        self.obstacle_gates = layout.obstacle_gates;
        self.obstacle_order = layout.obstacle_order;
        self.proximity_gates = layout.proximity_gates;
        self.proximity_range = layout.proximity_range;
        self.line_points = layout.line_points;
        self.line_spacing = layout.line_spacing;
        self.gate_sight = layout.gate_sight;
        self.observation_dim = layout.dim();
    }

    /// Length of the observation prefix the actor reads: all of it, or SPEC §5's 40 numbers
    /// under a privileged critic.
    pub fn actor_input_dim(&self) -> usize {
        if self.privileged_critic { self.observation_dim.min(sim::STATE_OBS_DIM) } else { self.observation_dim }
    }

    /// What the actor's input holds: the whole observation, or SPEC §5's 40 numbers in the same
    /// frame under a privileged critic.
    pub fn actor_observation_layout(&self) -> sim::ObservationLayout {
        if self.privileged_critic { sim::ObservationLayout::spec(self.observation_frame) } else { self.observation_layout() }
    }

    /// Layer widths of an MLP of this architecture's hidden layers: `inputs`, hidden…, `outputs`.
    pub fn layer_dims(&self, inputs: usize, outputs: usize) -> Vec<usize> {
        [vec![inputs], self.hidden.clone(), vec![outputs]].concat()
    }

    /// Layer widths of the state-based actor (`inputs`, hidden…, actions) and critic (…, 1).
    pub fn mlp_dims(&self) -> (Vec<usize>, Vec<usize>) {
        (self.layer_dims(self.actor_input_dim(), self.action_dim), self.layer_dims(self.observation_dim, 1))
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
    fn the_observation_is_described_as_the_actor_and_the_whole_row_hold_it() {
        let mut arch = Architecture { observation_frame: sim::ObservationFrame::Heading, ..Architecture::cpu() };
        assert_eq!(arch.actor_observation_layout().describe(), "raw 40-number state observation in the heading frame");
        arch.set_observation_layout(sim::ObservationLayout { line_points: 4, ..arch.observation_layout() });
        let line = ", then 4 points of the reference pilot's racing line every 2.5 m of arc from its nearest point";
        assert_eq!(arch.actor_observation_layout().describe(), format!("raw 52-number state observation in the heading frame{line}"));
        // Under a privileged critic the actor reads SPEC's 40; a served row still holds all 52.
        arch.privileged_critic = true;
        assert_eq!(arch.actor_observation_layout().describe(), "raw 40-number state observation in the heading frame");
        assert_eq!(arch.actor_observation_layout().dim(), arch.actor_input_dim());
        assert_eq!(arch.observation_layout().describe(), format!("raw 52-number state observation in the heading frame{line}"));
    }

    #[test]
    fn parameter_count_of_the_paper_network() {
        // Actor 40·512+512 + 512·512+512 + 512·4+4, critic the same with one output, log std 4.
        let actor = 40 * 512 + 512 + 512 * 512 + 512 + 512 * 4 + 4;
        let critic = 40 * 512 + 512 + 512 * 512 + 512 + 512 + 1;
        assert_eq!(Architecture::paper().parameter_count(), actor + critic + 4);
    }

    #[test]
    fn a_privileged_critic_keeps_the_extra_inputs_from_the_actor() {
        let mut arch = Architecture { hidden: vec![8], ..Architecture::paper() };
        arch.set_observation_layout(sim::ObservationLayout { obstacle_gates: 2, ..arch.observation_layout() });
        assert_eq!((arch.observation_dim, arch.actor_input_dim()), (64, 64));
        arch.privileged_critic = true;
        assert_eq!(arch.actor_input_dim(), 40);
        assert_eq!(arch.mlp_dims(), (vec![40, 8, 4], vec![64, 8, 1]));
        assert_eq!(arch.parameter_count(), (40 * 8 + 8 + 8 * 4 + 4) + (64 * 8 + 8 + 8 + 1) + 4);
    }
}
