//! What a policy's parameters are, whichever library computes with them: the vision agent's
//! layer sizes (SPEC §5), every parameter's shape in export order, and an exported parameter.

use crate::architecture::{Agent, Architecture};

/// Side of the camera image (pixels).
pub const IMAGE_SIDE: usize = 84;
/// Length of the CNN's embedding.
pub const EMBEDDING: usize = 128;
/// Length of the actor's state part: R_WB columns 0–1 (6), v (3), ω (3) — the first 12
/// numbers of the state observation (SPEC §5 order), normalised as the critic's are.
pub const PROPRIOCEPTION: usize = sim::PREVIOUS_ACTION_RANGE.start;
/// Length of the previous action, which follows the proprioception in the state observation.
const PREVIOUS_ACTION: usize = sim::ACTION_DIM;
/// The vision agent's three convolutions: (output channels, kernel, stride).
pub const CONVOLUTIONS: [(usize, usize, usize); 3] = [(32, 8, 4), (64, 4, 2), (64, 3, 1)];
/// Number of convolutions.
pub const CONVOLUTION_COUNT: usize = CONVOLUTIONS.len();
/// Flattened length after the convolutions: 64 channels × 7 × 7 for an 84×84 image.
pub const CONV_OUTPUT: usize = 64 * 7 * 7;

/// How many of the state observation's first numbers a vision actor of `arch` reads: the
/// proprioception, and the previous action after it when `arch.vision_previous_action`.
pub fn actor_state_len(arch: &Architecture) -> usize {
    PROPRIOCEPTION + if arch.vision_previous_action { PREVIOUS_ACTION } else { 0 }
}

/// One exported parameter: its id (so optimiser state can follow it), shape and values.
#[derive(Clone, Debug, PartialEq)]
pub struct ExportedParam {
    /// burn's parameter id.
    pub id: u64,
    /// Shape.
    pub shape: Vec<usize>,
    /// Row-major values.
    pub values: Vec<f32>,
}

/// Exported parameters whose shapes do not fit the architecture they are imported into.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
#[error("parameter shapes {got:?} do not fit the architecture's {expected:?}")]
pub struct ShapeMismatch {
    /// The parameters' shapes, in export order.
    pub got: Vec<Vec<usize>>,
    /// The architecture's.
    pub expected: Vec<Vec<usize>>,
}

/// Refuses exported parameters whose shapes are not `expected`.
pub fn check_shapes(expected: &[Vec<usize>], params: &[ExportedParam]) -> Result<(), ShapeMismatch> {
    let got: Vec<Vec<usize>> = params.iter().map(|p| p.shape.clone()).collect();
    if expected == got { Ok(()) } else { Err(ShapeMismatch { got, expected: expected.to_vec() }) }
}

/// (weight, bias) shapes of the layers between `dims`.
pub fn mlp_shapes(dims: &[usize]) -> Vec<Vec<usize>> {
    dims.windows(2).flat_map(|w| [vec![w[0], w[1]], vec![w[1]]]).collect()
}

/// Parameter shapes of a policy of `arch`, in export order: the state agent's actor layers
/// (weight, bias), critic layers, log std; a vision agent's convolutions and embedding first,
/// and its actor reading the embedding and the proprioception.
pub fn parameter_shapes(arch: &Architecture) -> Vec<Vec<usize>> {
    let mut shapes = Vec::new();
    match arch.agent {
        Agent::State => {
            let (actor, critic) = arch.mlp_dims();
            shapes.extend(mlp_shapes(&actor));
            shapes.extend(mlp_shapes(&critic));
        }
        Agent::Vision => {
            let mut channels = 1;
            for (out, kernel, _) in CONVOLUTIONS {
                shapes.push(vec![out, channels, kernel, kernel]);
                shapes.push(vec![out]);
                channels = out;
            }
            shapes.extend(mlp_shapes(&[CONV_OUTPUT, EMBEDDING]));
            shapes.extend(mlp_shapes(&arch.layer_dims(EMBEDDING + actor_state_len(arch), arch.action_dim)));
            shapes.extend(mlp_shapes(&arch.layer_dims(arch.observation_dim, 1)));
        }
    }
    shapes.push(vec![arch.action_dim]);
    shapes
}
