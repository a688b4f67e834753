//! The curriculum: task switching (`switching`), the task controller that owns every
//! environment's track (`controller`) and the same as a service with no transport in it
//! (`service`). Tracks themselves come from the `racetracks` crate; the service's gRPC adapter
//! and client live with the other adapters, in `proto` (`task_grpc`, `task_client`).

pub mod bench;
pub mod controller;
pub mod service;
pub mod switching;

pub use controller::{ActorRange, EnvSlot, SnapshotError, SwitchEvent, TaskController, TaskError};
pub use service::{LocalTasks, Registration, Summary, TaskEvent, TaskInfo, TaskService, TaskServiceError};
pub use switching::{InvalidSwitchParams, SwitchParams, SwitchPolicy};
