//! Checks of what Python hands in — shapes, finite numbers, names, counts — with errors that
//! name the argument and the entry, so a wrong call fails at the call and says where. The
//! limits on counts live here, each with its reason (python/README.md, "Limits").

use std::fmt::Display;
use std::ops::RangeInclusive;

use numpy::{Element, PyReadonlyArray, PyReadonlyArray2, PyUntypedArrayMethods};
use pyo3::exceptions::{PyOverflowError, PyTypeError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::PyDict;
use sim::EnvConfig;

/// Most environments one `VecEnv` steps (`num_envs`): training's profiles use 96; 4,096 hold
/// ~0.4 GB and take ~8 s to draw their generated tracks.
pub const MAX_ENVS: usize = 4096;
/// Most tracks one list may give, directories expanded (`tracks`), and the most
/// `validation_set` makes: each is generated or read whole, and held while the call runs.
pub const MAX_TRACKS: usize = 4096;
/// Most steps of a rollout, an episode or a deployment (`rollout_steps`, `max_episode_steps`,
/// `steps`): 5.5 hours of flight at 50 Hz.
pub const MAX_STEPS: u32 = 1_000_000;
/// Most deployments per track in an evaluation (`runs`); SPEC §9's protocol flies 25.
pub const MAX_RUNS: usize = 1000;
/// Most deployments of one evaluation in all (tracks × runs): a callable's evaluation flies
/// them all at once, each holding its environment (~90 kB: 10,000 take ~0.9 GB).
pub const MAX_DEPLOYMENTS: usize = 10_000;
/// Longest switching window (`switch_window`, rollouts): the thesis' is 600; each
/// environment keeps its window and ranks it at every report.
pub const MAX_SWITCH_WINDOW: usize = 10_000;
/// Most control points `fit` takes: the informed generator uses a handful. Interpolating
/// (smoothing 0) puts a knot at every point and the work grows with their cube: 256 points
/// take ~12 ms, 4,096 over a minute.
pub const MAX_CONTROL_POINTS: usize = 256;

/// An integer argument as Python passed it, of any size or type, refused by [`Int::within`]
/// with the argument's name. Taken as a Rust integer, `2**64` or `-1` would raise an
/// `OverflowError` that names nothing, and a float a `TypeError` that does not say which.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Int {
    /// An int.
    Value(i128),
    /// An int beyond 128 bits.
    Huge,
    /// Not an int: its type's name.
    Not(String),
}

impl<'py> FromPyObject<'_, 'py> for Int {
    type Error = PyErr;

    fn extract(obj: Borrowed<'_, 'py, PyAny>) -> PyResult<Self> {
        match obj.extract::<i128>() {
            Ok(v) => Ok(Self::Value(v)),
            Err(e) if e.is_instance_of::<PyOverflowError>(obj.py()) => Ok(Self::Huge),
            Err(_) => Ok(Self::Not(obj.get_type().name().map_or_else(|_| "?".to_owned(), |n| n.to_string()))),
        }
    }
}

impl Int {
    /// The number if it lies in `range`; else a `ValueError` (an int outside) or `TypeError`
    /// (not an int) naming `name`.
    pub fn within<T>(&self, name: &str, range: RangeInclusive<T>) -> PyResult<T>
    where
        T: Copy + PartialOrd + Display + TryFrom<i128>,
    {
        let outside = |what: String| PyValueError::new_err(format!("{name}: {what} is outside {}..={}", range.start(), range.end()));
        match self {
            Self::Value(v) => T::try_from(*v).ok().filter(|t| range.contains(t)).ok_or_else(|| outside(v.to_string())),
            Self::Huge => Err(outside("an int beyond 128 bits".to_owned())),
            Self::Not(kind) => Err(PyTypeError::new_err(format!("{name}: an int, not {kind}"))),
        }
    }
}

/// A float argument as Python passed it, refused by [`Float::finite`] with the argument's
/// name. Taken as an `f64`, an int beyond a float's range (`10**400`) would raise an
/// `OverflowError` that names nothing.
#[derive(Clone, Debug, PartialEq)]
pub enum Float {
    /// A number.
    Value(f64),
    /// An int beyond a float's range.
    Huge,
    /// Not a number: its type's name.
    Not(String),
}

impl<'py> FromPyObject<'_, 'py> for Float {
    type Error = PyErr;

    fn extract(obj: Borrowed<'_, 'py, PyAny>) -> PyResult<Self> {
        match obj.extract::<f64>() {
            Ok(v) => Ok(Self::Value(v)),
            Err(e) if e.is_instance_of::<PyOverflowError>(obj.py()) => Ok(Self::Huge),
            Err(_) => Ok(Self::Not(obj.get_type().name().map_or_else(|_| "?".to_owned(), |n| n.to_string()))),
        }
    }
}

impl Float {
    /// The number if it is finite; else a `ValueError` (NaN, infinite, too large) or `TypeError`
    /// (not a number) naming `name`.
    pub fn finite(&self, name: &str) -> PyResult<f64> {
        match self {
            Self::Value(v) if v.is_finite() => Ok(*v),
            Self::Value(v) => Err(PyValueError::new_err(format!("{name} is {v}, not a finite number"))),
            Self::Huge => Err(PyValueError::new_err(format!("{name}: an int beyond a float's range, not a finite number"))),
            Self::Not(kind) => Err(PyTypeError::new_err(format!("{name}: a number, not {kind}"))),
        }
    }
}

/// The rows of a float32 array of `cols` columns (and `rows` rows when given), every entry
/// finite, in row order whatever the array's memory layout; a copy, so no numpy buffer is read
/// once the interpreter's lock is released.
pub fn finite_rows(name: &str, array: &PyReadonlyArray2<'_, f32>, rows: Option<usize>, cols: usize) -> PyResult<Vec<f32>> {
    let shape = array.shape();
    let expected_rows = rows.unwrap_or(shape[0]);
    if shape != [expected_rows, cols] {
        let rows = rows.map_or_else(|| "n".to_owned(), |r| r.to_string());
        return Err(PyValueError::new_err(format!("{name}: expected shape ({rows}, {cols}), got {shape:?}")));
    }
    let values = in_row_order(array);
    if let Some(i) = values.iter().position(|v| !v.is_finite()) {
        return Err(PyValueError::new_err(format!("{name}[{}, {}] is {} (every entry must be finite)", i / cols, i % cols, values[i])));
    }
    Ok(values)
}

/// An array's entries in row order (C order), copied while the interpreter's lock is held:
/// Python code on another thread may resize or free the array once it is released (a borrow
/// does not stop `resize(refcheck=False)`). Reading the buffer as it lies would take a
/// column-major array — what `obs[:, idx]` or a transpose gives — for different numbers.
pub fn in_row_order<T: Element + Copy, D: numpy::ndarray::Dimension>(array: &PyReadonlyArray<'_, T, D>) -> Vec<T> {
    match array.as_slice() {
        Ok(values) if array.is_c_contiguous() => values.to_vec(),
        _ => array.as_array().iter().copied().collect(),
    }
}

/// `values` as `N` finite numbers, named `name` in the error.
pub fn finite_vector<const N: usize>(name: &str, values: &[f64]) -> PyResult<[f64; N]> {
    let array: [f64; N] =
        values.try_into().map_err(|_| PyValueError::new_err(format!("{name}: expected {N} numbers, got {}", values.len())))?;
    if let Some(i) = array.iter().position(|v| !v.is_finite()) {
        return Err(PyValueError::new_err(format!("{name}[{i}] is {} (every entry must be finite)", array[i])));
    }
    Ok(array)
}

/// What an agent observes, by the name Python uses.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Observation {
    /// The state-based agent's numbers (SPEC §5 and the racing line).
    State,
    /// The vision agent's camera image and SPEC §5's state numbers.
    Vision,
}

impl Observation {
    /// `"state"` or `"vision"`.
    pub fn parse(name: &str) -> PyResult<Self> {
        match name {
            "state" => Ok(Self::State),
            "vision" => Ok(Self::Vision),
            other => Err(PyValueError::new_err(format!("observation: {other:?} is not one of \"state\", \"vision\""))),
        }
    }

    /// The environment that agent trains in.
    pub fn env_config(self) -> EnvConfig {
        match self {
            Self::State => EnvConfig::state_agent(),
            Self::Vision => EnvConfig::vision_agent(),
        }
    }
}

/// SPEC §13's disturbances from a dict of `sim::Disturbances`' fields (`{"wind_speed": 3.0}`);
/// an unknown key or a value out of range is refused by name.
pub fn disturbances(table: &Bound<'_, PyDict>) -> PyResult<sim::Disturbances> {
    let mut fields = serde_json::Map::new();
    for (key, value) in table.iter() {
        let key: String = key.extract().map_err(|_| PyValueError::new_err("disturbance: keys must be strings"))?;
        if value.is_none() {
            continue;
        }
        let number = if key == "thrust_loss_motor" {
            serde_json::Value::from(
                value.extract::<u64>().map_err(|_| PyValueError::new_err(format!("disturbance[{key:?}]: a motor index 0-3")))?,
            )
        } else {
            let x: f64 = value.extract().map_err(|_| PyValueError::new_err(format!("disturbance[{key:?}]: a number")))?;
            serde_json::Number::from_f64(x)
                .map(serde_json::Value::Number)
                .ok_or_else(|| PyValueError::new_err(format!("disturbance[{key:?}]: {x} is not finite")))?
        };
        fields.insert(key, number);
    }
    let d: sim::Disturbances =
        serde_json::from_value(serde_json::Value::Object(fields)).map_err(|e| PyValueError::new_err(format!("disturbance: {e}")))?;
    d.check().map_err(|e| PyValueError::new_err(format!("disturbance.{}: {}", e.field, e.reason)))?;
    Ok(d)
}
