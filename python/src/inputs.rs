//! Checks of what Python hands in — shapes, finite numbers, names — with errors that name the
//! argument and the entry, so a wrong call fails at the call and says where.

use std::borrow::Cow;

use numpy::{Element, PyReadonlyArray, PyReadonlyArray2, PyUntypedArrayMethods};
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;
use sim::EnvConfig;

/// The rows of a float32 array of `cols` columns (and `rows` rows when given), every entry
/// finite, in row order whatever the array's memory layout.
pub fn finite_rows<'a>(name: &str, array: &'a PyReadonlyArray2<'_, f32>, rows: Option<usize>, cols: usize) -> PyResult<Cow<'a, [f32]>> {
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

/// An array's entries in row order (C order): borrowed when that is how they lie in memory, else
/// copied. Reading the buffer as it lies would take a column-major array — what `obs[:, idx]`
/// or a transpose gives — for different numbers, silently.
pub fn in_row_order<'a, T: Element + Copy, D: numpy::ndarray::Dimension>(array: &'a PyReadonlyArray<'_, T, D>) -> Cow<'a, [T]> {
    match array.as_slice() {
        Ok(values) if array.is_c_contiguous() => Cow::Borrowed(values),
        _ => Cow::Owned(array.as_array().iter().copied().collect()),
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
