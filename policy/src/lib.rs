//! The networks of a policy (burn): the state-based actor-critic (`network`), the vision
//! agent's (`vision`), both to and from their weights blobs (`models`), and inference for
//! acting and evaluating (`inference`). The matrix kernels are the `kernels` crate's; the policy
//! file (architecture, normaliser, weights blob, ONNX) is the `policyfile` crate's, whose main
//! types are re-exported here.

pub mod inference;
pub mod models;
pub mod network;
pub mod vision;

/// The burn device networks are built on (the CPU).
pub use burn::tensor::Device;
pub use inference::{
    Acting, ActingPolicy, ControllerFactory, HALF_LN_2PI, Policy, PolicyController, VisionPolicy, VisionPolicyController,
    controller_factory, gaussian_log_prob,
};
pub use models::NetworkBlob;
pub use network::ActorCritic;
pub use policyfile::{Agent, Architecture, BlobError, ObsNormalizer, WeightsBlob};
pub use vision::{VisionActorCritic, pixels_to_unit};
