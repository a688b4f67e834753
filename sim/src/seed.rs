//! Deterministic seed derivation shared by every crate that draws randomness from inputs alone
//! (track seeds, actor seeds, learner epochs).

/// SplitMix64: a well-mixed 64-bit hash, for draws that depend only on their inputs.
pub fn mix(mut x: u64) -> u64 {
    x = x.wrapping_add(0x9E37_79B9_7F4A_7C15);
    let mut z = x;
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}
