//! Evaluation from Python (SPEC §9), as `dronerace eval` runs it: a policy file's deterministic
//! actions, or any Python callable acting on batches of observations.

use std::sync::Arc;

use numpy::{PyArray1, PyArrayMethods, PyReadonlyArray2};
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;
use sim::eval::{EvalConfig, EvalReport};
use sim::{ACTION_DIM, Track};

use crate::inputs::{Int, MAX_DEPLOYMENTS, MAX_RUNS, MAX_STEPS, Observation, finite_rows};
use crate::policy_py::PyPolicy;
use crate::tracks::resolve;

/// The tracks and protocol of one evaluation, checked: 1 to 1,000 runs per track, 1 to
/// 1,000,000 steps, at most 10,000 deployments in all.
fn setup(tracks: &[Bound<'_, PyAny>], runs: &Int, steps: &Int, seed: &Int) -> PyResult<(Vec<Arc<Track>>, EvalConfig)> {
    let (runs, steps, seed) =
        (runs.within("runs", 1..=MAX_RUNS)?, steps.within("steps", 1..=MAX_STEPS)?, seed.within("seed", 0..=u64::MAX)?);
    if tracks.is_empty() {
        return Err(PyValueError::new_err("tracks: an empty list"));
    }
    let tracks = resolve("tracks", tracks)?;
    if tracks.len() * runs > MAX_DEPLOYMENTS {
        return Err(PyValueError::new_err(format!(
            "runs: {runs} runs on each of {} tracks make {} deployments; at most {MAX_DEPLOYMENTS} in one evaluation",
            tracks.len(),
            tracks.len() * runs
        )));
    }
    Ok((tracks, EvalConfig { runs, steps, seed, ..EvalConfig::default() }))
}

fn to_json(report: &EvalReport) -> PyResult<String> {
    serde_json::to_string(report).map_err(|e| PyValueError::new_err(e.to_string()))
}

/// Evaluates a policy file's deterministic actions: `runs` deployments of `steps` steps per
/// track from SPEC §9's perturbed starts (seed `seed`), in parallel; the report as JSON
/// (`dronerace eval`'s `eval.json`).
#[pyfunction]
// The text signature spells the defaults Python would otherwise see as `...` (an `Int`'s).
#[pyo3(signature = (policy, tracks, runs = Int::Value(25), steps = Int::Value(1000), seed = Int::Value(0)),
       text_signature = "(policy, tracks, runs=25, steps=1000, seed=0)")]
pub fn evaluate_policy(
    py: Python<'_>,
    policy: &PyPolicy,
    tracks: Vec<Bound<'_, PyAny>>,
    runs: Int,
    steps: Int,
    seed: Int,
) -> PyResult<String> {
    let (tracks, config) = setup(&tracks, &runs, &steps, &seed)?;
    let factory = policy::controller_factory(&policy.blob).map_err(|e| PyValueError::new_err(format!("policy: {e}")))?;
    let name = format!("policy v{} ({})", policy.blob.version, policy.blob.architecture.agent);
    let report = py.detach(|| sim::eval::evaluate(&name, &tracks, factory.as_ref(), &config));
    to_json(&report)
}

/// Evaluates `act`, a callable from a float32 array of observations (`n × observation_dim`, the
/// `observation` agent's layout) to `n × 4` actions, called once per step with every deployment
/// still flying: the same deployments as `evaluate_policy`. The report as JSON.
#[pyfunction]
#[pyo3(signature = (act, tracks, runs = Int::Value(25), steps = Int::Value(1000), seed = Int::Value(0), observation = "state", name = "callable"),
       text_signature = "(act, tracks, runs=25, steps=1000, seed=0, observation=\"state\", name=\"callable\")")]
#[allow(clippy::too_many_arguments, reason = "the Python function's keyword arguments")]
pub fn evaluate_callable(
    py: Python<'_>,
    act: Bound<'_, PyAny>,
    tracks: Vec<Bound<'_, PyAny>>,
    runs: Int,
    steps: Int,
    seed: Int,
    observation: &str,
    name: &str,
) -> PyResult<String> {
    let (tracks, config) = setup(&tracks, &runs, &steps, &seed)?;
    if Observation::parse(observation)? == Observation::Vision {
        return Err(PyValueError::new_err("observation: a callable is evaluated on state observations; pass a vision policy as a Policy"));
    }
    let layout = Observation::State.env_config().observation;
    let dim = layout.dim();
    let report =
        sim::eval::evaluate_batched(name, &tracks, layout, &config, |observations: &[f32], actions: &mut [f32]| -> PyResult<()> {
            let n = observations.len() / dim;
            let batch = PyArray1::from_slice(py, observations).reshape([n, dim])?;
            let answer = act.call1((batch,))?;
            let answer: PyReadonlyArray2<'_, f32> = answer.extract().map_err(|_| {
                PyValueError::new_err(format!(
                    "the callable's actions: expected a float32 array of shape ({n}, {ACTION_DIM}), got {answer}"
                ))
            })?;
            actions.copy_from_slice(&finite_rows("the callable's actions", &answer, Some(n), ACTION_DIM)?);
            Ok(())
        })?;
    to_json(&report)
}
