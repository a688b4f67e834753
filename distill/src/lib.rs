//! Teacher–student distillation by DAgger (Ross, Gordon and Bagnell 2011): a vision student
//! learns to race from a state-based policy, or a state-based student from the reference
//! pilot. The aggregated data set of labelled states (`dataset`), the student's regression on
//! it (`student`) and the run that flies, labels, switches tracks and regresses round after
//! round, with its checkpoints, metrics and validation (`run`).

pub mod dataset;
pub mod run;
pub mod student;

pub use dataset::DistillDataset;
pub use run::{DistillConfig, DistillFlags, Distiller, PILOT_TEACHER, RoundSummary, progress_line};
pub use student::Student;
