//! `dronerace._core`: the Rust side of the Python package. The simulator's vectorised
//! environment with the task controller in the loop, tracks, policies, the flight-stack racer
//! and evaluation, with numpy arrays in and out and the interpreter's lock released while rayon
//! works. The Python package (`python/dronerace/`) wraps it in gymnasium's API.

use pyo3::prelude::*;

mod env;
mod evaluate;
mod inputs;
mod policy_py;
mod racer;
mod tracks;

/// The module `dronerace._core`.
#[pymodule]
fn _core(m: &Bound<'_, PyModule>) -> PyResult<()> {
    // The importing thread (Python's, normally the main one) becomes one of rayon's workers:
    // each step then runs its share of the environments itself instead of handing the job to
    // sleeping workers and waiting to be woken, which cost ~40 µs a step of 96 environments
    // (python/README.md, "Speed"). If the pool exists already (another extension built it),
    // the module works as well with it.
    let _ = rayon::ThreadPoolBuilder::new().use_current_thread().build_global();
    m.add_class::<env::VecEnv>()?;
    m.add_class::<tracks::PyTrack>()?;
    m.add_class::<policy_py::PyPolicy>()?;
    m.add_class::<racer::PyRacer>()?;
    m.add_function(wrap_pyfunction!(tracks::library, m)?)?;
    m.add_function(wrap_pyfunction!(tracks::library_names, m)?)?;
    m.add_function(wrap_pyfunction!(tracks::load, m)?)?;
    m.add_function(wrap_pyfunction!(tracks::parse, m)?)?;
    m.add_function(wrap_pyfunction!(tracks::generate, m)?)?;
    m.add_function(wrap_pyfunction!(tracks::test_set, m)?)?;
    m.add_function(wrap_pyfunction!(tracks::validation_set, m)?)?;
    m.add_function(wrap_pyfunction!(tracks::fit, m)?)?;
    m.add_function(wrap_pyfunction!(evaluate::evaluate_policy, m)?)?;
    m.add_function(wrap_pyfunction!(evaluate::evaluate_callable, m)?)?;
    m.add("ACTION_DIM", sim::ACTION_DIM)?;
    m.add("IMAGE_SIDE", sim::camera::IMAGE_SIDE)?;
    Ok(())
}
