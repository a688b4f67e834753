//! The vectorised race environment Python steps: `num_envs` race environments in parallel,
//! gymnasium's next-step autoreset, and the task controller's switching in the loop.
//!
//! Autoreset as gymnasium 1.x does by default: the step that ends an episode returns its last
//! observation (with `terminated` or `truncated`); the next step ignores that environment's
//! action, starts a new episode and returns its first observation with reward 0. A task switch
//! (every `rollout_steps` steps, as the actors report rollouts in training) cuts the episode the
//! same way: that step is `truncated`, and the next starts on the new track.
//!
//! Environment `i` runs on random stream `i` of the seed, as `sim::VecEnv` (training's
//! environment) does, so the same seed and actions fly the same trajectories in both.
//!
//! The environments step into buffers of their own while the interpreter's lock is released;
//! the numpy arrays Python holds are only written with the lock held, after the step
//! ([`publish`]): Python code on another thread could otherwise resize or free an array under
//! a step that writes into it.

use std::sync::Arc;

use numpy::ndarray::{Dimension, Ix1, Ix2, Ix4};
use numpy::{Element, PyArray, PyArray1, PyArray2, PyArray4, PyArrayDescrMethods, PyArrayMethods, PyReadonlyArray2, PyUntypedArrayMethods};
use pyo3::exceptions::{PyRuntimeError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::{PyDict, PyString};
use rayon::prelude::*;
use sim::camera::{IMAGE_PIXELS, IMAGE_SIDE};
use sim::{ACTION_DIM, CrashCause, EnvConfig, EpisodeStats, RaceEnv, RandomizationParams, Track};
use taskctl::{SwitchParams, SwitchPolicy, TaskController};

use crate::inputs::{Float, Int, MAX_ENVS, MAX_STEPS, MAX_SWITCH_WINDOW, Observation, finite_rows};
use crate::tracks::{PyTrack, resolve};

/// Numbers of a body state row of `VecEnv.states`.
const STATE_COLUMNS: usize = 13;

/// Why an episode ended, as Python reads it in `infos["episode"]["outcome"]`.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Ending {
    Crash(CrashCause),
    TimeLimit,
    TrackSwitch,
}

impl Ending {
    fn name(self) -> &'static str {
        match self {
            Self::Crash(CrashCause::Ground) => "crash_ground",
            Self::Crash(CrashCause::Ceiling) => "crash_ceiling",
            Self::Crash(CrashCause::Wall) => "crash_wall",
            Self::Crash(CrashCause::Gate(_)) => "crash_gate",
            Self::TimeLimit => "time_limit",
            Self::TrackSwitch => "track_switch",
        }
    }
}

/// How an environment starts again at its next step.
#[derive(Clone, Debug)]
enum Restart {
    /// A new episode on its track.
    Episode,
    /// A new episode on a new track (a task switch).
    Track(Arc<Track>),
}

/// One environment and what the wrapper keeps about it.
#[derive(Clone, Debug)]
struct Slot {
    env: RaceEnv,
    restart: Option<Restart>,
    /// Sum of this rollout's rewards, reported to the task controller.
    rollout_return: f64,
}

/// What one environment's step gave.
#[derive(Clone, Copy, Debug, Default)]
struct Stepped {
    reward: f32,
    terminated: bool,
    truncated: bool,
    ended: Option<(EpisodeStats, Option<CrashCause>)>,
}

/// An episode that ended in the last step.
#[derive(Clone, Copy, Debug)]
struct Finished {
    env: usize,
    stats: EpisodeStats,
    ending: Ending,
}

/// What a step gives, in memory of this environment's own: written while the interpreter's lock
/// is released, then copied into the numpy arrays.
#[derive(Clone, Debug, Default)]
struct Buffers {
    observations: Vec<f32>,
    /// Empty without cameras.
    images: Vec<u8>,
    rewards: Vec<f32>,
    terminations: Vec<bool>,
    truncations: Vec<bool>,
}

/// `num_envs` race environments stepped in parallel into numpy arrays that are filled in place
/// (the same arrays every step, copy what you keep, unless Python made one read-only or
/// resized it: then that one is left alone and a fresh array takes its place).
#[pyclass(module = "dronerace._core")]
pub struct VecEnv {
    num_envs: usize,
    slots: Vec<Slot>,
    config: EnvConfig,
    /// Tracks given at construction, cycled over the environments; empty: generated tracks.
    given: Vec<Arc<Track>>,
    switching: SwitchParams,
    controller: Option<TaskController>,
    rollout_steps: u32,
    /// Fewest environments rayon hands one thread: 4, or all of them when the pool has one
    /// thread — then the calling thread steps them itself instead of waking the pool's only
    /// worker and waiting for it (python/README.md, "Speed").
    chunk: usize,
    steps_in_rollout: u32,
    rollout: u64,
    seed: u64,
    started: bool,
    finished: Vec<Finished>,
    buffers: Buffers,
    observations: Py<PyArray2<f32>>,
    images: Option<Py<PyArray4<u8>>>,
    rewards: Py<PyArray1<f32>>,
    terminations: Py<PyArray1<bool>>,
    truncations: Py<PyArray1<bool>>,
}

#[pymethods]
impl VecEnv {
    /// `num_envs` environments on `tracks` (each a `Track`, library name or path, cycled over
    /// the environments; `None`: tracks of the informed generator, drawn by the task controller),
    /// observing as the `observation` agent does ("state" or "vision"), switching tracks by
    /// `switching` ("adaptive", "random" or "none") after every `rollout_steps` steps.
    /// `randomize=False` flies the nominal vehicle from SPEC §9's perturbed start (evaluation's
    /// setting); `max_episode_steps` overrides the episode length. `switch_window` (l),
    /// `switch_alpha` (α) and `switch_probability` (the random policy's) are SPEC §8's. Limits:
    /// 1 to 4,096 environments, 1 to 1,000,000 steps, windows of 2 to 10,000 rollouts.
    #[new]
    #[pyo3(signature = (num_envs, tracks = None, seed = Int::Value(0), switching = None, observation = "state",
                        rollout_steps = Int::Value(250), randomize = true, max_episode_steps = None,
                        switch_window = Int::Value(600), switch_alpha = Float::Value(1000.0),
                        switch_probability = Float::Value(1.616e-3), disturbance = None),
           // The defaults Python would otherwise see as `...` (an `Int`'s).
           text_signature = "(num_envs, tracks=None, seed=0, switching=None, observation=\"state\", rollout_steps=250, \
                             randomize=True, max_episode_steps=None, switch_window=600, switch_alpha=1000.0, \
                             switch_probability=1.616e-3, disturbance=None)")]
    #[allow(clippy::too_many_arguments, reason = "the Python constructor's keyword arguments")]
    fn new(
        py: Python<'_>,
        num_envs: Int,
        tracks: Option<Vec<Bound<'_, PyAny>>>,
        seed: Int,
        switching: Option<&str>,
        observation: &str,
        rollout_steps: Int,
        randomize: bool,
        max_episode_steps: Option<Int>,
        switch_window: Int,
        switch_alpha: Float,
        switch_probability: Float,
        disturbance: Option<Bound<'_, PyDict>>,
    ) -> PyResult<Self> {
        let num_envs = num_envs.within("num_envs", 1..=MAX_ENVS)?;
        let seed = seed.within("seed", 0..=u64::MAX)?;
        let rollout_steps = rollout_steps.within("rollout_steps", 1..=MAX_STEPS)?;
        let switch_window = switch_window.within("switch_window", 2..=MAX_SWITCH_WINDOW)?;
        let (switch_alpha, switch_probability) = (switch_alpha.finite("switch_alpha")?, switch_probability.finite("switch_probability")?);
        let observation = Observation::parse(observation)?;
        let mut config = observation.env_config();
        if !randomize {
            // Evaluation's setting as `dronerace eval` flies it: nominal draws and SPEC's vehicle,
            // whose collision sphere is smaller than the one training uses.
            config.randomization = RandomizationParams::evaluation();
            config.quadrotor = EnvConfig::evaluation().quadrotor;
        }
        if let Some(steps) = max_episode_steps {
            config.race.max_episode_steps = steps.within("max_episode_steps", 1..=MAX_STEPS)?;
        }
        if let Some(table) = &disturbance {
            config.disturbance = crate::inputs::disturbances(table)?;
        }
        let given = match &tracks {
            Some(items) if items.is_empty() => return Err(PyValueError::new_err("tracks: an empty list (None draws generated tracks)")),
            Some(items) => resolve("tracks", items)?,
            None => Vec::new(),
        };
        // A user's own tracks stay unless switching is asked for; generated ones switch as in
        // training (the thesis' adaptive switching).
        let policy = match switching {
            None if given.is_empty() => SwitchPolicy::Adaptive,
            None => SwitchPolicy::None,
            Some("adaptive") => SwitchPolicy::Adaptive,
            Some("random") => SwitchPolicy::Random,
            Some("none") => SwitchPolicy::None,
            Some(other) => {
                return Err(PyValueError::new_err(format!("switching: {other:?} is not one of \"adaptive\", \"random\", \"none\"")));
            }
        };
        let switching = SwitchParams { policy, window: switch_window, alpha: switch_alpha, random_probability: switch_probability };
        switching.check().map_err(|e| {
            // Named as the constructor's keyword arguments are.
            let argument = if e.field == "random_probability" { "switch_probability".into() } else { format!("switch_{}", e.field) };
            PyValueError::new_err(format!("{argument}: {}", e.reason))
        })?;
        let images_on = observation == Observation::Vision;
        let dim = config.observation.dim();
        let buffers = Buffers {
            observations: vec![0.0; num_envs * dim],
            images: if images_on { vec![0; num_envs * IMAGE_PIXELS] } else { Vec::new() },
            rewards: vec![0.0; num_envs],
            terminations: vec![false; num_envs],
            truncations: vec![false; num_envs],
        };
        Ok(Self {
            num_envs,
            slots: Vec::new(),
            config,
            given,
            switching,
            controller: None,
            rollout_steps,
            chunk: if rayon::current_num_threads() > 1 { 4 } else { num_envs },
            steps_in_rollout: 0,
            rollout: 0,
            seed,
            started: false,
            finished: Vec::new(),
            buffers,
            observations: PyArray2::zeros(py, [num_envs, dim], false).unbind(),
            images: images_on.then(|| PyArray4::zeros(py, [num_envs, 1, IMAGE_SIDE, IMAGE_SIDE], false).unbind()),
            rewards: PyArray1::zeros(py, num_envs, false).unbind(),
            terminations: PyArray1::zeros(py, num_envs, false).unbind(),
            truncations: PyArray1::zeros(py, num_envs, false).unbind(),
        })
    }

    /// Starts every environment afresh: with `seed`, from scratch (tracks, task controller and
    /// random streams as a new environment of that seed); without, new episodes from where the
    /// streams are (the constructor's seed at the first reset). Returns the infos.
    #[pyo3(signature = (seed = None))]
    fn reset<'py>(&mut self, py: Python<'py>, seed: Option<Int>) -> PyResult<Bound<'py, PyDict>> {
        let seed = seed.map(|s| s.within("seed", 0..=u64::MAX)).transpose()?;
        if seed.is_some() || !self.started {
            self.seed = seed.unwrap_or(self.seed);
            self.rebuild()?;
        } else {
            for slot in &mut self.slots {
                match slot.restart.take() {
                    Some(Restart::Track(track)) => slot.env.set_track(track),
                    _ => slot.env.reset(),
                }
            }
        }
        self.finished.clear();
        let dim = self.config.observation.dim();
        let (slots, out, chunk) = (&self.slots, &mut self.buffers, self.chunk);
        py.detach(|| {
            slots.par_iter().zip(out.observations.par_chunks_mut(dim)).with_min_len(chunk).for_each(|(slot, row)| slot.env.observe(row));
            slots
                .par_iter()
                .zip(out.images.par_chunks_mut(IMAGE_PIXELS))
                .with_min_len(chunk)
                .for_each(|(s, image)| s.env.render_camera(image));
        });
        out.rewards.fill(0.0);
        out.terminations.fill(false);
        out.truncations.fill(false);
        self.publish(py)?;
        self.started = true;
        self.infos(py)
    }

    /// Steps every environment with its row of `actions` (`num_envs × 4`, float32, finite):
    /// `(rewards, terminations, truncations, infos)`, the arrays filled in place, the
    /// observations in place in `observations` (and `images`).
    #[allow(clippy::type_complexity, reason = "gymnasium's step tuple, less the observations")]
    fn step<'py>(
        &mut self,
        py: Python<'py>,
        actions: PyReadonlyArray2<'_, f32>,
    ) -> PyResult<(Bound<'py, PyArray1<f32>>, Bound<'py, PyArray1<bool>>, Bound<'py, PyArray1<bool>>, Bound<'py, PyDict>)> {
        if !self.started {
            return Err(PyRuntimeError::new_err("step before reset: call reset() first"));
        }
        // A copy: the actions array is Python's, and may change once the lock is released.
        let actions = finite_rows("actions", &actions, Some(self.num_envs), ACTION_DIM)?;
        let dim = self.config.observation.dim();
        let (slots, out, chunk) = (&mut self.slots, &mut self.buffers, self.chunk);
        let stepped: Vec<Stepped> = py.detach(|| {
            let stepped = slots
                .par_iter_mut()
                .zip(actions.par_chunks(ACTION_DIM))
                .zip(out.observations.par_chunks_mut(dim))
                .with_min_len(chunk)
                .map(|((slot, action), row)| {
                    let stepped = step_slot(slot, action);
                    slot.env.observe(row);
                    stepped
                })
                .collect();
            slots
                .par_iter()
                .zip(out.images.par_chunks_mut(IMAGE_PIXELS))
                .with_min_len(chunk)
                .for_each(|(s, image)| s.env.render_camera(image));
            stepped
        });
        self.finished.clear();
        for (i, s) in stepped.iter().enumerate() {
            (out.rewards[i], out.terminations[i], out.truncations[i]) = (s.reward, s.terminated, s.truncated);
            if let Some((stats, crash)) = s.ended {
                let ending = crash.map_or(Ending::TimeLimit, Ending::Crash);
                self.finished.push(Finished { env: i, stats, ending });
            }
        }
        self.steps_in_rollout += 1;
        if self.steps_in_rollout == self.rollout_steps {
            self.steps_in_rollout = 0;
            self.end_rollout()?;
        }
        self.publish(py)?;
        let infos = self.infos(py)?;
        Ok((self.rewards.bind(py).clone(), self.terminations.bind(py).clone(), self.truncations.bind(py).clone(), infos))
    }

    /// Current observations, `num_envs × observation_dim` float32 (filled in place; a fresh
    /// array after Python made the last one read-only or resized it).
    #[getter]
    fn observations<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray2<f32>> {
        self.observations.bind(py).clone()
    }

    /// Current camera images, `num_envs × 1 × 84 × 84` uint8 (vision only; else `None`).
    #[getter]
    fn images<'py>(&self, py: Python<'py>) -> Option<Bound<'py, PyArray4<u8>>> {
        self.images.as_ref().map(|i| i.bind(py).clone())
    }

    /// Each environment's body state now, `num_envs × 13` float64: position (m, world),
    /// velocity (m/s, world), orientation (w, x, y, z; body to world), angular velocity
    /// (rad/s, body) — what a flight stack would report, and what `Racer` takes.
    fn states<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArray2<f64>>> {
        let mut rows = Vec::with_capacity(self.slots.len() * STATE_COLUMNS);
        for slot in &self.slots {
            let b = slot.env.body();
            let q = b.attitude;
            rows.extend([b.position.x, b.position.y, b.position.z, b.velocity.x, b.velocity.y, b.velocity.z]);
            rows.extend([q.w, q.i, q.j, q.k, b.body_rates.x, b.body_rates.y, b.body_rates.z]);
        }
        PyArray1::from_vec(py, rows).reshape([self.slots.len(), STATE_COLUMNS])
    }

    /// Number of environments.
    #[getter]
    fn num_envs(&self) -> usize {
        self.num_envs
    }

    /// Length of one observation row.
    #[getter]
    fn observation_dim(&self) -> usize {
        self.config.observation.dim()
    }

    /// The tracks the environments fly now (after `reset`).
    fn tracks(&self) -> Vec<PyTrack> {
        self.slots.iter().map(|s| PyTrack { track: s.env.track().clone() }).collect()
    }

    /// Task switches made since the last seeded reset.
    #[getter]
    fn switches(&self) -> usize {
        self.controller.as_ref().map_or(0, |c| c.history().len())
    }
}

impl VecEnv {
    /// The step's buffers into the numpy arrays ([`publish`]).
    fn publish(&mut self, py: Python<'_>) -> PyResult<()> {
        let (n, out) = (self.num_envs, &self.buffers);
        publish(py, &mut self.observations, &out.observations, Ix2(n, self.config.observation.dim()))?;
        if let Some(images) = &mut self.images {
            publish(py, images, &out.images, Ix4(n, 1, IMAGE_SIDE, IMAGE_SIDE))?;
        }
        publish(py, &mut self.rewards, &out.rewards, Ix1(n))?;
        publish(py, &mut self.terminations, &out.terminations, Ix1(n))?;
        publish(py, &mut self.truncations, &out.truncations, Ix1(n))
    }

    /// Environments, streams and task controller as new for `self.seed`.
    fn rebuild(&mut self) -> PyResult<()> {
        let n = self.num_envs;
        let generator = racetracks::TrackGenerator::default();
        let task_error = |e: taskctl::TaskError| PyRuntimeError::new_err(e.to_string());
        // The given tracks cycled over the environments; none given: the controller draws them.
        let given: Vec<Arc<Track>> = (0..n).filter_map(|i| self.given.get(i % self.given.len().max(1)).cloned()).collect();
        let controller = if given.is_empty() {
            Some(TaskController::new(n, generator, self.switching, self.seed).map_err(task_error)?)
        } else if self.switching.policy != SwitchPolicy::None {
            Some(TaskController::with_tracks(given.clone(), generator, self.switching, self.seed).map_err(task_error)?)
        } else {
            None
        };
        let tracks = controller.as_ref().map_or(given, TaskController::tracks);
        self.slots = tracks
            .into_iter()
            .enumerate()
            .map(|(i, track)| Slot { env: RaceEnv::new(track, self.config, self.seed, i as u64), restart: None, rollout_return: 0.0 })
            .collect();
        self.controller = controller;
        (self.steps_in_rollout, self.rollout) = (0, 0);
        Ok(())
    }

    /// Reports the rollout's returns to the task controller; an environment it switches is cut
    /// (`truncated`) and restarts on its new track at its next step.
    fn end_rollout(&mut self) -> PyResult<()> {
        let truncations = &mut self.buffers.truncations;
        let rollout = self.rollout;
        self.rollout += 1;
        let Some(controller) = &mut self.controller else {
            return Ok(());
        };
        for (i, slot) in self.slots.iter_mut().enumerate() {
            let rollout_return = std::mem::take(&mut slot.rollout_return);
            let switched = controller.report(i, rollout, rollout_return).map_err(|e| PyRuntimeError::new_err(e.to_string()))?;
            if let Some(track) = switched {
                if slot.restart.is_none() {
                    truncations[i] = true;
                    self.finished.push(Finished { env: i, stats: *slot.env.stats(), ending: Ending::TrackSwitch });
                }
                slot.restart = Some(Restart::Track(track));
            }
        }
        Ok(())
    }

    /// gymnasium's infos: `laps` and `target_gate` of every environment, and where an episode
    /// ended in the last step, `episode` (return `r`, length `l`, `laps`, `gates_passed`,
    /// `fastest_lap`, `outcome`, `crash_gate`), each with its `_key` mask.
    fn infos<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        let n = self.num_envs;
        let infos = PyDict::new(py);
        let all = PyArray1::from_vec(py, vec![true; n]);
        let laps: Vec<i32> = self.slots.iter().map(|s| s.env.stats().laps as i32).collect();
        let targets: Vec<i32> = self.slots.iter().map(|s| s.env.target_gate() as i32).collect();
        infos.set_item("laps", PyArray1::from_vec(py, laps))?;
        infos.set_item("_laps", &all)?;
        infos.set_item("target_gate", PyArray1::from_vec(py, targets))?;
        infos.set_item("_target_gate", &all)?;
        if self.finished.is_empty() {
            return Ok(infos);
        }
        let (mut r, mut l, mut laps, mut gates) = (vec![0f32; n], vec![0i32; n], vec![0i32; n], vec![0i32; n]);
        let (mut fastest, mut crash_gate, mut mask) = (vec![f64::NAN; n], vec![-1i32; n], vec![false; n]);
        let mut outcome: Vec<Py<PyAny>> = (0..n).map(|_| py.None()).collect();
        for f in &self.finished {
            let (i, s) = (f.env, &f.stats);
            (r[i], l[i], laps[i], gates[i]) = (s.episode_return as f32, s.length as i32, s.laps as i32, s.gates_passed as i32);
            fastest[i] = s.fastest_lap.unwrap_or(f64::NAN);
            if let Ending::Crash(CrashCause::Gate(g)) = f.ending {
                crash_gate[i] = g as i32;
            }
            outcome[i] = PyString::new(py, f.ending.name()).into_any().unbind();
            mask[i] = true;
        }
        let episode = PyDict::new(py);
        episode.set_item("r", PyArray1::from_vec(py, r))?;
        episode.set_item("l", PyArray1::from_vec(py, l))?;
        episode.set_item("laps", PyArray1::from_vec(py, laps))?;
        episode.set_item("gates_passed", PyArray1::from_vec(py, gates))?;
        episode.set_item("fastest_lap", PyArray1::from_vec(py, fastest))?;
        episode.set_item("outcome", PyArray1::from_vec(py, outcome))?;
        episode.set_item("crash_gate", PyArray1::from_vec(py, crash_gate))?;
        infos.set_item("episode", episode)?;
        infos.set_item("_episode", PyArray1::from_vec(py, mask))?;
        Ok(infos)
    }
}

/// Copies `values` into `array`, with the interpreter's lock held, if the array is still as
/// the environment made it: writeable, of element type `T`, C-contiguous and of `shape`. An
/// array Python made read-only, resized, reshaped or re-typed is left alone (the user's) and a
/// fresh one takes its place, which the getters and the next step return.
fn publish<T: Element + Copy, D: Dimension>(py: Python<'_>, array: &mut Py<PyArray<T, D>>, values: &[T], shape: D) -> PyResult<()> {
    let bound = array.bind(py);
    let as_made = bound.dtype().is_equiv_to(&numpy::dtype::<T>(py)) && bound.shape() == shape.slice() && bound.is_c_contiguous();
    // The borrow checks the writeable flag (and that no Rust code holds the array).
    if as_made
        && let Ok(mut target) = bound.try_readwrite()
        && let Ok(slice) = target.as_slice_mut()
        && slice.len() == values.len()
    {
        slice.copy_from_slice(values);
        return Ok(());
    }
    *array = PyArray1::from_slice(py, values).reshape(shape)?.unbind();
    Ok(())
}

/// One environment's step: a pending restart (the action ignored), or the action flown.
fn step_slot(slot: &mut Slot, action: &[f32]) -> Stepped {
    match slot.restart.take() {
        Some(Restart::Episode) => {
            slot.env.reset();
            Stepped::default()
        }
        Some(Restart::Track(track)) => {
            slot.env.set_track(track);
            Stepped::default()
        }
        None => {
            let out = slot.env.step(&[action[0], action[1], action[2], action[3]]);
            slot.rollout_return += out.reward.total();
            let ended = out.done().then(|| {
                slot.restart = Some(Restart::Episode);
                (*slot.env.stats(), out.crash)
            });
            Stepped { reward: out.reward.total() as f32, terminated: out.terminated, truncated: out.truncated, ended }
        }
    }
}
