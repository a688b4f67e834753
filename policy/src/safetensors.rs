//! The safetensors file format (huggingface/safetensors), written and read by hand: an 8-byte
//! little-endian header length, a JSON header naming each tensor's dtype, shape and byte range
//! plus a string-to-string `__metadata__` map, then the tensor bytes. Python's `safetensors`
//! package and burn's importers open these files as they are.
//!
//! What we add inside the format: metadata key `crc32`, the CRC-32 of every other metadata
//! entry (sorted, `key NUL value NUL`), every tensor's name, dtype and shape (sorted by name,
//! each followed by NUL) and the tensor bytes; and on reading the rule
//! that the file is byte for byte as we write it, so a corrupted file is refused rather than
//! half-used, as every other file of ours is.

use std::collections::BTreeMap;

use serde_json::{Map, Value};

/// The first bytes every file of ours starts with: a header length, then `{"__metadata__":`
/// (we write metadata first), which tells our files apart from the older framed formats.
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
    fn dtype(&self) -> &'static str {
        match self {
            Self::F32(_) => "F32",
            Self::F64(_) => "F64",
            Self::U8(_) => "U8",
        }
    }

    fn len(&self) -> usize {
        match self {
            Self::F32(v) => v.len(),
            Self::F64(v) => v.len(),
            Self::U8(v) => v.len(),
        }
    }

    fn byte_len(&self) -> usize {
        match self {
            Self::F32(v) => 4 * v.len(),
            Self::F64(v) => 8 * v.len(),
            Self::U8(v) => v.len(),
        }
    }

    fn write(&self, out: &mut Vec<u8>) {
        match self {
            Self::F32(v) => v.iter().for_each(|x| out.extend_from_slice(&x.to_le_bytes())),
            Self::F64(v) => v.iter().for_each(|x| out.extend_from_slice(&x.to_le_bytes())),
            Self::U8(v) => out.extend_from_slice(v),
        }
    }

    /// Tensor `name`'s elements from its byte range.
    fn read(name: &str, dtype: &str, bytes: &[u8]) -> Result<Self, TensorFileError> {
        let malformed = |what: String| TensorFileError::Malformed(format!("tensor {name}: {what}"));
        let exact = |size: usize| {
            if bytes.len().is_multiple_of(size) { Ok(()) } else { Err(malformed(format!("{} bytes of {dtype}", bytes.len()))) }
        };
        Ok(match dtype {
            "F32" => {
                exact(4)?;
                Self::F32(bytes.chunks_exact(4).map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]])).collect())
            }
            "F64" => {
                exact(8)?;
                Self::F64(bytes.chunks_exact(8).map(|c| f64::from_le_bytes([c[0], c[1], c[2], c[3], c[4], c[5], c[6], c[7]])).collect())
            }
            "U8" => Self::U8(bytes.to_vec()),
            other => return Err(malformed(format!("dtype {other} is not one we write"))),
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

/// CRC-32 of the metadata entries, each tensor's name, dtype and shape, and the tensor bytes.
fn checksum(metadata: &BTreeMap<String, String>, tensors: &BTreeMap<String, Tensor>, data: &[u8]) -> String {
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
        field(tensor.data.dtype().as_bytes());
        field(format!("{:?}", tensor.shape).as_bytes());
    }
    h.update(data);
    format!("{:08x}", h.finalize())
}

impl TensorFile {
    /// Encodes the file (tensors in name order; header padded with spaces to 8 bytes, as the
    /// reference implementation does, so data is aligned).
    pub fn to_bytes(&self) -> Vec<u8> {
        let mut data = Vec::with_capacity(self.tensors.values().map(|t| t.data.byte_len()).sum());
        for tensor in self.tensors.values() {
            tensor.data.write(&mut data);
        }
        let mut out = self.header(checksum(&self.metadata, &self.tensors, &data));
        out.extend(data);
        out
    }

    /// Everything before the tensor bytes — length prefix, JSON header with `crc`, padding —
    /// for the tensors laid out in name order.
    #[allow(clippy::expect_used, reason = "a JSON map of strings and numbers always serialises")]
    fn header(&self, crc: String) -> Vec<u8> {
        let mut metadata = self.metadata.clone();
        metadata.insert("crc32".into(), crc);
        // `__metadata__` first: it marks our files (HEADER_START) and reads well in a hex dump.
        let mut header = serde_json::to_vec(&Value::Object(Map::from_iter([("__metadata__".to_string(), serde_json::json!(metadata))])))
            .expect("metadata serialises");
        header.pop(); // the closing brace: tensor entries follow
        let mut start = 0;
        for (name, tensor) in &self.tensors {
            let end = start + tensor.data.byte_len();
            let entry = serde_json::json!({ "dtype": tensor.data.dtype(), "shape": tensor.shape, "data_offsets": [start, end] });
            start = end;
            header.push(b',');
            header.extend(serde_json::to_vec(name).expect("a string serialises"));
            header.push(b':');
            header.extend(serde_json::to_vec(&entry).expect("an entry serialises"));
        }
        header.push(b'}');
        while !(8 + header.len()).is_multiple_of(8) {
            header.push(b' ');
        }
        let mut out = Vec::with_capacity(8 + header.len() + start);
        out.extend_from_slice(&(header.len() as u64).to_le_bytes());
        out.extend(header);
        out
    }

    /// True when `bytes` start like a file of ours (rather than an older format).
    pub fn sniff(bytes: &[u8]) -> bool {
        bytes.len() >= 8 + HEADER_START.len() && bytes[8..8 + HEADER_START.len()] == *HEADER_START
    }

    /// Decodes and verifies a file: every tensor's range inside the data and matching its
    /// shape, the ranges covering the data exactly, and the checksum.
    pub fn from_bytes(bytes: &[u8]) -> Result<Self, TensorFileError> {
        let malformed = |m: String| TensorFileError::Malformed(m);
        let Some(length) = bytes.get(..8) else { return Err(TensorFileError::Truncated(format!("{} bytes", bytes.len()))) };
        let length = u64::from_le_bytes([length[0], length[1], length[2], length[3], length[4], length[5], length[6], length[7]]);
        let length =
            usize::try_from(length).ok().filter(|&n| n <= MAX_HEADER).ok_or_else(|| malformed(format!("header length {length}")))?;
        let header = bytes
            .get(8..8 + length)
            .ok_or_else(|| TensorFileError::Truncated(format!("header of {length} bytes, {} present", bytes.len() - 8)))?;
        let data = &bytes[8 + length..];
        let header: Map<String, Value> = serde_json::from_slice(header).map_err(|e| malformed(format!("header: {e}")))?;
        let mut file = Self::default();
        let mut ranges = Vec::new();
        for (name, entry) in header {
            if name == "__metadata__" {
                let map = entry.as_object().ok_or_else(|| malformed("__metadata__ is not a map".into()))?;
                for (k, v) in map {
                    let v = v.as_str().ok_or_else(|| malformed(format!("metadata {k} is not a string")))?;
                    file.metadata.insert(k.clone(), v.to_owned());
                }
                continue;
            }
            let field = |key: &str| entry.get(key).ok_or_else(|| malformed(format!("tensor {name}: no {key}")));
            let dtype = field("dtype")?.as_str().ok_or_else(|| malformed(format!("tensor {name}: dtype")))?;
            let numbers = |key: &str| -> Result<Vec<usize>, TensorFileError> {
                let list = field(key)?.as_array().ok_or_else(|| malformed(format!("tensor {name}: {key} is not a list")))?;
                list.iter()
                    .map(|v| v.as_u64().and_then(|n| usize::try_from(n).ok()).ok_or_else(|| malformed(format!("tensor {name}: {key}"))))
                    .collect()
            };
            let shape = numbers("shape")?;
            let [start, end] = numbers("data_offsets")?[..] else { return Err(malformed(format!("tensor {name}: data_offsets"))) };
            let span = data.get(start..end).ok_or_else(|| malformed(format!("tensor {name}: bytes {start}..{end} outside the data")))?;
            let tensor = TensorData::read(&name, dtype, span)?;
            let numel = shape.iter().try_fold(1usize, |n, &d| n.checked_mul(d));
            if numel != Some(tensor.len()) {
                return Err(malformed(format!("tensor {name}: shape {shape:?} holds {numel:?} elements, the data {}", tensor.len())));
            }
            ranges.push((start, end));
            file.tensors.insert(name, Tensor { shape, data: tensor });
        }
        ranges.sort_unstable();
        let mut covered = 0;
        for (start, end) in ranges {
            if start != covered {
                return Err(malformed(format!("tensor data has a gap or an overlap at byte {start}")));
            }
            covered = end;
        }
        if covered != data.len() {
            return Err(malformed(format!("{} bytes after the last tensor", data.len() - covered)));
        }
        let crc = file.metadata.remove("crc32").ok_or_else(|| malformed("no crc32 in the metadata".into()))?;
        if crc != checksum(&file.metadata, &file.tensors, data) {
            return Err(TensorFileError::Checksum);
        }
        // The checksum cannot cover the header's own layout (whitespace, padding, key order):
        // a file of ours is accepted only with exactly the header we write.
        if file.header(crc) != bytes[..8 + length] {
            return Err(TensorFileError::Malformed("the header is not laid out as dronerace writes it (altered?)".into()));
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
        assert!(matches!(TensorFile::from_bytes(&lying), Err(TensorFileError::Malformed(m)) if m.contains("shape")));
        let mut huge = bytes;
        huge[..8].copy_from_slice(&u64::MAX.to_le_bytes());
        assert!(matches!(TensorFile::from_bytes(&huge), Err(TensorFileError::Malformed(_))));
    }
}
