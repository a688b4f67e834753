//! The distance bins that the analysis examples (`gate_probe`, `label_gap`) tabulate by, so
//! their tables line up row for row.

/// Distance bins (m) from the drone to the target gate's centre: below each bound.
pub const BINS: [(f64, &str); 4] = [(1.0, "< 1 m"), (2.0, "1-2 m"), (4.0, "2-4 m"), (f64::INFINITY, "> 4 m")];

/// Index into [`BINS`] of a distance (m); anything not below a bound goes to the last bin.
pub fn bin_of(distance: f64) -> usize {
    BINS.iter().position(|(bound, _)| distance < *bound).unwrap_or(BINS.len() - 1)
}
