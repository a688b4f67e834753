//! Bounds-checked little-endian reading, shared by the weights blob and the rollout wire format.

/// The input ended `needed` bytes short of a field starting at `at`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct Truncated {
    pub needed: usize,
    pub at: usize,
}

/// Reads fields in order, refusing to run past the end (and never allocating for a length the
/// input cannot hold).
pub(crate) struct Reader<'a> {
    bytes: &'a [u8],
    at: usize,
}

impl<'a> Reader<'a> {
    pub fn new(bytes: &'a [u8], at: usize) -> Self {
        Self { bytes, at }
    }

    pub fn remaining(&self) -> usize {
        self.bytes.len() - self.at
    }

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

    pub fn u8(&mut self) -> Result<u8, Truncated> {
        Ok(self.take(1)?[0])
    }

    pub fn u32(&mut self) -> Result<u32, Truncated> {
        Ok(u32::from_le_bytes(self.array()?))
    }

    pub fn u64(&mut self) -> Result<u64, Truncated> {
        Ok(u64::from_le_bytes(self.array()?))
    }

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
pub(crate) fn put_f32s(out: &mut Vec<u8>, values: &[f32]) {
    out.reserve(values.len() * 4);
    for v in values {
        out.extend_from_slice(&v.to_le_bytes());
    }
}
