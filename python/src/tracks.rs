//! Tracks for Python: the library, track files, the generators and the held-out sets, and the
//! one rule for what Python may name a track by (a `Track`, a library name, or a path).

use std::path::{Path, PathBuf};
use std::sync::Arc;

use pyo3::exceptions::{PyOSError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::PyDict;
use racetracks::track_file::MAX_TRACK_FILE_BYTES;
use racetracks::track_sets::TEST_SET_SIZE;
use racetracks::{ChosenTracksError, GeneratorKind, TrackFileError, TrackGenParams, TrackGenerator};
use sim::Track;
use sim::nalgebra::Vector3;
use sim::track::{MAX_COORDINATE, MAX_GATES};

use crate::inputs::{Float, Int, MAX_CONTROL_POINTS, MAX_TRACKS};

/// A racetrack: gates in racing order, a start pose and an arena. Immutable.
#[pyclass(name = "Track", module = "dronerace._core", frozen)]
#[derive(Clone)]
pub struct PyTrack {
    /// The track.
    pub track: Arc<Track>,
}

#[pymethods]
impl PyTrack {
    /// The track's name.
    #[getter]
    fn name(&self) -> String {
        self.track.name.clone()
    }

    /// Gates in racing order, each `(x, y, z, yaw)`: the opening's centre (m, world) and the
    /// heading of the flight direction through it (rad).
    #[getter]
    fn gates(&self) -> Vec<(f64, f64, f64, f64)> {
        self.track.gates.iter().map(|g| (g.position.x, g.position.y, g.position.z, g.yaw)).collect()
    }

    /// The start pose `(x, y, z, yaw)` (m, rad).
    #[getter]
    fn start(&self) -> (f64, f64, f64, f64) {
        let s = &self.track.start;
        (s.position.x, s.position.y, s.position.z, s.yaw)
    }

    /// The arena's corners `((x, y, z) min, (x, y, z) max)` (m).
    #[getter]
    fn arena(&self) -> ([f64; 3], [f64; 3]) {
        (self.track.arena.min.into(), self.track.arena.max.into())
    }

    /// The track file's text (TOML), which `parse` reads back to the same track.
    fn to_toml(&self) -> String {
        racetracks::track_to_toml(&self.track)
    }

    /// Writes the track file to `path`.
    fn save(&self, path: PathBuf) -> PyResult<()> {
        racetracks::write_track(&self.track, &path).map_err(file_error)
    }

    fn __eq__(&self, other: &Self) -> bool {
        self.track == other.track
    }

    fn __len__(&self) -> usize {
        self.track.gates.len()
    }

    fn __repr__(&self) -> String {
        format!("Track({:?}, {} gates)", self.track.name, self.track.gates.len())
    }
}

/// A track file's error as a Python exception: a missing or unreadable file is an `OSError`,
/// anything wrong inside it — or a file refused unread, a device or one too large — a
/// `ValueError`; both name the file (and the field).
pub fn file_error(e: TrackFileError) -> PyErr {
    match &e {
        TrackFileError::Io { source, .. } if !is_refusal(source) => PyOSError::new_err(e.to_string()),
        _ => PyValueError::new_err(e.to_string()),
    }
}

/// Whether a read failed because the file was refused (`durable::read_limited`: not a
/// regular file, too large, not UTF-8) rather than unreadable.
pub fn is_refusal(e: &std::io::Error) -> bool {
    matches!(e.kind(), std::io::ErrorKind::InvalidInput | std::io::ErrorKind::InvalidData)
}

fn wrap(tracks: Vec<Track>) -> Vec<PyTrack> {
    tracks.into_iter().map(|t| PyTrack { track: Arc::new(t) }).collect()
}

/// Every library track, in library order.
#[pyfunction]
pub fn library() -> PyResult<Vec<PyTrack>> {
    Ok(wrap(racetracks::library().map_err(file_error)?))
}

/// The library's track names.
#[pyfunction]
pub fn library_names() -> PyResult<Vec<String>> {
    Ok(racetracks::library().map_err(file_error)?.into_iter().map(|t| t.name).collect())
}

/// Reads a track file: TOML (SPEC §6), or a CSV of gate poses `x,y,z,yaw_deg` (one gate a row
/// in racing order), named by the file's stem.
#[pyfunction]
pub fn load(path: PathBuf) -> PyResult<PyTrack> {
    let track = if path.extension().is_some_and(|e| e.eq_ignore_ascii_case("csv")) {
        let text = durable::read_text_limited(&path, MAX_TRACK_FILE_BYTES as u64)
            .map_err(|source| file_error(TrackFileError::Io { file: path.clone(), source }))?;
        let name = path.file_stem().map_or_else(|| "track".into(), |s| s.to_string_lossy().into_owned());
        racetracks::track_from_csv(&name, &text, &path)
    } else {
        racetracks::read_track(&path)
    };
    Ok(PyTrack { track: Arc::new(track.map_err(file_error)?) })
}

/// Parses a track file's text (TOML); `name` names it in errors and is its default name.
#[pyfunction]
#[pyo3(signature = (text, name = "track"))]
pub fn parse(text: &str, name: &str) -> PyResult<PyTrack> {
    let track = racetracks::parse_track(text, Path::new(name)).map_err(file_error)?;
    Ok(PyTrack { track: Arc::new(track) })
}

/// The generated track of `seed`: the informed generator (SPEC §7) or the uniform one, with
/// `gates` gates (or a count drawn from `gates..=gates_max`), 2 to 64.
#[pyfunction]
// The text signature spells the defaults Python would otherwise see as `...` (an `Int`'s).
#[pyo3(signature = (seed, kind = "informed", gates = Int::Value(6), gates_max = None, name = None),
       text_signature = "(seed, kind=\"informed\", gates=6, gates_max=None, name=None)")]
pub fn generate(seed: Int, kind: &str, gates: Int, gates_max: Option<Int>, name: Option<String>) -> PyResult<PyTrack> {
    let seed = seed.within("seed", 0..=u64::MAX)?;
    let gates = gates.within("gates", 2..=MAX_GATES)?;
    let gates_max = gates_max.map(|g| g.within("gates_max", 2..=MAX_GATES)).transpose()?;
    let kind = match kind {
        "informed" => GeneratorKind::Informed,
        "uniform" => GeneratorKind::Uniform,
        other => return Err(PyValueError::new_err(format!("kind: {other:?} is not one of \"informed\", \"uniform\""))),
    };
    let generator = TrackGenerator { kind, params: TrackGenParams { gates, gates_max, ..TrackGenParams::default() } };
    let name = name.unwrap_or_else(|| format!("{kind:?}-{seed}").to_lowercase());
    let generated = generator.generate(seed, &name).map_err(|e| PyValueError::new_err(e.to_string()))?;
    Ok(PyTrack { track: Arc::new(generated.track) })
}

/// The evaluation test set (SPEC §9): the library, then generated tracks from `seed`, 40 in all
/// — what `dronerace tracks testset` writes.
#[pyfunction]
#[pyo3(signature = (seed = Int::Value(racetracks::track_sets::TEST_SEED.into())), text_signature = "(seed=9000000)")]
pub fn test_set(seed: Int) -> PyResult<Vec<PyTrack>> {
    // The generated tracks take seeds `seed`, `seed + 1`, …: they must not run past u64.
    let seed = seed.within("seed", 0..=u64::MAX - TEST_SET_SIZE as u64)?;
    Ok(wrap(racetracks::test_set(seed).map_err(|e| PyValueError::new_err(e.to_string()))?))
}

/// `count` tracks of the validation set (for choosing checkpoints; never trained on), at most
/// 4,096.
#[pyfunction]
pub fn validation_set(count: Int) -> PyResult<Vec<PyTrack>> {
    let count = count.within("count", 0..=MAX_TRACKS)?;
    Ok(wrap(racetracks::validation_set(count).map_err(|e| PyValueError::new_err(e.to_string()))?))
}

/// Fits a closed smoothing cubic spline through control points `[(x, y, z), …]` with smoothing
/// factor `smoothing` (scipy's `splprep(per=1, k=3)`): a dict of the parameters `u`, `knots`,
/// `coefficients` (`[xs, ys, zs]`, scipy's `tck[1]`) and `residual`, as `dronerace tracks fit`
/// prints. At most 256 points, each coordinate within ±1000 m (a track's arena).
#[pyfunction]
#[pyo3(signature = (points, smoothing = Float::Value(4.0)), text_signature = "(points, smoothing=4.0)")]
pub fn fit<'py>(py: Python<'py>, points: Vec<[Float; 3]>, smoothing: Float) -> PyResult<Bound<'py, PyDict>> {
    if points.len() > MAX_CONTROL_POINTS {
        return Err(PyValueError::new_err(format!("points: {} points; a fit takes at most {MAX_CONTROL_POINTS}", points.len())));
    }
    let smoothing = smoothing.finite("smoothing")?;
    let coordinate = |i: usize, p: &[Float; 3]| -> PyResult<[f64; 3]> {
        Ok([p[0].finite(&format!("points[{i}][0]"))?, p[1].finite(&format!("points[{i}][1]"))?, p[2].finite(&format!("points[{i}][2]"))?])
    };
    let points = points.iter().enumerate().map(|(i, p)| coordinate(i, p)).collect::<PyResult<Vec<[f64; 3]>>>()?;
    // Beyond the arena's bounds chord lengths overflow to infinity (1e300 squared), and the fit
    // of infinite parameters has no answer.
    for (i, p) in points.iter().enumerate() {
        if let Some(k) = p.iter().position(|c| !c.is_finite() || c.abs() > MAX_COORDINATE) {
            return Err(PyValueError::new_err(format!("points[{i}][{k}] is {:e}; coordinates lie within ±{MAX_COORDINATE} m", p[k])));
        }
    }
    let control: Vec<Vector3<f64>> = points.iter().map(|p| Vector3::from(*p)).collect();
    let fit = racetracks::spline::fit_closed_curve(&control, smoothing).map_err(|e| PyValueError::new_err(format!("points: {e}")))?;
    let out = PyDict::new(py);
    out.set_item("u", fit.u)?;
    out.set_item("knots", fit.curve.knots)?;
    out.set_item("coefficients", fit.curve.coefficients.to_vec())?;
    out.set_item("residual", fit.residual)?;
    Ok(out)
}

/// The tracks `items` name, each a `Track`, a library track's name or a track file or directory
/// (`str` or path), at most 4,096 in all with directories expanded; `field` names the argument
/// in errors.
pub fn resolve(field: &str, items: &[Bound<'_, PyAny>]) -> PyResult<Vec<Arc<Track>>> {
    let too_many = |n: usize| PyValueError::new_err(format!("{field}: {n} tracks; at most {MAX_TRACKS}"));
    if items.len() > MAX_TRACKS {
        return Err(too_many(items.len()));
    }
    let mut tracks = Vec::with_capacity(items.len());
    let library = racetracks::library().map_err(file_error)?;
    for (i, item) in items.iter().enumerate() {
        if let Ok(track) = item.cast::<PyTrack>() {
            tracks.push(track.get().track.clone());
            continue;
        }
        let path: PathBuf = item.extract().map_err(|_| {
            PyValueError::new_err(format!("{field}[{i}]: a track is a dronerace.Track, a library name or a path, not {item}"))
        })?;
        let text = path.to_string_lossy();
        let is_path = path.exists() || text.contains('/') || text.ends_with(".toml") || text.ends_with(".csv");
        if let (false, Some(track)) = (is_path, library.iter().find(|t| t.name.eq_ignore_ascii_case(&text))) {
            tracks.push(Arc::new(track.clone()));
            continue;
        }
        if !path.exists() {
            let known: Vec<&str> = library.iter().map(|t| t.name.as_str()).collect();
            return Err(PyValueError::new_err(format!(
                "{field}[{i}]: {text:?} is neither a library track ({}) nor an existing track file or directory",
                known.join(", ")
            )));
        }
        if path.extension().is_some_and(|e| e.eq_ignore_ascii_case("csv")) {
            tracks.push(load(path)?.track);
            continue;
        }
        let chosen = racetracks::chosen_tracks([field; 2], &[], &[path]).map_err(|e| match e {
            ChosenTracksError::File { source: TrackFileError::Io { .. }, .. } => PyOSError::new_err(e.to_string()),
            _ => PyValueError::new_err(e.to_string()),
        })?;
        tracks.extend(chosen.into_iter().map(Arc::new));
        if tracks.len() > MAX_TRACKS {
            return Err(too_many(tracks.len()));
        }
    }
    Ok(tracks)
}
