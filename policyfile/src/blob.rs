//! The versioned weights blob: architecture, normaliser, policy version and every parameter,
//! as a safetensors file (`crate::safetensors`) that round-trips bit-exactly, refuses
//! corruption and opens in Python (`safetensors.numpy.load_file`) and burn's importers.
//!
//! Tensors: `actor.<i>.weight` `[in, out]` and `actor.<i>.bias` `[out]` for layer i (so a
//! layer is `x @ W + b`, LeakyReLU between layers, none after the last; its output is the
//! action mean), the same for `critic` (output: the value), `log_std` `[action_dim]`,
//! `normalizer.mean` and `normalizer.var` (F64; observations are normalised as
//! `clip((x − mean) / sqrt(var + epsilon), ±clip)`). Metadata: `format` = `dronerace-policy`,
//! `format_version`, `policy_version`, `architecture` and `normalizer` (count, clip, epsilon)
//! as JSON, `param_ids` (burn's parameter ids, so optimiser moments re-attach), `crc32`.
//!
//! One format is read: this build's (3). Files of format 2 convert with
//! `docs/python/upgrade_policy.py` (policies/README.md); the shipped policies were converted so.

use crate::architecture::{Agent, Architecture};
use crate::normalizer::ObsNormalizer;
use crate::safetensors::{Tensor, TensorData, TensorFile, TensorFileError};
use crate::shapes::{CONVOLUTION_COUNT, ExportedParam, ShapeMismatch, parameter_shapes};
use frames::Truncated;

/// `format` in the metadata of a policy file.
const FORMAT_NAME: &str = "dronerace-policy";
/// `format_version` this build writes and reads: 3 holds the observation layout as one object
/// (`architecture.observation`).
const FORMAT: u32 = 3;

/// A blob that cannot be used.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum BlobError {
    /// The bytes end before the layout does.
    #[error("weights blob is truncated: needed {needed} more bytes at offset {at}")]
    Truncated {
        /// Bytes missing.
        needed: usize,
        /// Where they were needed.
        at: usize,
    },
    /// Not a weights blob at all.
    #[error("not a dronerace weights blob (a safetensors policy file)")]
    BadMagic,
    /// Written by another format version.
    #[error("weights blob format {0}; this build reads format {FORMAT} (format 2 converts with docs/python/upgrade_policy.py)")]
    UnsupportedFormat(u32),
    /// The checksum does not match the contents.
    #[error("weights blob checksum mismatch: the contents were altered")]
    Checksum,
    /// The blob holds another kind of agent than the one asked for.
    #[error("weights blob holds a {found} policy; a {expected} one is needed here")]
    Agent {
        /// Kind in the blob.
        found: Agent,
        /// Kind needed.
        expected: Agent,
    },
    /// The network shape differs from the one expected.
    #[error("weights blob holds architecture {found}, expected {expected}")]
    Architecture {
        /// Architecture in the blob, as JSON.
        found: String,
        /// Architecture expected, as JSON.
        expected: String,
    },
    /// Its parameters do not fit its own architecture.
    #[error("weights blob is malformed: {0}")]
    Shapes(#[from] ShapeMismatch),
    /// Anything else malformed inside.
    #[error("weights blob is malformed: {0}")]
    Malformed(String),
}

/// Largest magnitude a weight may have: initialised weights are O(1) and a healthy PPO update
/// moves them by ~1e-3; a weight this large means the training diverged.
pub const MAX_WEIGHT: f32 = 1.0e6;

/// Weights, normaliser and version of one policy.
#[derive(Clone, Debug, PartialEq)]
pub struct WeightsBlob {
    /// Policy version: the learner's update count that produced it.
    pub version: u64,
    /// Network shape.
    pub architecture: Architecture,
    /// Observation statistics the network was trained with.
    pub normalizer: ObsNormalizer,
    /// Parameters in export order ([`crate::shapes::parameter_shapes`]).
    pub params: Vec<ExportedParam>,
}

impl WeightsBlob {
    /// Refuses a blob of another kind of agent than `expected`.
    pub fn check_agent(&self, expected: Agent) -> Result<(), BlobError> {
        let found = self.architecture.agent;
        if found == expected { Ok(()) } else { Err(BlobError::Agent { found, expected }) }
    }

    /// Refuses a blob whose architecture is not `expected`.
    #[allow(clippy::expect_used, reason = "architectures serialise")]
    pub fn check_architecture(&self, expected: &Architecture) -> Result<(), BlobError> {
        if &self.architecture == expected {
            return Ok(());
        }
        let json = |a: &Architecture| serde_json::to_string(a).expect("architectures serialise");
        Err(BlobError::Architecture { found: json(&self.architecture), expected: json(expected) })
    }

    /// Tensor names in export order (a vision agent's start with `cnn.<i>` and `embedding`).
    pub fn tensor_names(architecture: &Architecture) -> Vec<String> {
        let mut names = Vec::new();
        if architecture.agent == Agent::Vision {
            for layer in 0..CONVOLUTION_COUNT {
                names.push(format!("cnn.{layer}.weight"));
                names.push(format!("cnn.{layer}.bias"));
            }
            names.push("embedding.weight".into());
            names.push("embedding.bias".into());
        }
        for net in ["actor", "critic"] {
            for layer in 0..=architecture.hidden.len() {
                names.push(format!("{net}.{layer}.weight"));
                names.push(format!("{net}.{layer}.bias"));
            }
        }
        names.push("log_std".into());
        names
    }

    /// The blob as a safetensors file in memory (a checkpoint adds its own sections to it).
    #[allow(clippy::expect_used, reason = "architectures, normaliser scalars and ids serialise")]
    pub fn to_tensor_file(&self) -> TensorFile {
        let mut file = TensorFile::default();
        let n = &self.normalizer;
        let meta = [
            ("format", FORMAT_NAME.to_string()),
            ("format_version", FORMAT.to_string()),
            ("policy_version", self.version.to_string()),
            ("architecture", serde_json::to_string(&self.architecture).expect("architectures serialise")),
            ("normalizer", serde_json::json!({ "count": n.count, "clip": n.clip, "epsilon": n.epsilon }).to_string()),
            ("param_ids", serde_json::to_string(&self.params.iter().map(|p| p.id).collect::<Vec<_>>()).expect("ids serialise")),
        ];
        file.metadata.extend(meta.map(|(k, v)| (k.to_string(), v)));
        for (name, p) in Self::tensor_names(&self.architecture).into_iter().zip(&self.params) {
            file.tensors.insert(name, Tensor { shape: p.shape.clone(), data: TensorData::F32(p.values.clone()) });
        }
        for (name, values) in [("normalizer.mean", &n.mean), ("normalizer.var", &n.var)] {
            file.tensors.insert(name.into(), Tensor { shape: vec![values.len()], data: TensorData::F64(values.clone()) });
        }
        file
    }

    /// Encodes the blob (a safetensors file).
    pub fn to_bytes(&self) -> Vec<u8> {
        self.to_tensor_file().to_bytes()
    }

    /// Decodes and verifies a blob.
    pub fn from_bytes(bytes: &[u8]) -> Result<Self, BlobError> {
        if !TensorFile::sniff(bytes) {
            // Too short to tell: a prefix of a policy file is truncated, anything else foreign.
            let shortest = 8 + crate::safetensors::HEADER_START.len();
            let prefix = bytes.len() < 8 || crate::safetensors::HEADER_START.starts_with(&bytes[8..]);
            if bytes.len() < shortest && prefix {
                return Err(BlobError::Truncated { needed: shortest - bytes.len(), at: bytes.len() });
            }
            return Err(BlobError::BadMagic);
        }
        Self::from_tensor_file(&TensorFile::from_bytes(bytes)?)
    }

    /// Reads the policy out of a safetensors file (extra tensors and metadata are ignored).
    pub fn from_tensor_file(file: &TensorFile) -> Result<Self, BlobError> {
        let malformed = |m: String| BlobError::Malformed(m);
        if file.meta("format")? != FORMAT_NAME {
            return Err(BlobError::BadMagic);
        }
        let format = file.meta("format_version")?;
        if format != FORMAT.to_string() {
            return Err(BlobError::UnsupportedFormat(format.parse().unwrap_or(u32::MAX)));
        }
        let version = file.meta("policy_version")?.parse().map_err(|e| malformed(format!("policy_version: {e}")))?;
        let architecture: Architecture =
            serde_json::from_str(file.meta("architecture")?).map_err(|e| malformed(format!("architecture: {e}")))?;
        #[derive(serde::Deserialize)]
        struct Scalars {
            count: f64,
            clip: f64,
            epsilon: f64,
        }
        let s: Scalars = serde_json::from_str(file.meta("normalizer")?).map_err(|e| malformed(format!("normalizer: {e}")))?;
        let ids: Vec<u64> = serde_json::from_str(file.meta("param_ids")?).map_err(|e| malformed(format!("param_ids: {e}")))?;
        let f64s = |name: &str| match &file.tensor(name)?.data {
            TensorData::F64(v) => Ok(v.clone()),
            _ => Err(malformed(format!("{name} is not F64"))),
        };
        let normalizer = ObsNormalizer {
            mean: f64s("normalizer.mean")?,
            var: f64s("normalizer.var")?,
            count: s.count,
            clip: s.clip,
            epsilon: s.epsilon,
        };
        check_observation_lengths(&architecture, &normalizer)?;
        let names = Self::tensor_names(&architecture);
        if ids.len() != names.len() {
            return Err(malformed(format!("{} parameter ids for {} parameters", ids.len(), names.len())));
        }
        let mut params = Vec::with_capacity(names.len());
        for ((name, id), shape) in names.iter().zip(ids).zip(parameter_shapes(&architecture)) {
            let tensor = file.tensor(name)?;
            if tensor.shape != shape {
                return Err(malformed(format!("{name} has shape {:?}; the architecture needs {shape:?}", tensor.shape)));
            }
            let TensorData::F32(values) = &tensor.data else { return Err(malformed(format!("{name} is not F32"))) };
            params.push(ExportedParam { id, shape: tensor.shape.clone(), values: values.clone() });
        }
        let blob = Self { version, architecture, normalizer, params };
        blob.check_parameters()?;
        Ok(blob)
    }

    /// Every parameter finite and within ±[`MAX_WEIGHT`]: a policy that fails this would act
    /// with NaN or saturated actions, and a learner that produced it has diverged.
    pub fn check_parameters(&self) -> Result<(), BlobError> {
        for (k, p) in self.params.iter().enumerate() {
            if let Some(i) = p.values.iter().position(|w| !(w.is_finite() && w.abs() <= MAX_WEIGHT)) {
                return Err(BlobError::Malformed(format!(
                    "parameter {k} (id {}) holds {} at {i}: not a finite weight within ±{MAX_WEIGHT:e}",
                    p.id, p.values[i]
                )));
            }
        }
        Ok(())
    }
}

/// The observation length must match what the layout holds, and the normaliser must match it.
fn check_observation_lengths(architecture: &Architecture, normalizer: &ObsNormalizer) -> Result<(), BlobError> {
    let layout = architecture.observation;
    if architecture.observation_dim != layout.dim() {
        return Err(BlobError::Malformed(format!(
            "observation_dim {} but SPEC §5's 40 numbers and {} racing-line points make {}",
            architecture.observation_dim,
            layout.line_points,
            layout.dim()
        )));
    }
    if normalizer.mean.len() != architecture.observation_dim || normalizer.var.len() != architecture.observation_dim {
        return Err(BlobError::Malformed("normaliser length differs from the observation length".into()));
    }
    // Values that would make normalising panic (a negative clip in `f64::clamp`) or return
    // non-finite observations.
    let scalars = [("clip", normalizer.clip, false), ("count", normalizer.count, false), ("epsilon", normalizer.epsilon, true)];
    for (name, value, zero_allowed) in scalars {
        if !(value.is_finite() && (value > 0.0 || (zero_allowed && value == 0.0))) {
            let bound = if zero_allowed { "≥ 0" } else { "positive" };
            return Err(BlobError::Malformed(format!("normalizer.{name} is {value}; it must be finite and {bound}")));
        }
    }
    if let Some(i) = normalizer.mean.iter().position(|m| !m.is_finite()) {
        return Err(BlobError::Malformed(format!("normalizer.mean[{i}] is not finite")));
    }
    if let Some(i) = normalizer.var.iter().position(|v| !(v.is_finite() && *v >= 0.0)) {
        return Err(BlobError::Malformed(format!("normalizer.var[{i}] is {}; it must be finite and ≥ 0", normalizer.var[i])));
    }
    Ok(())
}

impl From<TensorFileError> for BlobError {
    fn from(e: TensorFileError) -> Self {
        match e {
            TensorFileError::Checksum => Self::Checksum,
            other => Self::Malformed(other.to_string()),
        }
    }
}

impl From<Truncated> for BlobError {
    fn from(t: Truncated) -> Self {
        Self::Truncated { needed: t.needed, at: t.at }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::test_blobs::pattern_blob;

    fn blob() -> WeightsBlob {
        let arch = Architecture { hidden: vec![8, 8], ..Architecture::paper() };
        let mut normalizer = ObsNormalizer::new(arch.observation_dim);
        normalizer.update(&(0..arch.observation_dim * 3).map(|i| i as f32 * 0.1).collect::<Vec<_>>());
        pattern_blob(&arch, normalizer, 7, 0)
    }

    #[test]
    fn round_trips_bit_exactly_through_bytes() {
        let b = blob();
        let bytes = b.to_bytes();
        let back = WeightsBlob::from_bytes(&bytes).unwrap();
        assert_eq!(back, b);
        assert_eq!(back.to_bytes(), bytes);
        assert_eq!(back.params[0].values.len(), 40 * 8);
    }

    #[test]
    fn corrupt_truncated_foreign_and_mismatched_blobs_are_refused() {
        let b = blob();
        let bytes = b.to_bytes();
        assert!(
            matches!(WeightsBlob::from_bytes(&bytes[..bytes.len() - 9]), Err(BlobError::Malformed(m)) if m.contains("outside the data"))
        );
        let mut flipped = bytes.clone();
        *flipped.last_mut().unwrap() ^= 0x40;
        assert_eq!(WeightsBlob::from_bytes(&flipped), Err(BlobError::Checksum));
        assert_eq!(WeightsBlob::from_bytes(b"hello world, not a blob"), Err(BlobError::BadMagic));
        assert!(matches!(WeightsBlob::from_bytes(&bytes[..12]), Err(BlobError::Truncated { .. })));
        let e = b.check_architecture(&Architecture::paper()).unwrap_err().to_string();
        let mut other = b.to_tensor_file();
        other.metadata.insert("format_version".into(), "2".into());
        let older = WeightsBlob::from_bytes(&other.to_bytes()).unwrap_err();
        assert!(older == BlobError::UnsupportedFormat(2) && older.to_string().contains("upgrade_policy.py"), "{older}");
        assert!(e.contains("[8,8]") && e.contains("[512,512]"), "{e}");
    }

    /// A policy with a layout beyond SPEC's round-trips with it; a blob whose observation length
    /// disagrees with its layout is refused.
    #[test]
    fn a_normaliser_that_would_panic_or_emit_non_finite_values_is_refused_by_field() {
        let refused = |edit: &dyn Fn(&mut WeightsBlob)| {
            let mut b = blob();
            edit(&mut b);
            match WeightsBlob::from_bytes(&b.to_bytes()) {
                Err(BlobError::Malformed(m)) => m,
                other => panic!("accepted: {other:?}"),
            }
        };
        assert!(refused(&|b| b.normalizer.clip = -1.0).contains("normalizer.clip is -1"));
        assert!(refused(&|b| b.normalizer.count = 0.0).contains("normalizer.count"));
        assert!(refused(&|b| b.normalizer.epsilon = -1e-8).contains("normalizer.epsilon"));
        assert!(refused(&|b| b.normalizer.mean[3] = f64::INFINITY).contains("normalizer.mean[3]"));
        assert!(refused(&|b| b.normalizer.var[2] = -0.5).contains("normalizer.var[2]"));
        let mut fine = blob();
        fine.normalizer.epsilon = 0.0;
        assert!(WeightsBlob::from_bytes(&fine.to_bytes()).is_ok(), "epsilon 0 is a valid normaliser");
    }

    #[test]
    fn the_observation_layout_travels_with_the_blob_and_must_match_its_length() {
        let layout = sim::ObservationLayout {
            frame: sim::ObservationFrame::Heading,
            line_points: 2,
            line_spacing: 1.5,
            gate_sight: sim::GateSight::Camera,
        };
        let mut arch = Architecture { hidden: vec![8, 8], ..Architecture::paper() };
        arch.set_observation_layout(layout);
        let b = pattern_blob(&arch, ObsNormalizer::new(46), 3, 0);
        let back = WeightsBlob::from_bytes(&b.to_bytes()).unwrap();
        assert_eq!(back.architecture.observation, layout);
        assert_eq!(back.params[0].values.len(), 46 * 8);
        let wrong = Architecture { observation: sim::ObservationLayout { line_points: 1, ..layout }, ..arch.clone() };
        let e = WeightsBlob::from_bytes(&WeightsBlob { architecture: wrong, ..b.clone() }.to_bytes()).unwrap_err();
        assert!(
            matches!(&e, BlobError::Malformed(m) if m.contains("observation_dim 46") && m.contains("1 racing-line points make 43")),
            "{e}"
        );
    }
}
