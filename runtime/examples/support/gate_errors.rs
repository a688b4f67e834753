//! What the gate-placement analyses (`gate_probe`, `gate_localisation`, `label_gap`) share:
//! the distance bins they tabulate by, so their tables line up row for row, and the angle by
//! which a predicted corner direction misses the true one.

/// Distance bins (m) from the drone to the target gate's centre: below each bound.
pub const BINS: [(f64, &str); 4] = [(1.0, "< 1 m"), (2.0, "1-2 m"), (4.0, "2-4 m"), (f64::INFINITY, "> 4 m")];

/// Index into [`BINS`] of a distance (m); anything not below a bound goes to the last bin.
pub fn bin_of(distance: f64) -> usize {
    BINS.iter().position(|(bound, _)| distance < *bound).unwrap_or(BINS.len() - 1)
}

/// The angle (rad) between a true and a predicted direction (3 numbers each, any length).
#[allow(dead_code, reason = "label_gap tabulates by distance only")]
pub fn angle_between(truth: &[f32], guess: &[f32]) -> f64 {
    let dot: f32 = truth.iter().zip(guess).map(|(a, b)| a * b).sum();
    let norms = truth.iter().map(|v| v * v).sum::<f32>().sqrt() * guess.iter().map(|v| v * v).sum::<f32>().sqrt();
    f64::from((dot / norms.max(1e-9)).clamp(-1.0, 1.0)).acos()
}
