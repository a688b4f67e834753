//! The one frame codec of dronerace's hand-framed bytes (rollout chunks on the wire, task-
//! controller snapshots on disk; tensors travel as safetensors instead): an 8-byte magic, a
//! format version, the body's length, the body and a CRC-32 of everything before it, plus the
//! bounded reader their bodies are parsed with.
//!
//! Layout: magic `[u8; 8]`, format u32, body length u64, body, CRC-32 u32 (little-endian).

/// Bytes around the body: magic, format, length before it, CRC after.
pub const OVERHEAD: usize = 8 + 4 + 8 + 4;

/// Why bytes are not an intact frame of the expected kind.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum FrameError {
    /// Another kind of file or message.
    #[error("not a {kind} (bad magic)")]
    BadMagic {
        /// What was expected, e.g. "rollout chunk".
        kind: &'static str,
    },
    /// A format version this build does not read.
    #[error("{kind} format {found}; this build reads format {reads}")]
    UnsupportedFormat {
        /// What was expected.
        kind: &'static str,
        /// Version found.
        found: u32,
        /// Version this build reads.
        reads: u32,
    },
    /// Shorter or longer than its header says.
    #[error("{kind} is truncated or padded: {found} bytes where the header says {expected}")]
    Length {
        /// What was expected.
        kind: &'static str,
        /// Bytes the header announces (whole frame).
        expected: u64,
        /// Bytes present.
        found: usize,
    },
    /// The checksum does not match the contents.
    #[error("{kind} checksum mismatch: the contents were altered")]
    Checksum {
        /// What was expected.
        kind: &'static str,
    },
}

/// A kind of frame: its magic, the format version written, and a name for errors.
#[derive(Clone, Copy, Debug)]
pub struct FrameKind {
    /// First 8 bytes.
    pub magic: &'static [u8; 8],
    /// Format version this build writes and reads.
    pub format: u32,
    /// Name in errors, e.g. "rollout chunk".
    pub name: &'static str,
}

impl FrameKind {
    /// Frames `body`.
    pub fn encode(&self, body: &[u8]) -> Vec<u8> {
        let mut out = Vec::with_capacity(OVERHEAD + body.len());
        out.extend_from_slice(self.magic);
        out.extend_from_slice(&self.format.to_le_bytes());
        out.extend_from_slice(&(body.len() as u64).to_le_bytes());
        out.extend_from_slice(body);
        let crc = crc32fast::hash(&out);
        out.extend_from_slice(&crc.to_le_bytes());
        out
    }

    /// The body of an intact frame of this kind: magic, format, length and checksum verified.
    pub fn decode<'a>(&self, bytes: &'a [u8]) -> Result<&'a [u8], FrameError> {
        let kind = self.name;
        if !bytes.starts_with(self.magic) {
            return Err(FrameError::BadMagic { kind });
        }
        let mut r = Reader::new(bytes, self.magic.len());
        let short = |_| FrameError::Length { kind, expected: OVERHEAD as u64, found: bytes.len() };
        let format = r.u32().map_err(short)?;
        if format != self.format {
            return Err(FrameError::UnsupportedFormat { kind, found: format, reads: self.format });
        }
        let length = r.u64().map_err(short)?;
        let expected = length.saturating_add(OVERHEAD as u64);
        if expected != bytes.len() as u64 {
            return Err(FrameError::Length { kind, expected, found: bytes.len() });
        }
        let (framed, crc) = bytes.split_at(bytes.len() - 4);
        if crc32fast::hash(framed).to_le_bytes() != crc {
            return Err(FrameError::Checksum { kind });
        }
        Ok(&framed[OVERHEAD - 4..])
    }
}

/// The input ended `needed` bytes short of a field starting at `at`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Truncated {
    /// Bytes missing.
    pub needed: usize,
    /// Offset of the field.
    pub at: usize,
}

/// Reads fields in order, refusing to run past the end (and never allocating for a length the
/// input cannot hold).
pub struct Reader<'a> {
    bytes: &'a [u8],
    at: usize,
}

impl<'a> Reader<'a> {
    /// Reads `bytes` from offset `at`.
    pub fn new(bytes: &'a [u8], at: usize) -> Self {
        Self { bytes, at }
    }

    /// Bytes left after the read position.
    pub fn remaining(&self) -> usize {
        self.bytes.len() - self.at
    }

    /// The next `n` bytes.
    pub fn take(&mut self, n: usize) -> Result<&'a [u8], Truncated> {
        let end = self.at.checked_add(n).filter(|&e| e <= self.bytes.len());
        let end = end.ok_or(Truncated { needed: n.saturating_sub(self.remaining()), at: self.at })?;
        let slice = &self.bytes[self.at..end];
        self.at = end;
        Ok(slice)
    }

    /// A capacity to reserve for `count` items of at least `min_bytes` each: never more than
    /// the remaining input can hold, whatever a corrupt count field says.
    pub fn capacity_for(&self, count: usize, min_bytes: usize) -> usize {
        count.min(self.remaining() / min_bytes.max(1))
    }

    /// The next `N` bytes as an array.
    pub fn array<const N: usize>(&mut self) -> Result<[u8; N], Truncated> {
        let mut out = [0u8; N];
        out.copy_from_slice(self.take(N)?);
        Ok(out)
    }

    /// A byte.
    pub fn u8(&mut self) -> Result<u8, Truncated> {
        Ok(self.take(1)?[0])
    }

    /// A little-endian u32.
    pub fn u32(&mut self) -> Result<u32, Truncated> {
        Ok(u32::from_le_bytes(self.array()?))
    }

    /// A little-endian u64.
    pub fn u64(&mut self) -> Result<u64, Truncated> {
        Ok(u64::from_le_bytes(self.array()?))
    }

    /// A little-endian f64.
    pub fn f64(&mut self) -> Result<f64, Truncated> {
        Ok(f64::from_le_bytes(self.array()?))
    }

    /// `n` f32 values; a count whose byte length overflows is reported as truncation.
    pub fn f32s(&mut self, n: usize) -> Result<Vec<f32>, Truncated> {
        let len = n.checked_mul(4).ok_or(Truncated { needed: usize::MAX, at: self.at })?;
        Ok(self.take(len)?.chunks_exact(4).map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]])).collect())
    }

    /// `n` booleans stored one byte each; anything but 0 or 1 is refused as `None`.
    pub fn bools(&mut self, n: usize) -> Result<Option<Vec<bool>>, Truncated> {
        let raw = self.take(n)?;
        Ok(raw
            .iter()
            .map(|&b| match b {
                0 => Some(false),
                1 => Some(true),
                _ => None,
            })
            .collect())
    }
}

/// Appends little-endian f32 values.
pub fn put_f32s(out: &mut Vec<u8>, values: &[f32]) {
    out.reserve(values.len() * 4);
    for v in values {
        out.extend_from_slice(&v.to_le_bytes());
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const KIND: FrameKind = FrameKind { magic: b"DRTEST01", format: 3, name: "test frame" };

    #[test]
    fn a_frame_round_trips_and_every_kind_of_damage_is_named() {
        let bytes = KIND.encode(b"hello");
        assert_eq!(KIND.decode(&bytes), Ok(&b"hello"[..]));
        assert_eq!(KIND.decode(&KIND.encode(b"")), Ok(&b""[..]));
        let other = FrameKind { magic: b"DRTEST02", ..KIND };
        assert_eq!(other.decode(&bytes), Err(FrameError::BadMagic { kind: "test frame" }));
        let newer = FrameKind { format: 4, ..KIND };
        assert_eq!(newer.decode(&bytes), Err(FrameError::UnsupportedFormat { kind: "test frame", found: 3, reads: 4 }));
        assert!(matches!(KIND.decode(&bytes[..bytes.len() - 1]), Err(FrameError::Length { expected: 29, found: 28, .. })));
        assert!(matches!(KIND.decode(&bytes[..10]), Err(FrameError::Length { .. })));
        let mut altered = bytes.clone();
        altered[21] ^= 1;
        assert_eq!(KIND.decode(&altered), Err(FrameError::Checksum { kind: "test frame" }));
        let mut lying = bytes;
        lying[12..20].copy_from_slice(&u64::MAX.to_le_bytes());
        assert!(matches!(KIND.decode(&lying), Err(FrameError::Length { expected: u64::MAX, .. })));
    }

    #[test]
    fn the_reader_refuses_to_run_past_the_end() {
        let mut r = Reader::new(&[1, 0, 0, 0, 2], 0);
        assert_eq!(r.u32(), Ok(1));
        assert_eq!(r.u32(), Err(Truncated { needed: 3, at: 4 }));
        assert_eq!(r.f32s(usize::MAX).unwrap_err().at, 4);
        assert_eq!(r.capacity_for(1 << 40, 8), 0);
    }
}
