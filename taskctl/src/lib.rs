//! The curriculum: task switching (`switching`), the task controller that owns every
//! environment's track (`controller`), the same as a service with no transport in it
//! (`service`), its gRPC adapter (`grpc`) and a client implementing the service over gRPC
//! (`client`). Tracks themselves come from the `racetracks` crate.

pub mod client;
pub mod controller;
pub mod grpc;
pub mod service;
pub mod switching;

pub use controller::{ActorRange, EnvSlot, SnapshotError, SwitchEvent, TaskController, TaskError};
pub use service::{LocalTasks, Registration, Summary, TaskEvent, TaskInfo, TaskService, TaskServiceError};
pub use switching::{SwitchParams, SwitchPolicy};
