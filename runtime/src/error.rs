//! Why a run cannot start or go on ([`TrainError`]), and which config setting is to blame
//! ([`ConfigError`]).

use std::path::{Path, PathBuf};

use learner::checkpoint::CheckpointError;
use learner::learner::LearnerError;

/// A setting of a run config that cannot be used, named as the file spells it.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
#[error("{}{}{message}", file.as_ref().map_or(String::new(), |f| format!("{}: ", f.display())), if field.is_empty() { String::new() } else { format!("{field}: ") })]
pub struct ConfigError {
    /// The config file, when the config came from one.
    pub file: Option<PathBuf>,
    /// The dotted field (`ppo.gamma`, `learner.actor_timeout_seconds`); empty for text that is
    /// not a config at all (toml's message then names the line and key).
    pub field: String,
    /// What is wrong with it.
    pub message: String,
}

impl ConfigError {
    /// An error in `field`.
    pub fn new(field: impl Into<String>, message: impl Into<String>) -> Self {
        Self { file: None, field: field.into(), message: message.into() }
    }

    /// The same error, in `file`.
    pub fn in_file(self, file: &Path) -> Self {
        Self { file: Some(file.to_path_buf()), ..self }
    }
}

/// Why training cannot go on.
#[derive(Debug, thiserror::Error)]
pub enum TrainError {
    /// Bad configuration.
    #[error("config: {0}")]
    Config(#[from] ConfigError),
    /// The run directory holds no run to resume, or one that must not be started again.
    #[error("{}: {message}", dir.display())]
    RunDirectory {
        /// The run directory.
        dir: PathBuf,
        /// What is wrong.
        message: String,
    },
    /// Learner refused a rollout or a state.
    #[error(transparent)]
    Learner(#[from] LearnerError),
    /// Checkpoint I/O.
    #[error(transparent)]
    Checkpoint(#[from] CheckpointError),
    /// Task controller error.
    #[error(transparent)]
    Task(#[from] taskctl::TaskError),
    /// A task-controller call failed.
    #[error(transparent)]
    TaskService(#[from] taskctl::TaskServiceError),
    /// Actor error.
    #[error(transparent)]
    Actor(#[from] actor::ActorError),
    /// The actor's loop failed (training in one process).
    #[error(transparent)]
    ActorLoop(#[from] crate::actor_process::ActorProcessError),
    /// Training in one process lost its turn order (a bug, reported rather than hidden).
    #[error("in-process training: {0}")]
    TurnOrder(String),
    /// The validation set could not be built.
    #[error("validation set: {0}")]
    ValidationSet(#[from] crate::validation::ValidationSetError),
    /// The test set could not be built.
    #[error("test set: {0}")]
    TestSet(#[from] racetracks::TrackSetError),
    /// A weights blob could not be used.
    #[error(transparent)]
    Blob(#[from] policy::BlobError),
    /// Updates kept diverging: each was refused and rolled back, and the next one diverged too.
    #[error(
        "{count} updates in a row were refused (non-finite or exploding) and rolled back; the last: {last}. The run stops at its last good weights: lower the learning rate or check the rollouts"
    )]
    Diverged {
        /// Refused updates in a row.
        count: u32,
        /// Why the last was refused.
        last: String,
    },
    /// Checkpoints (or the task controller's snapshots) kept failing to be written (a full or
    /// failing disk): going on would train what nothing keeps.
    #[error("{count} writes of the run's state in a row failed; the last: {last}. Free space in the run directory, then resume")]
    CheckpointsFailing {
        /// Failed writes in a row.
        count: u32,
        /// The last error.
        last: String,
    },
    /// A file or directory of the run could not be read or written.
    #[error("{}: {source}", file.display())]
    Io {
        /// The file or directory.
        file: PathBuf,
        /// What the system said.
        #[source]
        source: std::io::Error,
    },
    /// A section of a checkpoint or a config could not be encoded or decoded.
    #[error("{what}: {reason}")]
    Encoding {
        /// Which file and section.
        what: String,
        /// Why.
        reason: String,
    },
    /// The rollout transport failed.
    #[error(transparent)]
    Link(#[from] transport::LinkError),
    /// The run's `train.log` could not be written.
    #[error(transparent)]
    Log(#[from] crate::progress::LogError),
    /// The task-controller snapshot inside a checkpoint is unusable.
    #[error(transparent)]
    Snapshot(#[from] taskctl::SnapshotError),
}

impl TrainError {
    /// A failure that restarting the process from its checkpoint would only repeat: the
    /// supervisor stops the run instead (see [`crate::supervisor::EXIT_FATAL`]).
    pub fn is_fatal(&self) -> bool {
        match self {
            Self::Diverged { .. } | Self::CheckpointsFailing { .. } => true,
            // A full disk stays full across a restart (which would lose the iterations since
            // the last checkpoint each time).
            Self::Io { source, .. } => matches!(source.kind(), std::io::ErrorKind::StorageFull | std::io::ErrorKind::QuotaExceeded),
            _ => false,
        }
    }
}
