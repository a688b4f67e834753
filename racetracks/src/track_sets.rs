//! The held-out track sets and the seed ranges they own: a *validation* set for choosing
//! checkpoints and defaults, and the *test* set of SPEC §9 for reporting. Training draws its
//! generator seeds from hashes and skips this reserved range, so neither set is ever trained on.

use std::ops::Range;

use sim::Track;

use crate::generator::{GenerateError, TrackGenerator};
use crate::track_file::TrackFileError;

/// First generator seed of the validation set (tracks `val-8000000`, `val-8000001`, …).
pub const VALIDATION_SEED: u64 = 8_000_000;
/// First generator seed of the default test set's generated tracks (SPEC §9).
pub const TEST_SEED: u64 = 9_000_000;
/// Tracks in the test set: the library topped up with generated tracks.
pub const TEST_SET_SIZE: usize = 40;
/// Seeds that training never uses: validation from 8,000,000, test from 9,000,000.
pub const HELD_OUT_SEEDS: Range<u64> = VALIDATION_SEED..TEST_SEED + 1_000_000;

/// True for a seed that belongs to the validation or the test range.
pub fn is_held_out(seed: u64) -> bool {
    HELD_OUT_SEEDS.contains(&seed)
}

/// Why a held-out set cannot be built.
#[derive(Debug, thiserror::Error)]
pub enum TrackSetError {
    /// A generated member failed.
    #[error(transparent)]
    Generate(#[from] GenerateError),
    /// The library could not be read.
    #[error(transparent)]
    Library(#[from] TrackFileError),
    /// More validation tracks than the range holds (counted from its start).
    #[error("validation tracks up to the {0}th asked for: the validation range holds 1,000,000")]
    TooLarge(usize),
}

/// `count` informed tracks from the validation range.
pub fn validation_set(count: usize) -> Result<Vec<Track>, TrackSetError> {
    validation_tracks(0, count)
}

/// `count` informed tracks of the validation range from its `first`-th on: tracks a run's
/// validation (which reads the first ones) never saw, when `first` is at least its count.
pub fn validation_tracks(first: usize, count: usize) -> Result<Vec<Track>, TrackSetError> {
    if first.saturating_add(count) > (TEST_SEED - VALIDATION_SEED) as usize {
        return Err(TrackSetError::TooLarge(first.saturating_add(count)));
    }
    generated(VALIDATION_SEED + first as u64, count, "val")
}

/// The test set: the hand-designed library, then generated tracks from `seed`, `seed + 1`, …
/// up to [`TEST_SET_SIZE`] (`tracks testset` writes exactly these).
pub fn test_set(seed: u64) -> Result<Vec<Track>, TrackSetError> {
    let mut tracks = crate::library()?;
    let generated_count = TEST_SET_SIZE.saturating_sub(tracks.len());
    tracks.extend(generated(seed, generated_count, "test")?);
    Ok(tracks)
}

fn generated(first_seed: u64, count: usize, prefix: &str) -> Result<Vec<Track>, TrackSetError> {
    let generator = TrackGenerator::default();
    (0..count as u64).map(|i| Ok(generator.generate(first_seed + i, &format!("{prefix}-{}", first_seed + i))?.track)).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn validation_and_test_ranges_are_disjoint_and_held_out() {
        let validation = VALIDATION_SEED..TEST_SEED;
        let test = TEST_SEED..HELD_OUT_SEEDS.end;
        assert!(validation.end <= test.start, "validation ends before test begins");
        for seed in [VALIDATION_SEED, TEST_SEED - 1, TEST_SEED, TEST_SEED + 30] {
            assert!(is_held_out(seed), "{seed}");
        }
        assert!(!is_held_out(VALIDATION_SEED - 1) && !is_held_out(HELD_OUT_SEEDS.end));
    }

    #[test]
    fn sets_are_named_by_their_seeds_and_reproducible() {
        let v = validation_set(3).unwrap();
        let names: Vec<&str> = v.iter().map(|t| t.name.as_str()).collect();
        assert_eq!(names, ["val-8000000", "val-8000001", "val-8000002"]);
        assert_eq!(v, validation_set(3).unwrap());
        // Later tracks of the range continue the same sequence.
        assert_eq!(validation_tracks(1, 2).unwrap(), v[1..]);
        assert!(matches!(validation_tracks(999_999, 2), Err(TrackSetError::TooLarge(1_000_001))));
        let t = test_set(TEST_SEED).unwrap();
        assert_eq!(t.len(), TEST_SET_SIZE);
        assert_eq!(t.last().unwrap().name, format!("test-{}", TEST_SEED + (TEST_SET_SIZE - crate::library().unwrap().len()) as u64 - 1));
        // No validation track is a test track.
        assert!(v.iter().all(|a| t.iter().all(|b| a.gates != b.gates)));
    }
}
