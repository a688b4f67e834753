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
    // (python/README.md, "Speed"). Only beside another worker, though: as the only one, a step
    // called from a second Python thread would wait for it forever while it waits in Python
    // (in `join()`, say), since that thread runs rayon's jobs only inside a call of its own.
    // If the pool exists already (another extension built it), the module works as well with it.
    let threads = pool_threads();
    let pool = rayon::ThreadPoolBuilder::new().num_threads(threads);
    let _ = if threads >= 2 { pool.use_current_thread() } else { pool }.build_global();
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

/// Threads of rayon's pool, counted as rayon counts them: `RAYON_NUM_THREADS` when set above 0,
/// else the CPUs this process may run on (its affinity, as `taskset` sets it, and its quota).
fn pool_threads() -> usize {
    let cpus = || std::thread::available_parallelism().map_or(1, std::num::NonZero::get);
    std::env::var("RAYON_NUM_THREADS").ok().and_then(|s| s.parse::<usize>().ok()).filter(|&n| n > 0).unwrap_or_else(cpus)
}
