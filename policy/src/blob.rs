//! The versioned weights blob: architecture, normaliser, policy version and every parameter,
//! in a little-endian binary layout that round-trips bit-exactly and refuses corruption.
//!
//! Layout: `DRPOLICY`, format u32, version u64, architecture (u32 length + JSON), normaliser
//! (dim u32, count, clip, epsilon, mean[dim], var[dim] as f64), parameters (count u32; each:
//! id u64, rank u8, dims u32[rank], values f32[numel]), CRC-32 of everything before it.

use burn::tensor::Device;

use crate::architecture::Architecture;
use crate::bytes::{Reader, Truncated, put_f32s};
use crate::network::{ActorCritic, ExportedParam};
use crate::normalizer::ObsNormalizer;

const MAGIC: &[u8; 8] = b"DRPOLICY";
const FORMAT: u32 = 1;

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
    #[error("not a dronerace weights blob (bad magic)")]
    BadMagic,
    /// Written by another format version.
    #[error("weights blob format {0}; this build reads format {FORMAT}")]
    UnsupportedFormat(u32),
    /// The checksum does not match the contents.
    #[error("weights blob checksum mismatch: the contents were altered")]
    Checksum,
    /// The network shape differs from the one expected.
    #[error("weights blob holds architecture {found}, expected {expected}")]
    Architecture {
        /// Architecture in the blob, as JSON.
        found: String,
        /// Architecture expected, as JSON.
        expected: String,
    },
    /// Anything else malformed inside.
    #[error("weights blob is malformed: {0}")]
    Malformed(String),
}

/// Weights, normaliser and version of one policy.
#[derive(Clone, Debug, PartialEq)]
pub struct WeightsBlob {
    /// Policy version: the learner's update count that produced it.
    pub version: u64,
    /// Network shape.
    pub architecture: Architecture,
    /// Observation statistics the network was trained with.
    pub normalizer: ObsNormalizer,
    /// Parameters in [`ActorCritic::export`] order.
    pub params: Vec<ExportedParam>,
}

impl WeightsBlob {
    /// Captures a model with its normaliser.
    pub fn from_model(version: u64, architecture: &Architecture, normalizer: &ObsNormalizer, model: &ActorCritic) -> Self {
        Self { version, architecture: architecture.clone(), normalizer: normalizer.clone(), params: model.export() }
    }

    /// The network on `device`, with its original parameter ids.
    pub fn model(&self, device: &Device) -> Result<ActorCritic, BlobError> {
        ActorCritic::import(&self.architecture, &self.params, device).map_err(BlobError::Malformed)
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

    /// Encodes the blob.
    #[allow(clippy::expect_used, reason = "architectures serialise")]
    pub fn to_bytes(&self) -> Vec<u8> {
        let mut out = Vec::with_capacity(64 + 4 * self.params.iter().map(|p| p.values.len()).sum::<usize>());
        out.extend_from_slice(MAGIC);
        out.extend_from_slice(&FORMAT.to_le_bytes());
        out.extend_from_slice(&self.version.to_le_bytes());
        let arch = serde_json::to_vec(&self.architecture).expect("architectures serialise");
        out.extend_from_slice(&(arch.len() as u32).to_le_bytes());
        out.extend_from_slice(&arch);
        let n = &self.normalizer;
        out.extend_from_slice(&(n.dim() as u32).to_le_bytes());
        for x in [n.count, n.clip, n.epsilon].iter().chain(&n.mean).chain(&n.var) {
            out.extend_from_slice(&x.to_le_bytes());
        }
        out.extend_from_slice(&(self.params.len() as u32).to_le_bytes());
        for p in &self.params {
            out.extend_from_slice(&p.id.to_le_bytes());
            out.push(p.shape.len() as u8);
            for d in &p.shape {
                out.extend_from_slice(&(*d as u32).to_le_bytes());
            }
            put_f32s(&mut out, &p.values);
        }
        let crc = crc32fast::hash(&out);
        out.extend_from_slice(&crc.to_le_bytes());
        out
    }

    /// Decodes and verifies a blob.
    pub fn from_bytes(bytes: &[u8]) -> Result<Self, BlobError> {
        if bytes.len() < MAGIC.len() || &bytes[..MAGIC.len()] != MAGIC {
            return Err(BlobError::BadMagic);
        }
        if bytes.len() < 16 {
            return Err(BlobError::Truncated { needed: 16 - bytes.len(), at: bytes.len() });
        }
        let (body, crc) = bytes.split_at(bytes.len() - 4);
        let mut r = Reader::new(body, MAGIC.len());
        let format = r.u32()?;
        if format != FORMAT {
            return Err(BlobError::UnsupportedFormat(format));
        }
        if crc32fast::hash(body).to_le_bytes() != crc {
            return Err(BlobError::Checksum);
        }
        let version = r.u64()?;
        let arch_len = r.u32()? as usize;
        let architecture: Architecture =
            serde_json::from_slice(r.take(arch_len)?).map_err(|e| BlobError::Malformed(format!("architecture: {e}")))?;
        let dim = r.u32()? as usize;
        let (count, clip, epsilon) = (r.f64()?, r.f64()?, r.f64()?);
        let mean = (0..dim).map(|_| r.f64()).collect::<Result<_, _>>()?;
        let var = (0..dim).map(|_| r.f64()).collect::<Result<_, _>>()?;
        let normalizer = ObsNormalizer { mean, var, count, clip, epsilon };
        let count = r.u32()? as usize;
        let mut params = Vec::with_capacity(r.capacity_for(count, 9)); // id u64 + rank u8 at least
        for _ in 0..count {
            let id = r.u64()?;
            let rank = r.u8()? as usize;
            let shape: Vec<usize> = (0..rank).map(|_| r.u32().map(|d| d as usize)).collect::<Result<_, _>>()?;
            let numel = shape.iter().try_fold(1usize, |n, &d| n.checked_mul(d));
            let numel = numel.ok_or_else(|| BlobError::Malformed(format!("parameter {id}: shape {shape:?} overflows")))?;
            let values = r.f32s(numel)?;
            params.push(ExportedParam { id, shape, values });
        }
        if r.remaining() != 0 {
            return Err(BlobError::Malformed(format!("{} bytes after the parameters", r.remaining())));
        }
        if normalizer.dim() != architecture.observation_dim {
            return Err(BlobError::Malformed("normaliser length differs from the observation length".into()));
        }
        Ok(Self { version, architecture, normalizer, params })
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

    fn blob() -> WeightsBlob {
        let arch = Architecture { hidden: vec![8, 8], ..Architecture::paper() };
        let model = ActorCritic::new(&arch, -0.5, 1, &Device::flex());
        let mut normalizer = ObsNormalizer::new(arch.observation_dim);
        normalizer.update(&(0..arch.observation_dim * 3).map(|i| i as f32 * 0.1).collect::<Vec<_>>());
        WeightsBlob::from_model(7, &arch, &normalizer, &model)
    }

    #[test]
    fn round_trips_bit_exactly_through_bytes_and_the_model() {
        let b = blob();
        let bytes = b.to_bytes();
        let back = WeightsBlob::from_bytes(&bytes).unwrap();
        assert_eq!(back, b);
        // Through a rebuilt network and out again: the same bits.
        let again = WeightsBlob::from_model(7, &b.architecture, &b.normalizer, &back.model(&Device::flex()).unwrap());
        assert_eq!(again.to_bytes(), bytes);
        assert_eq!(again.params[0].values.len(), 40 * 8);
        assert!(again.params.last().unwrap().values.iter().all(|&v| v == -0.5), "initial log std");
    }

    #[test]
    fn corrupt_truncated_foreign_and_mismatched_blobs_are_refused() {
        let b = blob();
        let bytes = b.to_bytes();
        assert!(matches!(WeightsBlob::from_bytes(&bytes[..bytes.len() - 9]), Err(BlobError::Checksum)));
        let mut flipped = bytes.clone();
        flipped[100] ^= 0x40;
        assert_eq!(WeightsBlob::from_bytes(&flipped), Err(BlobError::Checksum));
        assert_eq!(WeightsBlob::from_bytes(b"hello world, not a blob"), Err(BlobError::BadMagic));
        assert!(matches!(WeightsBlob::from_bytes(&bytes[..12]), Err(BlobError::Truncated { .. })));
        let e = b.check_architecture(&Architecture::paper()).unwrap_err().to_string();
        assert!(e.contains("[8,8]") && e.contains("[512,512]"), "{e}");
    }
}
