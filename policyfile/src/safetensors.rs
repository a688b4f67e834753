//! Our files in the safetensors format (huggingface/safetensors), encoded and decoded by the
//! format's own crate: an 8-byte little-endian header length, a JSON header naming each
//! tensor's dtype, shape and byte range plus a string-to-string `__metadata__` map, then the
//! tensor bytes. Python's `safetensors` package and burn's importers open these files as they
//! are.
//!
//! What we add inside the format: metadata key `crc32`, the CRC-32 of every other metadata
//! entry (sorted, `key NUL value NUL`), every tensor's name, dtype and shape (sorted by name,
//! each followed by NUL) and the tensors' bytes in name order; and a header in canonical JSON
//! (keys sorted, no whitespace but the format's padding), so that a file's bytes follow from
//! its contents and a corrupted file is refused rather than half-used, as every other file of
//! ours is. (The crate writes metadata in hash order; the header is canonicalised after it.)

use std::collections::BTreeMap;

use safetensors::tensor::TensorView;
use safetensors::{Dtype, SafeTensorError, SafeTensors};
use serde_json::Value;

/// The first bytes every file of ours starts with: a header length, then `{"__metadata__":`
/// (first in the sorted header: every tensor name starts with a lower-case letter), which tells
/// our files apart from the older framed formats.
pub const HEADER_START: &[u8] = b"{\"__metadata__\":";

/// Longest header accepted (a corrupt length must not make us allocate gigabytes).
const MAX_HEADER: usize = 16 << 20;

/// Element types we store.
#[derive(Clone, Debug, PartialEq)]
pub enum TensorData {
    /// `F32`: parameters.
    F32(Vec<f32>),
    /// `F64`: normaliser statistics.
    F64(Vec<f64>),
    /// `U8`: opaque sections (optimiser state, environment state).
    U8(Vec<u8>),
}

impl TensorData {
    /// The format's element type.
    fn dtype(&self) -> Dtype {
        match self {
            Self::F32(_) => Dtype::F32,
            Self::F64(_) => Dtype::F64,
            Self::U8(_) => Dtype::U8,
        }
    }

    /// The elements as little-endian bytes.
    fn to_le_bytes(&self) -> Vec<u8> {
        match self {
            Self::F32(v) => v.iter().flat_map(|x| x.to_le_bytes()).collect(),
            Self::F64(v) => v.iter().flat_map(|x| x.to_le_bytes()).collect(),
            Self::U8(v) => v.clone(),
        }
    }

    /// Tensor `name`'s elements from its bytes (whose length the crate checked against its
    /// shape and dtype).
    fn read(name: &str, dtype: Dtype, bytes: &[u8]) -> Result<Self, TensorFileError> {
        Ok(match dtype {
            Dtype::F32 => Self::F32(bytes.chunks_exact(4).map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]])).collect()),
            Dtype::F64 => {
                Self::F64(bytes.chunks_exact(8).map(|c| f64::from_le_bytes([c[0], c[1], c[2], c[3], c[4], c[5], c[6], c[7]])).collect())
            }
            Dtype::U8 => Self::U8(bytes.to_vec()),
            other => return Err(TensorFileError::Malformed(format!("tensor {name}: dtype {other} is not one we write"))),
        })
    }
}

/// One named tensor.
#[derive(Clone, Debug, PartialEq)]
pub struct Tensor {
    /// Dimensions, row-major.
    pub shape: Vec<usize>,
    /// Elements.
    pub data: TensorData,
}

impl Tensor {
    /// A vector of bytes.
    pub fn bytes(data: Vec<u8>) -> Self {
        Self { shape: vec![data.len()], data: TensorData::U8(data) }
    }
}

/// A safetensors file in memory: metadata and tensors by name.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct TensorFile {
    /// The `__metadata__` map (without our `crc32`: added on writing, checked on reading).
    pub metadata: BTreeMap<String, String>,
    /// Tensors by name.
    pub tensors: BTreeMap<String, Tensor>,
}

/// Why bytes are not a file of ours.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum TensorFileError {
    /// Too short for its header.
    #[error("truncated: {0}")]
    Truncated(String),
    /// The header or a tensor entry is malformed.
    #[error("malformed: {0}")]
    Malformed(String),
    /// The checksum does not match the contents.
    #[error("checksum mismatch: the contents were altered")]
    Checksum,
}

/// CRC-32 of the metadata entries, each tensor's name, dtype and shape, and the tensors' bytes,
/// all in name order (so the same for any layout of the data).
fn checksum(metadata: &BTreeMap<String, String>, tensors: &BTreeMap<String, Tensor>) -> String {
    let mut h = crc32fast::Hasher::new();
    let mut field = |bytes: &[u8]| {
        h.update(bytes);
        h.update(&[0]);
    };
    for (k, v) in metadata {
        field(k.as_bytes());
        field(v.as_bytes());
    }
    for (name, tensor) in tensors {
        field(name.as_bytes());
        field(tensor.data.dtype().to_string().as_bytes());
        field(format!("{:?}", tensor.shape).as_bytes());
    }
    for tensor in tensors.values() {
        h.update(&tensor.data.to_le_bytes());
    }
    format!("{:08x}", h.finalize())
}

/// `header` (the JSON between the length prefix and the data) in canonical form: keys sorted,
/// no whitespace, padded with spaces so that the data starts at a multiple of 8 bytes, as the
/// format's crate pads.
fn canonical_header(header: &[u8]) -> Result<Vec<u8>, TensorFileError> {
    let value: Value = serde_json::from_slice(header).map_err(|e| TensorFileError::Malformed(format!("header: {e}")))?;
    let mut canonical = serde_json::to_vec(&value).map_err(|e| TensorFileError::Malformed(format!("header: {e}")))?;
    while !(8 + canonical.len()).is_multiple_of(8) {
        canonical.push(b' ');
    }
    Ok(canonical)
}

/// The crate's error as ours.
fn format_error(e: SafeTensorError) -> TensorFileError {
    match e {
        SafeTensorError::HeaderTooSmall | SafeTensorError::InvalidHeaderLength => TensorFileError::Truncated(e.to_string()),
        SafeTensorError::MetadataIncompleteBuffer => {
            TensorFileError::Malformed("tensor bytes outside the data: the file is cut short or has bytes after the last tensor".into())
        }
        other => TensorFileError::Malformed(other.to_string()),
    }
}

impl TensorFile {
    /// Encodes the file: the data laid out by the format's crate, the header canonical.
    #[allow(clippy::expect_used, reason = "tensors whose shape matches their data and a header the crate wrote always encode")]
    pub fn to_bytes(&self) -> Vec<u8> {
        let mut metadata: std::collections::HashMap<String, String> = self.metadata.clone().into_iter().collect();
        metadata.insert("crc32".into(), checksum(&self.metadata, &self.tensors));
        let bytes: Vec<(&String, Dtype, &[usize], Vec<u8>)> =
            self.tensors.iter().map(|(name, t)| (name, t.data.dtype(), t.shape.as_slice(), t.data.to_le_bytes())).collect();
        let views = bytes.iter().map(|(name, dtype, shape, data)| {
            (name.as_str(), TensorView::new(*dtype, shape.to_vec(), data).expect("a tensor's shape matches its data"))
        });
        let written = safetensors::serialize(views, Some(metadata)).expect("our tensors encode");
        let length = header_length(&written).expect("the crate wrote a header");
        let header = canonical_header(&written[8..8 + length]).expect("the crate wrote JSON");
        let mut out = Vec::with_capacity(8 + header.len() + written.len() - 8 - length);
        out.extend_from_slice(&(header.len() as u64).to_le_bytes());
        out.extend(header);
        out.extend_from_slice(&written[8 + length..]);
        out
    }

    /// True when `bytes` start like a file of ours (rather than an older format).
    pub fn sniff(bytes: &[u8]) -> bool {
        bytes.len() >= 8 + HEADER_START.len() && bytes[8..8 + HEADER_START.len()] == *HEADER_START
    }

    /// Decodes and verifies a file: the format's own checks (every tensor's range inside the
    /// data and matching its shape, the ranges covering the data exactly), a canonical header,
    /// and the checksum.
    pub fn from_bytes(bytes: &[u8]) -> Result<Self, TensorFileError> {
        let length = header_length(bytes)?;
        let parsed = SafeTensors::deserialize(bytes).map_err(format_error)?;
        // The checksum cannot cover the header's own layout (whitespace, padding, key order):
        // a file of ours is accepted only with its header in canonical form.
        if canonical_header(&bytes[8..8 + length])? != bytes[8..8 + length] {
            return Err(TensorFileError::Malformed("the header is not laid out as dronerace writes it (altered?)".into()));
        }
        let (_, metadata) = SafeTensors::read_metadata(bytes).map_err(format_error)?;
        let mut file = Self::default();
        if let Some(map) = metadata.metadata() {
            file.metadata = map.iter().map(|(k, v)| (k.clone(), v.clone())).collect();
        }
        for (name, view) in parsed.tensors() {
            let data = TensorData::read(&name, view.dtype(), view.data())?;
            file.tensors.insert(name, Tensor { shape: view.shape().to_vec(), data });
        }
        let crc = file.metadata.remove("crc32").ok_or_else(|| TensorFileError::Malformed("no crc32 in the metadata".into()))?;
        if crc != checksum(&file.metadata, &file.tensors) {
            return Err(TensorFileError::Checksum);
        }
        Ok(file)
    }

    /// A metadata entry, or an error naming it.
    pub fn meta(&self, key: &str) -> Result<&str, TensorFileError> {
        self.metadata.get(key).map(String::as_str).ok_or_else(|| TensorFileError::Malformed(format!("no {key} in the metadata")))
    }

    /// A tensor, or an error naming it.
    pub fn tensor(&self, name: &str) -> Result<&Tensor, TensorFileError> {
        self.tensors.get(name).ok_or_else(|| TensorFileError::Malformed(format!("no tensor {name}")))
    }
}

/// The header length a file's first 8 bytes give, if the header is inside the file and no
/// longer than [`MAX_HEADER`] (a corrupt length must not make us allocate gigabytes).
fn header_length(bytes: &[u8]) -> Result<usize, TensorFileError> {
    let Some(prefix) = bytes.get(..8) else { return Err(TensorFileError::Truncated(format!("{} bytes", bytes.len()))) };
    let length = u64::from_le_bytes([prefix[0], prefix[1], prefix[2], prefix[3], prefix[4], prefix[5], prefix[6], prefix[7]]);
    let length = usize::try_from(length)
        .ok()
        .filter(|&n| n <= MAX_HEADER)
        .ok_or_else(|| TensorFileError::Malformed(format!("header length {length}")))?;
    if bytes.len() - 8 < length {
        return Err(TensorFileError::Truncated(format!("header of {length} bytes, {} present", bytes.len() - 8)));
    }
    Ok(length)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn file() -> TensorFile {
        let mut f = TensorFile::default();
        f.metadata.insert("format".into(), "test".into());
        f.tensors
            .insert("w".into(), Tensor { shape: vec![2, 3], data: TensorData::F32(vec![1.0, -2.5, 3.0, 0.0, f32::MIN_POSITIVE, 7.0]) });
        f.tensors.insert("mean".into(), Tensor { shape: vec![2], data: TensorData::F64(vec![0.1, -1e300]) });
        f.tensors.insert("state".into(), Tensor::bytes(vec![1, 2, 3]));
        f
    }

    #[test]
    fn round_trips_bit_exactly_with_an_aligned_header() {
        let bytes = file().to_bytes();
        assert!(TensorFile::sniff(&bytes));
        let header = u64::from_le_bytes(bytes[..8].try_into().unwrap()) as usize;
        assert_eq!((8 + header) % 8, 0);
        assert_eq!(TensorFile::from_bytes(&bytes).unwrap(), file());
    }

    #[test]
    fn altered_truncated_and_inconsistent_files_are_refused() {
        let bytes = file().to_bytes();
        let mut flipped = bytes.clone();
        *flipped.last_mut().unwrap() ^= 1;
        assert_eq!(TensorFile::from_bytes(&flipped), Err(TensorFileError::Checksum));
        assert!(matches!(TensorFile::from_bytes(&bytes[..bytes.len() - 1]), Err(TensorFileError::Malformed(_))));
        assert!(matches!(TensorFile::from_bytes(&bytes[..20]), Err(TensorFileError::Truncated(_))));
        let mut lying = bytes.clone();
        let at = lying.windows(5).position(|w| w == b"[2,3]").expect("the shape is in the header");
        lying[at + 1] = b'3';
        assert!(matches!(TensorFile::from_bytes(&lying), Err(TensorFileError::Malformed(_))));
        // A header whose layout changed but not its meaning: a padding space made a newline.
        let padded = (0..8)
            .map(|n| {
                let mut f = file();
                f.metadata.insert("pad".into(), "x".repeat(n));
                f.to_bytes()
            })
            .find(|b| b[8 + u64::from_le_bytes(b[..8].try_into().unwrap()) as usize - 1] == b' ')
            .expect("some length leaves padding");
        let mut respaced = padded.clone();
        respaced[8 + u64::from_le_bytes(padded[..8].try_into().unwrap()) as usize - 1] = b'\n';
        assert!(TensorFile::from_bytes(&padded).is_ok());
        assert!(matches!(TensorFile::from_bytes(&respaced), Err(TensorFileError::Malformed(m)) if m.contains("laid out")));
        let mut huge = bytes;
        huge[..8].copy_from_slice(&u64::MAX.to_le_bytes());
        assert!(matches!(TensorFile::from_bytes(&huge), Err(TensorFileError::Malformed(_))));
    }

    /// Files written before the format's crate wrote ours (the data in name order) still read,
    /// with the same checksum: the shipped generalist is one.
    #[test]
    fn a_file_of_the_earlier_layout_reads_and_rewrites_to_the_same_contents() {
        let path = concat!(env!("CARGO_MANIFEST_DIR"), "/../policies/generalist.bin");
        let old = std::fs::read(path).unwrap();
        let file = TensorFile::from_bytes(&old).unwrap();
        assert!(file.tensors.len() > 4 && file.metadata.contains_key("architecture"));
        let again = TensorFile::from_bytes(&file.to_bytes()).unwrap();
        assert_eq!(again, file);
    }

    #[test]
    fn equal_contents_encode_to_equal_bytes() {
        assert_eq!(file().to_bytes(), file().to_bytes());
        let mut other = file();
        other.metadata.insert("a".into(), "b".into());
        other.metadata.insert("z".into(), "y".into());
        assert_eq!(other.to_bytes(), other.clone().to_bytes());
    }
}
