//! Racetracks and the curriculum: track files, the hand-designed library, the closed smoothing
//! spline, track generators, and task switching with the task controller, its gRPC service
//! and a blocking client.

pub mod client;
pub mod controller;
pub mod files;
pub mod generator;
pub mod grpc;
pub mod library;
pub mod spline;
pub mod switching;
pub mod track_file;
pub mod track_sets;

pub use controller::{ActorRange, EnvSlot, SnapshotError, SwitchEvent, TaskController, TaskError};
pub use generator::{GenerateError, GeneratorKind, TrackGenParams, TrackGenerator};
pub use library::{library, library_track};
pub use switching::{SwitchParams, SwitchPolicy};
pub use track_file::{TrackFileError, parse_track, read_track, read_track_dir, track_to_toml, write_track};
pub use track_sets::{TrackSetError, test_set, validation_set};
