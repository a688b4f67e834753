//! `dronerace export`: a checkpoint's policy — or the weight average of several — as a
//! stand-alone weights blob without optimiser, environments or curriculum, or as an ONNX model
//! other programs run (ONNX Runtime, TensorRT, …).

use std::path::PathBuf;
use std::str::FromStr;

use policy::WeightsBlob;

/// Formats a policy is exported in.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ExportFormat {
    /// The policy as a weights blob (safetensors: architecture, normaliser, version, weights),
    /// what `eval --policy`, `serve`, `train --init-from` and actors read.
    Safetensors,
    /// The deterministic actor with its normaliser folded in, as an ONNX model (opset 13).
    Onnx,
}

impl FromStr for ExportFormat {
    type Err = String;

    fn from_str(name: &str) -> Result<Self, String> {
        match name {
            "safetensors" => Ok(Self::Safetensors),
            "onnx" => Ok(Self::Onnx),
            other => Err(format!("{other:?} is neither safetensors nor onnx")),
        }
    }
}

/// Why a policy could not be exported.
#[derive(Debug, thiserror::Error)]
pub enum ExportError {
    /// Nothing named.
    #[error("export: name the checkpoint or weights blob to export")]
    Nothing,
    /// A checkpoint or blob could not be read.
    #[error("reading {}: {source}", path.display())]
    Read {
        /// The file.
        path: PathBuf,
        /// Why.
        source: crate::checkpoint::CheckpointError,
    },
    /// The policies could not be averaged (other architectures) or converted.
    #[error(transparent)]
    Policy(#[from] policy::BlobError),
}

/// An exported policy and its file's bytes.
pub struct Exported {
    /// The policy written (the mean of several under the newest one's normaliser).
    pub blob: WeightsBlob,
    /// The file's contents.
    pub bytes: Vec<u8>,
}

/// The policy of the one checkpoint or blob in `paths`, or the mean of their weights under the
/// newest one's normaliser (stochastic weight averaging), encoded as `format`.
pub fn export(paths: &[PathBuf], format: ExportFormat) -> Result<Exported, ExportError> {
    let blobs = paths
        .iter()
        .map(|path| crate::checkpoint::read_policy(path).map_err(|source| ExportError::Read { path: path.clone(), source }))
        .collect::<Result<Vec<_>, _>>()?;
    let blob = match blobs.as_slice() {
        [] => return Err(ExportError::Nothing),
        [one] => one.clone(),
        many => policyfile::averaging::average(many)?,
    };
    let bytes = match format {
        ExportFormat::Safetensors => blob.to_bytes(),
        ExportFormat::Onnx => policyfile::onnx::actor_model(&blob)?,
    };
    Ok(Exported { blob, bytes })
}
