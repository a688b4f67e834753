//! Policies: the actor-critic network (burn), the observation normaliser, the versioned
//! weights blob that carries both to actors, inference for acting and evaluating, and the
//! rollout chunk actors send back.

pub mod architecture;
pub mod averaging;
pub mod blob;
pub mod dense;
pub mod inference;
mod narrow;
pub mod network;
pub mod normalizer;
pub mod onnx;
pub mod rollout;
mod rows;
pub mod run_length;
pub mod safetensors;
pub mod surgery;
pub mod vision;

pub use architecture::{Agent, Architecture};
pub use blob::{BlobError, WeightsBlob};
/// The burn device networks are built on (the CPU).
pub use burn::tensor::Device;
pub use inference::{
    Acting, ActingPolicy, ControllerFactory, HALF_LN_2PI, Policy, PolicyController, VisionPolicy, VisionPolicyController,
    controller_factory, gaussian_log_prob,
};
pub use network::ActorCritic;
pub use normalizer::ObsNormalizer;
pub use rollout::{ChunkLimits, EpisodeRecord, RolloutCheckError, RolloutChunk, RolloutWireError};
pub use vision::{VisionActorCritic, pixels_to_unit};
