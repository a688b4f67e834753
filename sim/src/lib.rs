//! Quadrotor racing simulator: dynamics, race environment, vectorised environment, reference
//! pilot and evaluation harness. Pure computation, no I/O.

pub mod camera;
pub mod disturbance;
pub mod eval;
pub mod mirror;
pub mod observation;
pub mod params;
pub mod poses_text;
pub mod quadrotor;
pub mod race;
pub mod racer;
pub mod racing_line;
pub mod randomization;
pub mod reference_pilot;
pub mod replay;
pub mod reward;
pub mod seed;
pub mod track;
pub mod vec_env;

pub use camera::CameraPose;
pub use disturbance::Disturbances;
pub use mirror::{ACTION_MIRROR_SIGNS, ObservationMirror};
pub use nalgebra;
pub use observation::{
    DEFAULT_LINE_SPACING, GateSight, LINE_POINT_DIM, NEXT_CORNERS_RANGE, ObservationFrame, ObservationLayout, PREVIOUS_ACTION_RANGE,
    STATE_OBS_DIM, TARGET_CORNERS_RANGE,
};
pub use params::{GRAVITY, QuadrotorParams, RaceParams};
pub use race::{CrashCause, EnvConfig, EpisodeStats, RaceEnv, StepOutcome};
pub use racer::Racer;
pub use racing_line::{FrameClearance, LinePoint, PathLimits, RacingLine};
pub use randomization::RandomizationParams;
pub use reference_pilot::{Controller, PilotMemory, PilotParams, ReferencePilot};
pub use reward::{ProgressDistance, RewardParams, RewardTerms};
pub use track::{Arena, Gate, Pose, Track};
pub use vec_env::{ACTION_DIM, VecEnv};
