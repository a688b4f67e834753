//! A trained policy flying for someone else: what `dronerace serve` answers, with no transport
//! in it. [`Pilot`] is the service — an action for an observation, or a race flown from the
//! drone's state, with the server keeping target gate, laps and previous action — and
//! [`PilotError`] says what was refused and why; the gRPC adapter (`transport::pilot_grpc`) maps it
//! to status codes in one place. (The reference pilot that policies are compared with is
//! another thing: `sim::ReferencePilot`.)

use std::path::Path;
use std::sync::Arc;

use policy::Policy;
use sim::quadrotor::BodyState;
use sim::{Racer, Track};

/// Why a pilot refused a request (or, for the internal kinds, failed to answer it).
#[derive(Debug, thiserror::Error)]
pub enum PilotError {
    /// The observation has the wrong length for this policy.
    #[error("observation has {got} values; this policy reads {expected}")]
    ObservationLength {
        /// Values sent.
        got: usize,
        /// Values the policy reads.
        expected: usize,
    },
    /// A number of the request is NaN or infinite.
    #[error("{field}[{index}] is {value}, not a finite number")]
    NotFinite {
        /// The request's field (`observation`).
        field: &'static str,
        /// Index within it.
        index: usize,
        /// The number sent.
        value: f64,
    },
    /// A drone state's field has the wrong length, a non-finite number or a quaternion far
    /// from unit length.
    #[error(transparent)]
    State(#[from] sim::racer::ReportedStateError),
    /// A race started without a track, on a pilot that has none of its own.
    #[error("RaceStart.track_toml is empty and this server has no --track: send the track file's text")]
    NoTrack,
    /// The race's track file does not parse.
    #[error(transparent)]
    Track(#[from] racetracks::TrackFileError),
    /// The policy produced a non-finite action: nothing is sent (internal).
    #[error("the policy produced action[{index}] = {value}; nothing is sent")]
    NonFiniteAction {
        /// Index of the action.
        index: usize,
        /// The number produced.
        value: f32,
    },
    /// The policy's action is not 4 numbers (internal).
    #[error("the policy's action has {0} numbers, not 4")]
    ActionShape(usize),
}

impl PilotError {
    /// The pilot failed, rather than the request being wrong.
    pub fn is_internal(&self) -> bool {
        matches!(self, Self::NonFiniteAction { .. } | Self::ActionShape(_))
    }
}

/// What a client needs to know to talk to a pilot.
#[derive(Clone, Debug, PartialEq)]
pub struct Description {
    /// Length of an observation.
    pub observation_dim: usize,
    /// Length of an action.
    pub action_dim: usize,
    /// The frame observations are expressed in (its name).
    pub observation_frame: String,
    /// Version of the policy.
    pub policy_version: u64,
    /// The observation's layout, part by part.
    pub observation_layout: String,
}

/// A drone's state as a flight stack reports it, unchecked: world position (m), world velocity
/// (m/s), orientation (w, x, y, z; body to world) and body rates (rad/s).
#[derive(Clone, Copy, Debug)]
pub struct DroneState<'a> {
    /// Position (3, m, world).
    pub position: &'a [f64],
    /// Velocity (3, m/s, world).
    pub velocity: &'a [f64],
    /// Orientation (4: w, x, y, z; body to world).
    pub orientation: &'a [f64],
    /// Angular velocity (3, rad/s, body).
    pub angular_velocity: &'a [f64],
}

/// The answer to one drone state of a race.
#[derive(Clone, Debug, PartialEq)]
pub struct RaceCommand {
    /// The normalised action (4, in [-1, 1]).
    pub action: Vec<f32>,
    /// The gate the drone races for next.
    pub target_gate: usize,
    /// Laps completed.
    pub laps: u32,
}

/// A policy serving actions: the transport-free `dronerace.v1.Pilot`.
pub trait Pilot: Send + Sync {
    /// What clients need to know.
    fn describe(&self) -> Description;

    /// The deterministic action (finite, in [-1, 1]) for one observation in raw units.
    fn act(&self, observation: &[f32]) -> Result<Vec<f32>, PilotError>;

    /// A race on the track whose file text is `track_toml` (the pilot's own track if empty).
    fn start_race(&self, track_toml: &str) -> Result<Racer, PilotError>;

    /// The command for the drone's state in a race: the observation built as training builds
    /// it, the policy's action, and the race's target gate and laps after it.
    fn race_step(&self, racer: &mut Racer, state: DroneState<'_>) -> Result<RaceCommand, PilotError> {
        let observation = racer.observe(&body_state(state)?);
        let action = self.act(&observation)?;
        let flown: [f32; 4] = action.as_slice().try_into().map_err(|_| PilotError::ActionShape(action.len()))?;
        racer.acted(&flown);
        Ok(RaceCommand { action, target_gate: racer.target_gate(), laps: racer.laps() })
    }
}

/// One trained policy as a [`Pilot`], with an optional track for races that name none.
#[derive(Clone)]
pub struct PolicyPilot {
    policy: Arc<Policy>,
    track: Option<Arc<Track>>,
}

impl PolicyPilot {
    /// Serves `policy`.
    pub fn new(policy: Arc<Policy>) -> Self {
        Self { policy, track: None }
    }

    /// Races on `track` when a race names none.
    pub fn with_track(self, track: Arc<Track>) -> Self {
        Self { track: Some(track), ..self }
    }
}

impl Pilot for PolicyPilot {
    fn describe(&self) -> Description {
        let layout = self.policy.observation_layout();
        Description {
            observation_dim: self.policy.observation_dim(),
            action_dim: self.policy.action_dim(),
            observation_frame: layout.frame.name().into(),
            policy_version: self.policy.version(),
            observation_layout: layout.describe(),
        }
    }

    fn act(&self, observation: &[f32]) -> Result<Vec<f32>, PilotError> {
        let expected = self.policy.observation_dim();
        if observation.len() != expected {
            return Err(PilotError::ObservationLength { got: observation.len(), expected });
        }
        if let Some(index) = observation.iter().position(|x| !x.is_finite()) {
            return Err(PilotError::NotFinite { field: "observation", index, value: f64::from(observation[index]) });
        }
        finite(self.policy.deterministic_actions(observation))
    }

    fn start_race(&self, track_toml: &str) -> Result<Racer, PilotError> {
        let track = if track_toml.trim().is_empty() {
            self.track.clone().ok_or(PilotError::NoTrack)?
        } else {
            Arc::new(racetracks::parse_track(track_toml, Path::new("RaceStart.track_toml"))?)
        };
        Ok(Racer::new(track, self.policy.observation_layout()))
    }
}

/// The action if every number of it is finite: a drone must never be sent NaN. Policy files
/// are checked for finite weights when read; this holds the line for whatever slips past.
fn finite(action: Vec<f32>) -> Result<Vec<f32>, PilotError> {
    match action.iter().position(|a| !a.is_finite()) {
        Some(index) => Err(PilotError::NonFiniteAction { index, value: action[index] }),
        None => Ok(action),
    }
}

/// A reported state as the simulator's body state, refused naming the field.
fn body_state(state: DroneState<'_>) -> Result<BodyState, PilotError> {
    let values = [state.position, state.velocity, state.orientation, state.angular_velocity];
    let names = ["DroneState.position", "DroneState.velocity", "DroneState.orientation", "DroneState.angular_velocity"];
    Ok(sim::racer::reported_body_state(values, names)?)
}

#[cfg(test)]
mod tests {
    use super::*;
    use policy::{ActorCritic, Architecture, Device, ObsNormalizer, WeightsBlob};
    use sim::racer::ReportedStateError;

    #[test]
    fn a_policy_file_with_nan_weights_is_refused_and_no_nan_action_is_sent() {
        let arch = Architecture::cpu();
        let net = ActorCritic::new(&arch, -0.5, 1, &Device::flex());
        let mut blob = <WeightsBlob as policy::NetworkBlob>::from_model(1, &arch, &ObsNormalizer::new(arch.observation_dim), &net);
        let healthy = PolicyPilot::new(Arc::new(Policy::from_blob(&blob).unwrap()));
        assert!(healthy.act(&vec![0.1; arch.observation_dim]).unwrap().iter().all(|a| a.is_finite()));
        // A file with a NaN weight is refused when read, naming the parameter. (Built in memory
        // and flown, such a network acts with zeros on this backend, not NaN: only the check
        // when the file is read tells the policy is broken.)
        blob.params[1].values[3] = f32::NAN;
        let error = WeightsBlob::from_bytes(&blob.to_bytes()).unwrap_err().to_string();
        assert!(error.contains("parameter 1") && error.contains("not a finite weight"), "{error}");
        // Whatever slips past, the service never sends a non-finite action, and says so as its
        // own failure rather than the caller's.
        let refused = finite(vec![0.5, f32::NAN, 0.0, 1.0]).unwrap_err();
        assert!(refused.is_internal() && refused.to_string().contains("action[1]"), "{refused}");
        assert_eq!(finite(vec![0.5, -1.0]).unwrap(), vec![0.5, -1.0]);
    }

    #[test]
    fn a_drone_state_is_refused_naming_its_field() {
        let ok = [0.0; 3];
        let unit = [1.0, 0.0, 0.0, 0.0];
        let state = |position: &'static [f64], orientation: &'static [f64]| DroneState {
            position,
            velocity: &[0.0; 3],
            orientation,
            angular_velocity: &[0.0; 3],
        };
        assert!(body_state(DroneState { position: &ok, velocity: &ok, orientation: &unit, angular_velocity: &ok }).is_ok());
        let short = body_state(state(&[0.0, 1.0], &[1.0, 0.0, 0.0, 0.0])).unwrap_err();
        assert!(
            matches!(short, PilotError::State(ReportedStateError::Length { field: "DroneState.position", got: 2, expected: 3 })),
            "{short}"
        );
        let nan = body_state(state(&[0.0, f64::NAN, 0.0], &[1.0, 0.0, 0.0, 0.0])).unwrap_err();
        assert!(matches!(nan, PilotError::State(ReportedStateError::NotFinite { field: "DroneState.position", index: 1, .. })), "{nan}");
        let skewed = body_state(state(&[0.0; 3], &[2.0, 0.0, 0.0, 0.0])).unwrap_err();
        assert!(matches!(skewed, PilotError::State(ReportedStateError::NotUnitQuaternion { .. })) && !skewed.is_internal(), "{skewed}");
    }
}
