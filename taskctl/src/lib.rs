//! Racetracks: track files, the hand-designed library, generation and task switching.

pub mod generator;
pub mod library;
pub mod spline;
pub mod track_file;

pub use library::{library, library_track};
pub use track_file::{TrackFileError, parse_track, read_track, read_track_dir, track_to_toml, write_track};
