//! Payloads larger than a gRPC message travel as numbered parts and are reassembled whole or
//! not at all: a stream that breaks mid-payload leaves nothing behind.

use prost::bytes::Bytes;

use crate::security::{MAX_PAYLOAD_BYTES, PART_BYTES};

/// Splits `payload` into `(part, parts, data)` pieces of at most [`PART_BYTES`].
pub fn split(payload: Bytes) -> Vec<(u32, u32, Bytes)> {
    let parts = payload.len().div_ceil(PART_BYTES).max(1) as u32;
    (0..parts)
        .map(|i| {
            let start = i as usize * PART_BYTES;
            let end = (start + PART_BYTES).min(payload.len());
            (i, parts, payload.slice(start..end))
        })
        .collect()
}

/// Why a part was refused; the payload it belonged to is dropped.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum PartError {
    /// A part announced a different part count than the payload's first part.
    #[error("part count changed from {was} to {now} within one payload")]
    CountChanged {
        /// Count announced by the first part.
        was: u32,
        /// Count announced now.
        now: u32,
    },
    /// A part arrived out of order (or a payload of zero parts).
    #[error("part {part} of {parts} where part {expected} was expected")]
    OutOfOrder {
        /// Part received.
        part: u32,
        /// Its part count.
        parts: u32,
        /// Part expected.
        expected: u32,
    },
    /// The parts add up to more than [`MAX_PAYLOAD_BYTES`].
    #[error("payload exceeds {MAX_PAYLOAD_BYTES} bytes")]
    TooLarge,
}

/// Collects the parts of one payload after another, in order.
#[derive(Default)]
pub struct Reassembler {
    buffer: Vec<u8>,
    expected: Option<(u32, u32)>,
}

impl Reassembler {
    /// Adds part `part` of `parts`; returns the whole payload with its last part. Parts out of
    /// order, a changing part count or more than [`MAX_PAYLOAD_BYTES`] are refused.
    pub fn push(&mut self, part: u32, parts: u32, data: &[u8]) -> Result<Option<Vec<u8>>, PartError> {
        let next = match self.expected {
            Some((_, total)) if total != parts => return Err(PartError::CountChanged { was: total, now: parts }),
            Some((next, _)) => next,
            None => 0,
        };
        if parts == 0 || part != next {
            return Err(PartError::OutOfOrder { part, parts, expected: next });
        }
        if self.buffer.len() + data.len() > MAX_PAYLOAD_BYTES {
            return Err(PartError::TooLarge);
        }
        self.buffer.extend_from_slice(data);
        if part + 1 == parts {
            self.expected = None;
            return Ok(Some(std::mem::take(&mut self.buffer)));
        }
        self.expected = Some((part + 1, parts));
        Ok(None)
    }

    /// Bytes of the payload collected so far.
    pub fn buffered(&self) -> usize {
        self.buffer.len()
    }

    /// True when a payload has begun but not ended.
    pub fn is_partial(&self) -> bool {
        self.expected.is_some()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn split_then_reassemble_is_the_identity_and_disorder_is_refused() {
        let payload: Vec<u8> = (0..(2 * PART_BYTES + 17)).map(|i| (i % 251) as u8).collect();
        let pieces = split(Bytes::from(payload.clone()));
        assert_eq!(pieces.len(), 3);
        let mut r = Reassembler::default();
        assert_eq!(r.push(0, 3, &pieces[0].2).unwrap(), None);
        assert!(r.is_partial());
        assert_eq!(r.push(2, 3, &pieces[2].2).unwrap_err(), PartError::OutOfOrder { part: 2, parts: 3, expected: 1 });
        let mut r = Reassembler::default();
        let mut out = None;
        for (i, n, d) in &pieces {
            out = r.push(*i, *n, d).unwrap();
        }
        assert_eq!(out.unwrap(), payload);
        assert_eq!(split(Bytes::new()).len(), 1, "an empty payload is one empty part");
    }
}
