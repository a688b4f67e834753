//! Trained policies for Python: open a checkpoint or weights blob, act deterministically on a
//! batch of raw observations (the policy's normaliser applied inside), as evaluation flies it.

use std::path::PathBuf;
use std::sync::Arc;

use numpy::{PyArray1, PyArray2, PyArrayMethods, PyReadonlyArray2, PyReadonlyArray4, PyUntypedArrayMethods};
use pyo3::exceptions::{PyOSError, PyValueError};
use pyo3::prelude::*;
use sim::ACTION_DIM;
use sim::camera::IMAGE_PIXELS;

use crate::inputs::{finite_rows, in_row_order};
use crate::tracks::is_refusal;

/// Largest policy file `Policy.load` reads (bytes), the learner's bound for checkpoints
/// (`learner::checkpoint::MAX_FILE_BYTES`): today's are 0.6–3 MB. A device such as `/dev/zero`
/// or a larger file is refused unread rather than read until memory runs out.
pub const MAX_POLICY_FILE_BYTES: u64 = 256 << 20;

/// A trained policy (state-based or vision), read from a checkpoint or weights blob.
#[pyclass(name = "Policy", module = "dronerace._core", frozen)]
pub struct PyPolicy {
    /// The weights as read, for evaluation's controllers.
    pub blob: policy::WeightsBlob,
    /// The policy, ready to act.
    pub acting: Arc<policy::ActingPolicy>,
    path: PathBuf,
}

#[pymethods]
impl PyPolicy {
    /// Opens a checkpoint (`ckpt-*.bin`, `best.bin`) or weights blob (`policies/*.bin`): a
    /// regular file of at most 256 MiB.
    #[staticmethod]
    fn load(path: PathBuf) -> PyResult<Self> {
        let bytes = durable::read_limited(&path, MAX_POLICY_FILE_BYTES).map_err(|e| {
            let message = format!("{}: {e}", path.display());
            if is_refusal(&e) { PyValueError::new_err(format!("path: {message}")) } else { PyOSError::new_err(message) }
        })?;
        let blob = policy::WeightsBlob::from_bytes(&bytes).map_err(|e| PyValueError::new_err(format!("{}: {e}", path.display())))?;
        let acting = policy::ActingPolicy::from_blob(&blob).map_err(|e| PyValueError::new_err(format!("{}: {e}", path.display())))?;
        Ok(Self { blob, acting: Arc::new(acting), path })
    }

    /// Deterministic actions (the mean, clipped to [-1, 1]) for raw observations
    /// (`n × observation_dim` float32, as the environment writes them) and, for a vision policy,
    /// their camera images (`n × 1 × 84 × 84` uint8): `n × 4` float32.
    #[pyo3(signature = (observations, images = None))]
    fn act<'py>(
        &self,
        py: Python<'py>,
        observations: PyReadonlyArray2<'py, f32>,
        images: Option<PyReadonlyArray4<'py, u8>>,
    ) -> PyResult<Bound<'py, PyArray2<f32>>> {
        let raw = finite_rows("observations", &observations, None, self.observation_dim())?;
        let n = observations.shape()[0];
        // Both copied (`finite_rows`, `in_row_order`) before the lock is released below.
        let pixels: Vec<u8> = match (&images, self.acting.sees_images()) {
            (Some(images), true) => {
                let shape = images.shape();
                if shape != [n, 1, sim::camera::IMAGE_SIDE, sim::camera::IMAGE_SIDE] {
                    return Err(PyValueError::new_err(format!("images: expected shape ({n}, 1, 84, 84), got {shape:?}")));
                }
                in_row_order(images)
            }
            (None, true) => return Err(PyValueError::new_err("images: a vision policy acts on camera images too")),
            (_, false) => Vec::new(),
        };
        debug_assert!(pixels.is_empty() || pixels.len() == n * IMAGE_PIXELS);
        let acting = self.acting.clone();
        let actions = py.detach(|| acting.deterministic_actions(&raw, &pixels));
        PyArray1::from_vec(py, actions).reshape([n, ACTION_DIM])
    }

    /// The policy's version (the learner's update count when it was saved).
    #[getter]
    fn version(&self) -> u64 {
        self.acting.version()
    }

    /// `"state"` or `"vision"`.
    #[getter]
    fn agent(&self) -> &'static str {
        if self.acting.sees_images() { "vision" } else { "state" }
    }

    /// Length of the raw observation row it reads.
    #[getter]
    pub fn observation_dim(&self) -> usize {
        self.acting.observation_layout().dim()
    }

    fn __repr__(&self) -> String {
        format!("Policy({:?}, v{}, {} agent)", self.path.display().to_string(), self.version(), self.agent())
    }
}
