//! The race state a flight stack keeps, for Python: a real drone's state in, the observation
//! (or the policy's action) out, target gate, laps and previous action kept as training does.

use std::sync::Arc;

use numpy::PyArray1;
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;
use sim::quadrotor::BodyState;

use crate::inputs::{Observation, finite_vector};
use crate::policy_py::PyPolicy;
use crate::tracks::PyTrack;

/// One race on one track, fed the drone's state once per control step (50 Hz).
#[pyclass(name = "Racer", module = "dronerace._core")]
pub struct PyRacer {
    racer: sim::Racer,
    policy: Option<Arc<policy::ActingPolicy>>,
}

#[pymethods]
impl PyRacer {
    /// A race on `track` from its start, observing as `policy` reads (or as the `observation`
    /// agent does when no policy is given).
    #[new]
    #[pyo3(signature = (track, policy = None, observation = "state"))]
    fn new(track: &PyTrack, policy: Option<&PyPolicy>, observation: &str) -> PyResult<Self> {
        let layout = match policy {
            Some(p) if p.acting.sees_images() => {
                return Err(PyValueError::new_err("policy: a vision policy needs camera images; the Racer builds state observations"));
            }
            Some(p) => p.acting.observation_layout(),
            None => Observation::parse(observation)?.env_config().observation,
        };
        Ok(Self { racer: sim::Racer::new(track.track.clone(), layout), policy: policy.map(|p| p.acting.clone()) })
    }

    /// Takes the drone's state — `position` (3, m, world), `velocity` (3, m/s, world),
    /// `orientation` (4: w, x, y, z; body to world) and `angular_velocity` (3, rad/s, body) —
    /// counts the target gate if the path since the last state passed it, and returns the
    /// observation (float32).
    fn observe<'py>(
        &mut self,
        py: Python<'py>,
        position: Vec<f64>,
        velocity: Vec<f64>,
        orientation: Vec<f64>,
        angular_velocity: Vec<f64>,
    ) -> PyResult<Bound<'py, PyArray1<f32>>> {
        let body = body_state(&position, &velocity, &orientation, &angular_velocity)?;
        Ok(PyArray1::from_vec(py, self.racer.observe(&body)))
    }

    /// Records the action flown from the state just observed (4 numbers; clipped to [-1, 1]).
    fn acted(&mut self, action: Vec<f64>) -> PyResult<()> {
        let a = finite_vector::<4>("action", &action)?;
        self.racer.acted(&a.map(|v| v as f32));
        Ok(())
    }

    /// `observe`, the policy's deterministic action, and `acted`: the action (4, float32, in
    /// [-1, 1]) to fly from this state.
    fn act<'py>(
        &mut self,
        py: Python<'py>,
        position: Vec<f64>,
        velocity: Vec<f64>,
        orientation: Vec<f64>,
        angular_velocity: Vec<f64>,
    ) -> PyResult<Bound<'py, PyArray1<f32>>> {
        let policy =
            self.policy.clone().ok_or_else(|| PyValueError::new_err("act: this Racer has no policy (Racer(track, policy=...))"))?;
        let body = body_state(&position, &velocity, &orientation, &angular_velocity)?;
        let observation = self.racer.observe(&body);
        let action = policy.deterministic_actions(&observation, &[]);
        let action: [f32; 4] = std::array::from_fn(|i| action[i]);
        self.racer.acted(&action);
        Ok(PyArray1::from_slice(py, &action))
    }

    /// The gate the drone races to now.
    #[getter]
    fn target_gate(&self) -> usize {
        self.racer.target_gate()
    }

    /// Laps completed.
    #[getter]
    fn laps(&self) -> u32 {
        self.racer.laps()
    }

    /// The track raced.
    #[getter]
    fn track(&self) -> PyTrack {
        PyTrack { track: self.racer.track().clone() }
    }
}

/// The drone's state from Python's numbers, each checked and named as the argument.
fn body_state(position: &[f64], velocity: &[f64], orientation: &[f64], angular_velocity: &[f64]) -> PyResult<BodyState> {
    sim::racer::reported_body_state(
        [position, velocity, orientation, angular_velocity],
        ["position", "velocity", "orientation", "angular_velocity"],
    )
    .map_err(|e| PyValueError::new_err(e.to_string()))
}
