//! A trained policy as a file, without the networks that train it: the architecture and the
//! shapes of its parameters (`architecture`, `shapes`), the observation normaliser
//! (`normalizer`), the versioned weights blob (`blob`) in its safetensors container
//! (`safetensors`), ONNX export (`onnx`), weight averaging (`averaging`) and rewrites that keep
//! what a policy does (`surgery`). Serving, export and Python read policies through it; the
//! `policy` crate turns a blob into burn networks and back.

pub mod architecture;
pub mod averaging;
pub mod blob;
pub mod normalizer;
pub mod onnx;
pub mod safetensors;
pub mod shapes;
pub mod surgery;
#[cfg(test)]
mod test_blobs;

pub use architecture::{Agent, Architecture};
pub use blob::{BlobError, WeightsBlob};
pub use normalizer::ObsNormalizer;
pub use shapes::{ExportedParam, ShapeMismatch};
