//! Racetracks without networking: track files, the hand-designed library, the closed smoothing
//! spline (FITPACK-equivalent), the informed and uniform generators, and the held-out
//! validation and test sets. Anything that only reads or makes tracks links this crate alone.

pub mod generator;
pub mod library;
pub mod ood;
pub mod spline;
pub mod track_file;
pub mod track_sets;

pub use generator::{GenerateError, GeneratorKind, Rejection, TrackGenParams, TrackGenerator, WriteTracksError};
pub use library::{ChosenTracksError, chosen_tracks, library, library_track};
pub use track_file::{TrackFileError, parse_track, read_track, read_track_dir, track_from_csv, track_to_toml, write_track};
pub use track_sets::{TrackSetError, test_set, validation_set, validation_tracks};
