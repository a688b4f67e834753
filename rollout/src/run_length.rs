//! Run-length coding of camera images for the wire. The renderer draws flat grey gate frames
//! on a black background, so an 84×84 image is a few hundred runs: each run is its byte value
//! and its length (u16, little-endian), 3 bytes for up to 65,535 equal bytes. Measured on
//! training flights, a 7,056-byte image takes ~0.4 kB (docs/notebook/vision.md, "Images on the wire").

/// Appends the run-length code of `bytes` to `out`.
pub fn encode(bytes: &[u8], out: &mut Vec<u8>) {
    let mut rest = bytes;
    while let Some(&value) = rest.first() {
        let run = rest.iter().take(u16::MAX as usize).take_while(|&&b| b == value).count();
        out.push(value);
        out.extend_from_slice(&(run as u16).to_le_bytes());
        rest = &rest[run..];
    }
}

/// Decodes `code` into exactly `len` bytes; `None` when the code is malformed (a zero-length
/// run, a cut-off run) or decodes to another length. Never allocates beyond `len`.
pub fn decode(code: &[u8], len: usize) -> Option<Vec<u8>> {
    if !code.len().is_multiple_of(3) {
        return None;
    }
    let mut out = Vec::with_capacity(len.min(code.len() / 3 * u16::MAX as usize));
    for run in code.chunks_exact(3) {
        let count = u16::from_le_bytes([run[1], run[2]]) as usize;
        if count == 0 || out.len() + count > len {
            return None;
        }
        out.resize(out.len() + count, run[0]);
    }
    (out.len() == len).then_some(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trips_and_refuses_malformed_codes() {
        let mut image = vec![0u8; 70_000];
        image[5..9].fill(255);
        image[100..300].fill(55);
        image[69_999] = 155;
        let mut code = Vec::new();
        encode(&image, &mut code);
        assert_eq!(code.len(), 3 * 7, "runs: 0, 255, 0, 55, 0 (65,535 + the rest), 155");
        assert_eq!(decode(&code, image.len()).unwrap(), image);
        assert_eq!(decode(&code, image.len() - 1), None, "decodes to more than announced");
        assert_eq!(decode(&code, image.len() + 1), None, "decodes to less");
        assert_eq!(decode(&code[..code.len() - 1], image.len()), None, "a cut-off run");
        assert_eq!(decode(&[7, 0, 0], 0), None, "a zero-length run");
        let mut empty = Vec::new();
        encode(&[], &mut empty);
        assert_eq!((empty.len(), decode(&empty, 0)), (0, Some(Vec::new())));
    }
}
