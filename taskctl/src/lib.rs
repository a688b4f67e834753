//! The curriculum: task switching (`switching`), the task controller that owns every
//! environment's track (`controller`), its gRPC service (`grpc`) and a blocking client
//! (`client`). Tracks themselves come from the `racetracks` crate.

pub mod client;
pub mod controller;
pub mod grpc;
pub mod switching;

pub use controller::{ActorRange, EnvSlot, SnapshotError, SwitchEvent, TaskController, TaskError};
pub use switching::{SwitchParams, SwitchPolicy};
