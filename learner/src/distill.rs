//! Teacher–student distillation by DAgger (Ross, Gordon and Bagnell 2011): the aggregated data
//! set of visited states, each labelled with the teacher's action (a state-based policy's mean,
//! or the reference pilot's), and the student's supervised regression on it — a vision student,
//! or a state-based one (imitation of the pilot). The loop that flies the student and
//! fills the data set is `runtime::distill`.
//!
//! A sample keeps the camera's pose (track, target gate, position, attitude), not its image:
//! the renderer is deterministic, so a minibatch's images are rendered again when it is trained
//! on (~10 µs an image, against ~1 ms for the CNN's gradient on it). A sample then takes ~250
//! bytes instead of 7 kB, so a data set of a million samples and its checkpoint stay small.

use std::collections::HashMap;
use std::sync::Arc;

use burn::module::Module;
use burn::optim::{AdamConfig, GradientsParams, ModuleOptimizer};
use burn::tensor::{Bytes, Device, Tensor, TensorData};
use policy::gate_head::{GATE_TARGETS, GateHead, gate_targets, shown_mask};
use policy::vision::image_tensor;
use policy::{Agent, Architecture, ObsNormalizer, VisionActorCritic, WeightsBlob};
use rand::Rng;
use rayon::prelude::*;
use sim::camera::IMAGE_PIXELS;
use sim::frame_stack::render_frames;
use sim::{ACTION_DIM, CameraHistory, CameraPose, FrameStack, RaceEnv, STATE_OBS_DIM, Track};

use crate::learner::{LearnerError, Network};
use crate::ppo::update::scalar;

/// The frame of a serialised data set (format 3: the frame stack and each sample's frames).
const DATASET_FRAME: frames::FrameKind = frames::FrameKind { magic: b"DRDAGGER", format: 3, name: "distillation data set" };

/// Format 2, still read: one frame a sample, the state length recorded.
const DATASET_FRAME_V2: frames::FrameKind = frames::FrameKind { format: 2, ..DATASET_FRAME };

/// Format 1, still read: one frame a sample, every state SPEC §5's 40 numbers.
const DATASET_FRAME_V1: frames::FrameKind = frames::FrameKind { format: 1, ..DATASET_FRAME };

/// One visited state: where the camera was at the frames the student sees and the teacher's
/// label (its raw state observation is the data set's row of the same index).
#[derive(Clone, Debug, PartialEq)]
struct Sample {
    /// Index into the data set's track table.
    track: u32,
    /// The camera poses of the frames seen, the current one first.
    frames: Vec<CameraPose>,
    /// Teacher's deterministic action.
    label: [f32; ACTION_DIM],
}

impl Sample {
    /// The current camera pose.
    fn now(&self) -> &CameraPose {
        &self.frames[0]
    }
}

/// A visited state with its teacher's label, not yet in a data set.
#[derive(Clone, Debug, PartialEq)]
pub struct LabelledState {
    sample: Sample,
    state: Vec<f32>,
}

/// DAgger's aggregated data set, capped by reservoir sampling: once full, the `n`-th sample
/// seen replaces a random one with probability `capacity / n`, so the set stays a uniform
/// sample of every state visited so far (DAgger aggregates all of them).
#[derive(Debug, Default)]
pub struct DistillDataset {
    tracks: Vec<Arc<Track>>,
    /// Track table index by the address of the `Arc` the environments hold (the table keeps
    /// every `Arc` alive, so an address is never reused for another track).
    track_index: HashMap<usize, u32>,
    samples: Vec<Sample>,
    /// Raw state observations (the teacher's layout), `state_dim` per sample, in sample order.
    states: Vec<f32>,
    state_dim: usize,
    /// The camera frames every sample holds.
    frame_stack: FrameStack,
    capacity: usize,
    seen: u64,
}

impl DistillDataset {
    /// An empty data set holding at most `capacity` samples of `state_dim`-number states and
    /// the camera frames of `frame_stack`.
    pub fn new(capacity: usize, state_dim: usize, frame_stack: FrameStack) -> Self {
        Self { capacity: capacity.max(1), state_dim, frame_stack, ..Self::default() }
    }

    /// The camera frames every sample holds.
    pub fn frame_stack(&self) -> FrameStack {
        self.frame_stack
    }

    /// Length of a sample's raw state observation.
    pub fn state_dim(&self) -> usize {
        self.state_dim
    }

    /// Samples held.
    pub fn len(&self) -> usize {
        self.samples.len()
    }

    /// True when no sample is held.
    pub fn is_empty(&self) -> bool {
        self.samples.is_empty()
    }

    /// Samples offered so far (held or not).
    pub fn seen(&self) -> u64 {
        self.seen
    }

    /// Offers the state `env` is in with its current camera frame (a data set of single
    /// frames), its raw observation `state` (`state_dim` numbers) and the teacher's `label`.
    pub fn offer(&mut self, env: &RaceEnv, state: &[f32], label: &[f32], rng: &mut impl Rng) {
        let labelled = self.label(env, None, state, label);
        self.offer_labelled(labelled, rng);
    }

    /// The state `env` is in, with the frames `camera` (its history, of the data set's frame
    /// stack; `None`: the current frame of a single-frame data set) shows of it, labelled, to
    /// be offered later ([`DistillDataset::offer_labelled`]) or dropped: e.g. held back until
    /// it is known not to be the run-up to a crash.
    pub fn label(&mut self, env: &RaceEnv, camera: Option<&CameraHistory>, state: &[f32], label: &[f32]) -> LabelledState {
        assert_eq!(state.len(), self.state_dim, "a state of the data set's length");
        let frames = match camera {
            Some(camera) => camera.frames(),
            None => vec![CameraPose::of(env)],
        };
        assert_eq!(frames.len(), self.frame_stack.frames, "the frames of the data set's frame stack");
        debug_assert_eq!(frames.first(), Some(&CameraPose::of(env)), "the history is the environment's");
        let sample = Sample { track: self.track_id(env.track()), frames, label: std::array::from_fn(|i| label[i]) };
        LabelledState { sample, state: state.to_vec() }
    }

    /// Offers a state labelled by [`DistillDataset::label`].
    pub fn offer_labelled(&mut self, labelled: LabelledState, rng: &mut impl Rng) {
        self.seen += 1;
        let slot = if self.samples.len() < self.capacity {
            None
        } else {
            match rng.random_range(0..self.seen) {
                j if j < self.capacity as u64 => Some(j as usize),
                _ => return,
            }
        };
        let LabelledState { sample, state } = labelled;
        match slot {
            Some(j) => {
                self.samples[j] = sample;
                let range = self.state_range(j);
                self.states[range].copy_from_slice(&state);
            }
            None => {
                self.samples.push(sample);
                self.states.extend_from_slice(&state);
            }
        }
    }

    /// Where sample `row`'s state sits in `states`.
    fn state_range(&self, row: usize) -> std::ops::Range<usize> {
        row * self.state_dim..(row + 1) * self.state_dim
    }

    fn track_id(&mut self, track: &Arc<Track>) -> u32 {
        let key = Arc::as_ptr(track) as usize;
        if let Some(&id) = self.track_index.get(&key) {
            return id;
        }
        let id = self.tracks.len() as u32;
        self.tracks.push(track.clone());
        self.track_index.insert(key, id);
        id
    }

    /// The camera observations of samples `rows` (`rows.len() × frames × 84 × 84` bytes, each
    /// sample's current frame first), rendered again.
    pub fn images(&self, rows: &[usize]) -> Vec<u8> {
        let len = self.frame_stack.image_len();
        let mut out = vec![0u8; rows.len() * len];
        out.par_chunks_mut(len).zip(rows.par_iter()).for_each(|(images, &row)| {
            let sample = &self.samples[row];
            render_frames(&sample.frames, &self.tracks[sample.track as usize], images);
        });
        out
    }

    /// Where the gates are seen from samples `rows` (`rows.len() × 26` numbers, as
    /// [`policy::gate_head::gate_targets`]): the targets of a student's gate head.
    pub fn gate_targets(&self, rows: &[usize]) -> Vec<f32> {
        rows.iter()
            .flat_map(|&r| {
                let sample = &self.samples[r];
                let (position, rotation) = sample.now().position_and_rotation();
                gate_targets(&self.tracks[sample.track as usize], sample.now().target as usize, &position, &rotation)
            })
            .collect()
    }

    /// Labels every sample again with `teacher`'s actions for its stored state (`rows × state_dim`
    /// numbers in, `rows × ACTION_DIM` out), a few thousand at a time.
    pub fn relabel(&mut self, teacher: impl Fn(&[f32]) -> Vec<f32>) {
        const ROWS: usize = 4096;
        for (chunk, states) in self.samples.chunks_mut(ROWS).zip(self.states.chunks(ROWS * self.state_dim.max(1))) {
            let labels = teacher(states);
            assert_eq!(labels.len(), chunk.len() * ACTION_DIM, "one label per state");
            for (sample, label) in chunk.iter_mut().zip(labels.chunks_exact(ACTION_DIM)) {
                sample.label = std::array::from_fn(|k| label[k]);
            }
        }
    }

    /// Raw state observations of samples `rows`, row after row.
    pub fn states(&self, rows: &[usize]) -> Vec<f32> {
        rows.iter().flat_map(|&r| &self.states[self.state_range(r)]).copied().collect()
    }

    /// Teacher labels of samples `rows`, row after row.
    pub fn labels(&self, rows: &[usize]) -> Vec<f32> {
        rows.iter().flat_map(|&r| self.samples[r].label).collect()
    }

    /// The data set as bytes (a `frames` frame): capacity, count seen, state length, frame
    /// stack, the tracks (JSON), the samples.
    #[allow(clippy::expect_used, reason = "tracks serialise")]
    pub fn to_bytes(&self) -> Vec<u8> {
        let tracks: Vec<&Track> = self.tracks.iter().map(Arc::as_ref).collect();
        let tracks = serde_json::to_vec(&tracks).expect("tracks serialise");
        let mut body = Vec::with_capacity(32 + tracks.len() + self.samples.len() * 256);
        body.extend_from_slice(&(self.capacity as u64).to_le_bytes());
        body.extend_from_slice(&self.seen.to_le_bytes());
        body.extend_from_slice(&(self.state_dim as u64).to_le_bytes());
        body.extend_from_slice(&(self.frame_stack.frames as u64).to_le_bytes());
        body.extend_from_slice(&(self.frame_stack.stride as u64).to_le_bytes());
        body.extend_from_slice(&(tracks.len() as u64).to_le_bytes());
        body.extend_from_slice(&tracks);
        body.extend_from_slice(&(self.samples.len() as u64).to_le_bytes());
        for (i, s) in self.samples.iter().enumerate() {
            body.extend_from_slice(&s.track.to_le_bytes());
            for frame in &s.frames {
                body.extend_from_slice(&frame.target.to_le_bytes());
                for v in frame.position.iter().chain(&frame.attitude) {
                    body.extend_from_slice(&v.to_le_bytes());
                }
            }
            frames::put_f32s(&mut body, &self.states[self.state_range(i)]);
            frames::put_f32s(&mut body, &s.label);
        }
        DATASET_FRAME.encode(&body)
    }

    /// Reads [`DistillDataset::to_bytes`]' output, or a data set of an earlier format (one
    /// frame a sample; format 1 also without the state length: SPEC §5's 40 numbers); errors
    /// say what is wrong.
    pub fn from_bytes(bytes: &[u8]) -> Result<Self, LearnerError> {
        let (body, format) = match DATASET_FRAME.decode(bytes) {
            Ok(body) => (body, 3),
            Err(frames::FrameError::UnsupportedFormat { found: found @ (1 | 2), .. }) => {
                let kind = if found == 1 { DATASET_FRAME_V1 } else { DATASET_FRAME_V2 };
                (kind.decode(bytes).map_err(|e| LearnerError::State(e.to_string()))?, found)
            }
            Err(e) => return Err(LearnerError::State(e.to_string())),
        };
        let bad = |what: String| LearnerError::State(format!("distillation data set: {what}"));
        let short = |t: frames::Truncated| bad(format!("ends {} bytes short at byte {}", t.needed, t.at));
        let mut r = frames::Reader::new(body, 0);
        let capacity = r.u64().map_err(short)? as usize;
        let seen = r.u64().map_err(short)?;
        let state_dim = if format >= 2 { r.u64().map_err(short)? as usize } else { STATE_OBS_DIM };
        let frame_stack = match format {
            3 => FrameStack { frames: r.u64().map_err(short)? as usize, stride: r.u64().map_err(short)? as usize },
            _ => FrameStack::default(),
        };
        frame_stack.check().map_err(bad)?;
        let json_len = r.u64().map_err(short)? as usize;
        let tracks: Vec<Track> = serde_json::from_slice(r.take(json_len).map_err(short)?).map_err(|e| bad(format!("track table: {e}")))?;
        let tracks: Vec<Arc<Track>> = tracks.into_iter().map(Arc::new).collect();
        let count = r.u64().map_err(short)? as usize;
        let frame_bytes = 4 + 7 * 8;
        // Sizes come from the file: every capacity is bounded by the bytes that are really there.
        let per_sample = frame_stack
            .frames
            .saturating_mul(frame_bytes)
            .saturating_add(state_dim.saturating_add(ACTION_DIM).saturating_mul(4))
            .saturating_add(4);
        let mut samples = Vec::with_capacity(r.capacity_for(count, per_sample));
        let mut states = Vec::with_capacity(samples.capacity().saturating_mul(state_dim));
        for i in 0..count {
            let track = r.u32().map_err(short)?;
            let gates = tracks.get(track as usize).map(|t| t.gates.len()).ok_or_else(|| bad(format!("sample {i}: no track {track}")))?;
            let mut frames = Vec::with_capacity(r.capacity_for(frame_stack.frames, frame_bytes));
            for _ in 0..frame_stack.frames {
                let target = r.u32().map_err(short)?;
                if target as usize >= gates {
                    return Err(bad(format!("sample {i}: target gate {target} of a {gates}-gate track")));
                }
                let mut pose = [0f64; 7];
                for v in &mut pose {
                    *v = r.f64().map_err(short)?;
                }
                frames.push(CameraPose { target, position: [pose[0], pose[1], pose[2]], attitude: [pose[3], pose[4], pose[5], pose[6]] });
            }
            states.extend(r.f32s(state_dim).map_err(short)?);
            let label = r.f32s(ACTION_DIM).map_err(short)?;
            samples.push(Sample { track, frames, label: std::array::from_fn(|k| label[k]) });
        }
        if r.remaining() != 0 || samples.len() > capacity.max(1) {
            return Err(bad(format!("{} bytes after {count} samples, capacity {capacity}", r.remaining())));
        }
        let track_index = tracks.iter().enumerate().map(|(i, t)| (Arc::as_ptr(t) as usize, i as u32)).collect();
        Ok(Self { tracks, track_index, samples, states, state_dim, frame_stack, capacity: capacity.max(1), seen })
    }
}

/// A student under supervised training: its actor regresses the teacher's actions. Taught by a
/// state-based policy, it takes the teacher's critic (same state input, so that PPO can start
/// from the student) and its normaliser, frozen. Taught by a scripted teacher (the reference
/// pilot), it has a fresh critic and learns its normaliser from the states it is shown
/// ([`Student::observe`]), as PPO would. A vision student may also carry a gate head
/// ([`Student::with_gate_head`]) whose loss on its embedding is added to the imitation loss.
pub struct Student {
    /// Always `Some` between calls; taken while burn's optimiser consumes and returns it.
    model: Option<Network>,
    optimizer: ModuleOptimizer,
    architecture: Architecture,
    normalizer: ObsNormalizer,
    /// True when the normaliser follows the states seen (no policy teacher to take it from).
    learns_normalizer: bool,
    version: u64,
    device: Device,
    /// The training-only gate head and the weight of its loss, when the student has one.
    gate_head: Option<(GateHead, f64)>,
    /// True when a vision student's CNN and embedding layer keep their weights
    /// ([`Student::with_frozen_encoder`]).
    frozen_encoder: bool,
}

/// The losses of one regression step, before it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct StepLoss {
    /// Mean squared error of the action means against the teacher's labels.
    pub imitation: f64,
    /// Mean squared error of the gate head on the gates the images show (none without a head).
    pub gate: Option<f64>,
}

/// Adam for the regression (ε as SPEC §10; no weight decay).
fn student_adam() -> ModuleOptimizer {
    AdamConfig::new().with_epsilon(1e-5).init()
}

impl Student {
    /// A student of `architecture` (its agent says which network): a fresh actor (seeded, log
    /// std `initial_log_std`), or `start`'s (a policy of the same architecture, e.g. a student
    /// distilled on one track) with a fresh optimiser. With a `teacher` — a state-based policy
    /// whose observation and hidden widths `architecture` shares — the critic and the
    /// normaliser are the teacher's; without one, a fresh critic and a normaliser to learn.
    pub fn new(
        architecture: &Architecture,
        teacher: Option<&WeightsBlob>,
        start: Option<&WeightsBlob>,
        initial_log_std: f64,
        seed: u64,
    ) -> Result<Self, LearnerError> {
        let device = Device::flex().autodiff();
        let architecture = architecture.clone();
        let start_error = |e: policy::BlobError| LearnerError::State(format!("starting student: {e}"));
        // A vision start whose actor does not read the previous action learns to: it is widened
        // with zero weights, so the student starts out acting exactly as the start did.
        let widened = match start {
            Some(blob) if architecture.vision_previous_action && !blob.architecture.vision_previous_action => {
                Some(blob.with_vision_previous_action().map_err(start_error)?)
            }
            _ => None,
        };
        let start = widened.as_ref().or(start);
        // A single-frame vision start learns to see earlier frames as well, the same way: its
        // first convolution gains zero weights for them.
        let stacked = match start {
            Some(blob) if blob.architecture.agent == Agent::Vision && blob.architecture.frame_stack != architecture.frame_stack => {
                Some(blob.with_frame_stack(architecture.frame_stack, policy::FrameWidening::Zero).map_err(start_error)?)
            }
            _ => None,
        };
        let start = stacked.as_ref().or(start);
        if let Some(blob) = start {
            // A vision student's CNN and actor read the image and the proprioception alone, and
            // its critic becomes the teacher's: a start taught in another layout fits.
            let mut expected = architecture.clone();
            if teacher.is_some() && architecture.agent == Agent::Vision {
                expected.set_observation_layout(blob.architecture.observation);
            }
            blob.check_architecture(&expected).map_err(start_error)?;
        }
        let mut model = match start {
            None => Network::new(&architecture, initial_log_std, seed, &device),
            Some(blob) => Network::from_blob(blob, &device).map_err(start_error)?,
        };
        let normalizer = match teacher {
            None => start.map_or_else(|| ObsNormalizer::new(architecture.observation_dim), |blob| blob.normalizer.clone()),
            Some(teacher) => {
                let teacher_error = |e: policy::BlobError| LearnerError::State(format!("teacher: {e}"));
                teacher.check_agent(Agent::State).map_err(teacher_error)?;
                teacher
                    .check_architecture(&Architecture {
                        agent: Agent::State,
                        vision_previous_action: false,
                        frame_stack: FrameStack::default(),
                        ..architecture.clone()
                    })
                    .map_err(teacher_error)?;
                let critic = teacher.model(&device).map_err(teacher_error)?.critic;
                match &mut model {
                    Network::State(m) => m.critic = critic,
                    Network::Vision(m) => m.critic = critic,
                }
                teacher.normalizer.clone()
            }
        };
        Ok(Self {
            model: Some(model),
            optimizer: student_adam(),
            architecture,
            normalizer,
            learns_normalizer: teacher.is_none(),
            version: 0,
            device,
            gate_head: None,
            frozen_encoder: false,
        })
    }

    /// Restores a student from its weights blob and optimiser state ([`Student::weights`],
    /// [`Student::optimizer_state`]); `learns_normalizer` as it was created (no policy teacher).
    pub fn restore(weights: &[u8], optimizer: &[u8], learns_normalizer: bool) -> Result<Self, LearnerError> {
        let blob = WeightsBlob::from_bytes(weights).map_err(|e| LearnerError::State(e.to_string()))?;
        let device = Device::flex().autodiff();
        let model = Network::from_blob(&blob, &device).map_err(|e| LearnerError::State(e.to_string()))?;
        let optimizer = student_adam()
            .from_bytes(Bytes::from_bytes_vec(optimizer.to_vec()))
            .map_err(|e| LearnerError::State(format!("student optimiser: {e:?}")))?;
        Ok(Self {
            model: Some(model),
            optimizer,
            architecture: blob.architecture.clone(),
            normalizer: blob.normalizer,
            learns_normalizer,
            version: blob.version,
            device,
            gate_head: None,
            frozen_encoder: false,
        })
    }

    /// Gives a vision student a gate head whose loss counts `weight` times the imitation loss:
    /// `saved` ([`Student::gate_head_bytes`], on resume) or a fresh one from `seed`.
    pub fn with_gate_head(mut self, weight: f64, saved: Option<&[u8]>, seed: u64) -> Result<Self, LearnerError> {
        if !matches!(self.model(), Network::Vision(_)) {
            return Err(LearnerError::State("a gate head needs a vision student".into()));
        }
        let head = match saved {
            Some(bytes) => GateHead::from_bytes(bytes, &self.device).map_err(LearnerError::State)?,
            None => GateHead::new(seed, &self.device),
        };
        self.gate_head = Some((head, weight));
        Ok(self)
    }

    /// Keeps a vision student's CNN and embedding layer as they are: only its actor (and a
    /// gate head) learn, on the embedding of a CNN trained apart, e.g. to place gates
    /// ([`Student::gate_step`]). Errors for a state student.
    pub fn with_frozen_encoder(mut self) -> Result<Self, LearnerError> {
        if !matches!(self.model(), Network::Vision(_)) {
            return Err(LearnerError::State("a frozen encoder needs a vision student".into()));
        }
        self.frozen_encoder = true;
        Ok(self)
    }

    /// The gate head's weights, for exact resume (none without a head).
    pub fn gate_head_bytes(&self) -> Option<Vec<u8>> {
        self.gate_head.as_ref().map(|(head, _)| head.to_bytes())
    }

    #[allow(clippy::expect_used, reason = "the model is present between calls")]
    fn model(&self) -> &Network {
        self.model.as_ref().expect("the model is present between calls")
    }

    /// Gradient steps taken so far (the blob's version).
    pub fn version(&self) -> u64 {
        self.version
    }

    /// The student as a weights blob of its agent.
    pub fn weights(&self) -> WeightsBlob {
        self.model().blob(self.version, &self.architecture, &self.normalizer)
    }

    /// The optimiser's moments, for exact resume.
    #[allow(clippy::expect_used, reason = "optimiser state serialises")]
    pub fn optimizer_state(&self) -> Vec<u8> {
        self.optimizer.into_bytes().expect("optimiser state serialises").to_vec()
    }

    /// Shows the student raw states (rows of the observation): a student without a policy
    /// teacher folds them into its normaliser; one with a teacher keeps the teacher's.
    pub fn observe(&mut self, raw_states: &[f32]) {
        if self.learns_normalizer {
            self.normalizer.update(raw_states);
        }
    }

    /// One gradient step of the mean squared error between the student's action means and the
    /// teacher's labels on samples `rows` of `data` (plus the gate head's weighted loss when the
    /// student has one); returns the losses before the step.
    #[allow(clippy::expect_used, reason = "the model is present between calls; float outputs")]
    pub fn train_step(&mut self, data: &DistillDataset, rows: &[usize], learning_rate: f64) -> StepLoss {
        let n = rows.len();
        let dim = data.state_dim();
        let mut states = vec![0.0; n * dim];
        self.normalizer.normalize(&data.states(rows), &mut states);
        let states = Tensor::<2>::from_data(TensorData::new(states, [n, dim]), &self.device);
        let labels = Tensor::<2>::from_data(TensorData::new(data.labels(rows), [n, ACTION_DIM]), &self.device);
        let squared_error = |means: Tensor<2>| (means - labels).powi_scalar(2).mean();
        let (loss, model) = match self.model.take().expect("the model is present between calls") {
            Network::State(model) => {
                let loss = squared_error(model.action_means(states));
                let value = f64::from(scalar(loss.clone()));
                let grads = GradientsParams::from_grads(loss.backward(), &model);
                (StepLoss { imitation: value, gate: None }, Network::State(self.optimizer.step(learning_rate, model, grads)))
            }
            Network::Vision(model) => {
                assert_eq!(data.frame_stack().frames, model.frames(), "a data set of the frames the student sees");
                let pixels = data.images(rows);
                let embedding = self.embedding(&model, &pixels, data.frame_stack().frames, !self.frozen_encoder);
                let imitation = squared_error(model.actor_mean_of(embedding.clone(), states));
                let imitation_value = f64::from(scalar(imitation.clone()));
                match self.gate_head.take() {
                    None => {
                        let grads = GradientsParams::from_grads(imitation.backward(), &model);
                        let model = self.optimizer.step(learning_rate, model, grads);
                        (StepLoss { imitation: imitation_value, gate: None }, Network::Vision(model))
                    }
                    Some((head, weight)) => {
                        let gate = gate_loss(&head, embedding, &pixels, data, rows, &self.device);
                        let gate_value = f64::from(scalar(gate.clone()));
                        let mut grads = (imitation + gate.mul_scalar(weight)).backward();
                        let model_grads = GradientsParams::from_module(&mut grads, &model);
                        let head_grads = GradientsParams::from_module(&mut grads, &head);
                        let model = self.optimizer.step(learning_rate, model, model_grads);
                        self.gate_head = Some((self.optimizer.step(learning_rate, head, head_grads), weight));
                        (StepLoss { imitation: imitation_value, gate: Some(gate_value) }, Network::Vision(model))
                    }
                }
            }
        };
        self.model = Some(model);
        self.version += 1;
        loss
    }

    /// One gradient step of the gate head's loss alone on samples `rows` — the student's
    /// perception trained apart from imitation, its actor untouched. With `train_cnn` false
    /// (or a frozen encoder) only the head learns: a probe of what the CNN already encodes.
    /// Returns the loss before the step; errors without a vision student and a gate head.
    #[allow(clippy::expect_used, reason = "the model is present between calls; float outputs")]
    pub fn gate_step(&mut self, data: &DistillDataset, rows: &[usize], learning_rate: f64, train_cnn: bool) -> Result<f64, LearnerError> {
        let Some((head, weight)) = self.gate_head.take() else {
            return Err(LearnerError::State("a gate step needs a gate head".into()));
        };
        let model = match self.model.take().expect("the model is present between calls") {
            Network::Vision(model) => model,
            other => {
                self.model = Some(other);
                self.gate_head = Some((head, weight));
                return Err(LearnerError::State("a gate step needs a vision student".into()));
            }
        };
        let train_cnn = train_cnn && !self.frozen_encoder;
        let pixels = data.images(rows);
        let embedding = self.embedding(&model, &pixels, data.frame_stack().frames, train_cnn);
        let loss = gate_loss(&head, embedding, &pixels, data, rows, &self.device);
        let value = f64::from(scalar(loss.clone()));
        let mut grads = loss.backward();
        let head_grads = GradientsParams::from_module(&mut grads, &head);
        let model = match train_cnn {
            true => {
                let model_grads = GradientsParams::from_module(&mut grads, &model);
                self.optimizer.step(learning_rate, model, model_grads)
            }
            false => model,
        };
        self.gate_head = Some((self.optimizer.step(learning_rate, head, head_grads), weight));
        self.model = Some(Network::Vision(model));
        self.version += 1;
        Ok(value)
    }

    /// `model`'s embedding of `pixels`; a constant that no gradient reaches unless `trained`.
    fn embedding(&self, model: &VisionActorCritic, pixels: &[u8], frames: usize, trained: bool) -> Tensor<2> {
        if trained {
            return model.embed(image_tensor(pixels, frames, &self.device));
        }
        // On the inner backend, as PPO's frozen layers are: a graph recorded through the CNN
        // and then detached would be kept by burn's autodiff, never differentiated.
        let inner = self.device.clone().without_autodiff();
        Tensor::<2>::from_data(model.valid().embed(image_tensor(pixels, frames, &inner)).into_data(), &self.device)
    }

    /// The student's vision network and gate head as they are now, for analyses (none for a
    /// state student or one without a head).
    pub fn vision_with_gate_head(&self) -> Option<(VisionActorCritic, GateHead)> {
        match (self.model(), &self.gate_head) {
            (Network::Vision(model), Some((head, _))) => Some((model.valid(), head.valid())),
            _ => None,
        }
    }
}

/// The gate head's loss on `embedding` (of `pixels`, samples `rows` of `data`): the mean squared
/// error over the numbers scored, those of the gates each sample's current frame shows — a
/// mean over them, so a loss weight does not depend on how often gates are in view.
fn gate_loss(head: &GateHead, embedding: Tensor<2>, pixels: &[u8], data: &DistillDataset, rows: &[usize], device: &Device) -> Tensor<1> {
    let n = rows.len();
    // The head places the gates of the current frame, each observation's first.
    let observation = data.frame_stack().image_len();
    let mask: Vec<f32> = pixels.chunks_exact(observation).flat_map(|o| shown_mask(&o[..IMAGE_PIXELS])).collect();
    let scored = mask.iter().sum::<f32>().max(1.0);
    let mask = Tensor::<2>::from_data(TensorData::new(mask, [n, GATE_TARGETS]), device);
    let targets = Tensor::<2>::from_data(TensorData::new(data.gate_targets(rows), [n, GATE_TARGETS]), device);
    ((head.forward(embedding) - targets).powi_scalar(2) * mask).sum().div_scalar(scored)
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;
    use sim::nalgebra::Vector3;
    use sim::{Controller, EnvConfig, Gate};

    fn track() -> Arc<Track> {
        let gates = vec![Gate::new(Vector3::new(4.0, 0.0, 2.0), 0.0), Gate::new(Vector3::new(-4.0, 0.0, 2.0), 3.0)];
        Arc::new(Track::new("two", gates, None, sim::Arena::default()).unwrap())
    }

    #[test]
    fn the_reservoir_keeps_its_cap_and_a_uniform_sample_and_the_bytes_round_trip() {
        // Line points make the state longer than SPEC §5's; the data set keeps whatever it is given.
        let layout = sim::ObservationLayout { line_points: 3, ..sim::ObservationLayout::spec(sim::ObservationFrame::Heading) };
        let mut data = DistillDataset::new(100, layout.dim(), FrameStack::default());
        let mut rng = ChaCha8Rng::seed_from_u64(0);
        let mut env = RaceEnv::new(track(), EnvConfig::default(), 0, 0);
        let mut offered = Vec::new();
        for i in 0..1000 {
            // The label numbers the sample, so the survivors tell which were kept.
            let state = env.observation_in(layout);
            data.offer(&env, &state, &[i as f32, 0.0, 0.0, 0.0], &mut rng);
            offered.push(state);
            env.step(&[0.1, 0.0, 0.0, 0.0]);
            if env.stats().crash.is_some() || env.stats().length >= 200 {
                env.reset();
            }
        }
        assert_eq!((data.len(), data.seen()), (100, 1000));
        assert_eq!(data.tracks.len(), 1, "one track, one table entry");
        let kept: Vec<f32> = data.labels(&(0..100).collect::<Vec<_>>()).chunks(4).map(|l| l[0]).collect();
        let late = kept.iter().filter(|&&i| i >= 500.0).count();
        // Uniform over 1000 offers: ~50 of the 100 from the second half (binomial sd 5).
        assert!((30..=70).contains(&late), "{late} of 100 from the second half");
        // Each kept state is the one offered with its label.
        let all: Vec<usize> = (0..100).collect();
        for (state, label) in data.states(&all).chunks(layout.dim()).zip(&kept) {
            assert_eq!(state, offered[*label as usize].as_slice());
        }
        let back = DistillDataset::from_bytes(&data.to_bytes()).unwrap();
        assert_eq!((back.samples.clone(), back.seen, back.capacity), (data.samples.clone(), 1000, 100));
        assert_eq!((back.state_dim(), back.states(&all)), (layout.dim(), data.states(&all)));
        assert_eq!(back.images(&[0, 57, 99]), data.images(&[0, 57, 99]), "the same images are rendered again");
        let mut bytes = data.to_bytes();
        bytes.truncate(bytes.len() - 9);
        assert!(DistillDataset::from_bytes(&bytes).is_err());
    }

    #[test]
    fn a_sample_renders_the_image_its_environment_showed() {
        let mut data = DistillDataset::new(10, STATE_OBS_DIM, FrameStack::default());
        let mut env = RaceEnv::new(track(), EnvConfig::default(), 3, 1);
        for _ in 0..20 {
            env.step(&[0.2, 0.1, 0.0, 0.3]);
        }
        data.offer(&env, &[0.0; STATE_OBS_DIM], &[0.0; 4], &mut ChaCha8Rng::seed_from_u64(0));
        let mut shown = vec![0u8; IMAGE_PIXELS];
        env.render_camera(&mut shown);
        assert!(shown.iter().any(|&p| p > 0), "a gate is in view");
        assert_eq!(data.images(&[0]), shown);
    }

    #[test]
    fn format_1_and_2_data_sets_still_read_as_single_frames() {
        let mut data = DistillDataset::new(10, STATE_OBS_DIM, FrameStack::default());
        let env = RaceEnv::new(track(), EnvConfig::default(), 3, 1);
        let state: Vec<f32> = (0..STATE_OBS_DIM).map(|i| i as f32).collect();
        data.offer(&env, &state, &[0.5; 4], &mut ChaCha8Rng::seed_from_u64(0));
        // Format 2 is format 3 of single frames without the frame stack (the fourth and fifth
        // u64 of the body), format 1 is format 2 without the state length (the third).
        let body = DATASET_FRAME.decode(&data.to_bytes()).unwrap().to_vec();
        let v2 = DATASET_FRAME_V2.encode(&[&body[..24], &body[40..]].concat());
        let v1 = DATASET_FRAME_V1.encode(&[&body[..16], &body[40..]].concat());
        for earlier in [v1, v2] {
            let back = DistillDataset::from_bytes(&earlier).unwrap();
            assert_eq!((back.state_dim(), back.states(&[0]), back.labels(&[0])), (STATE_OBS_DIM, state.clone(), vec![0.5; 4]));
            assert_eq!((back.frame_stack(), back.images(&[0])), (FrameStack::default(), data.images(&[0])));
        }
    }

    #[test]
    fn a_stacked_frame_data_set_renders_each_samples_earlier_frames_and_a_stacked_student_learns_from_them() {
        let arch = Architecture { hidden: vec![16, 16], ..Architecture::paper() };
        let teacher = WeightsBlob::from_model(
            1,
            &arch,
            &ObsNormalizer::new(arch.observation_dim),
            &policy::ActorCritic::new(&arch, -0.5, 7, &Device::flex()),
        );
        let stack = FrameStack { frames: 3, stride: 2 };
        let mut data = DistillDataset::new(64, arch.observation_dim, stack);
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        let mut env = RaceEnv::new(track(), EnvConfig::default(), 1, 0);
        let mut camera = CameraHistory::new(stack);
        camera.restart(CameraPose::of(&env));
        let mut shown = Vec::new();
        for step in 0..24 {
            let mut image = vec![0u8; IMAGE_PIXELS];
            env.render_camera(&mut image);
            shown.push(image);
            let labelled = data.label(&env, Some(&camera), &env.observation_in(arch.observation), &[step as f32 / 24.0, 0.5, 0.0, -0.5]);
            data.offer_labelled(labelled, &mut rng);
            env.step(&[0.3, 0.2, -0.1, 0.2]);
            camera.record(CameraPose::of(&env));
        }
        assert_eq!(data.images(&[10]), [&shown[10][..], &shown[8], &shown[6]].concat(), "the frames of steps 10, 8 and 6");
        assert_eq!(data.images(&[1]), [&shown[1][..], &shown[0], &shown[0]].concat(), "the first frame stands in before it");
        let back = DistillDataset::from_bytes(&data.to_bytes()).unwrap();
        let rows: Vec<usize> = (0..data.len()).collect();
        assert_eq!((back.frame_stack(), back.images(&rows)), (stack, data.images(&rows)), "the frames round-trip");

        // A stacked student started from a single-frame one acts as it did, then learns.
        let vision_arch = Architecture { agent: Agent::Vision, ..arch.clone() };
        let single = Student::new(&vision_arch, Some(&teacher), None, 0.0, 2).unwrap().weights();
        let stacked_arch = Architecture { frame_stack: stack, ..vision_arch };
        let mut student = Student::new(&stacked_arch, Some(&teacher), Some(&single), 0.0, 3).unwrap();
        let (images, states) = (data.images(&rows), data.states(&rows));
        let current: Vec<u8> = images.chunks_exact(stack.image_len()).flat_map(|o| o[..IMAGE_PIXELS].to_vec()).collect();
        let act = |blob: &WeightsBlob, images: &[u8]| policy::VisionPolicy::from_blob(blob).unwrap().mean_actions(images, &states);
        assert_eq!(act(&student.weights(), &images), act(&single, &current));
        let first = student.train_step(&data, &rows, 1e-3).imitation;
        let mut last = first;
        for _ in 0..40 {
            last = student.train_step(&data, &rows, 1e-3).imitation;
        }
        assert!(last < 0.5 * first, "loss {first} → {last}");
        assert_eq!(student.weights().architecture.frame_stack, stack);
    }

    #[test]
    fn regression_brings_the_students_actions_to_the_teachers() {
        // A tiny problem: 32 states on a two-gate track, labels from a fixed teacher.
        let arch = Architecture { hidden: vec![32, 32], ..Architecture::paper() };
        let teacher_net = policy::ActorCritic::new(&arch, -0.5, 7, &Device::flex());
        let teacher = WeightsBlob::from_model(1, &arch, &ObsNormalizer::new(arch.observation_dim), &teacher_net);
        let teacher_policy = policy::Policy::from_blob(&teacher).unwrap();
        let mut data = DistillDataset::new(64, arch.observation_dim, FrameStack::default());
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        let mut env = RaceEnv::new(track(), EnvConfig::default(), 1, 0);
        for _ in 0..32 {
            let state = env.observation_in(arch.observation);
            // Labels scaled up so that the student's initial near-zero head is far from them.
            let label: Vec<f32> = teacher_policy.deterministic_actions(&state).iter().map(|a| (a * 40.0).clamp(-1.0, 1.0)).collect();
            data.offer(&env, &state, &label, &mut rng);
            env.step(&[0.3, 0.2, -0.1, 0.2]);
        }
        let vision_arch = Architecture { agent: Agent::Vision, ..arch.clone() };
        let mut student = Student::new(&vision_arch, Some(&teacher), None, 0.0, 2).unwrap();
        let rows: Vec<usize> = (0..data.len()).collect();
        let first = student.train_step(&data, &rows, 1e-3).imitation;
        let mut last = first;
        for _ in 0..60 {
            last = student.train_step(&data, &rows, 1e-3).imitation;
        }
        assert!(first > 0.05, "the fresh student is far from the labels: {first}");
        assert!(last < 0.25 * first, "loss {first} → {last}");
        // The student's blob flies with the same actions the training saw.
        let blob = student.weights();
        assert_eq!((blob.version, blob.architecture.agent), (61, Agent::Vision));
        let vision = policy::VisionPolicy::from_blob(&blob).unwrap();
        let means = vision.mean_actions(&data.images(&rows), &data.states(&rows));
        let mse: f32 = means.iter().zip(data.labels(&rows)).map(|(m, l)| (m - l).powi(2)).sum::<f32>() / means.len() as f32;
        assert!(f64::from(mse) < 0.3 * first, "{mse}");
        // The critic is the teacher's: same values on the same states.
        let states = Tensor::<2>::from_data(TensorData::new(data.states(&rows[..4]), [4, STATE_OBS_DIM]), &Device::flex());
        let teacher_values = teacher_net.forward(states.clone()).1.into_data();
        let student_values = blob.vision_model(&Device::flex()).unwrap().critic.forward(states).squeeze_dim::<1>(1).into_data();
        assert_eq!(teacher_values, student_values);
        // A new student can start from this one: same actions, a fresh optimiser, version 0.
        let second = Student::new(&vision_arch, Some(&teacher), Some(&blob), 0.0, 99).unwrap();
        let again = policy::VisionPolicy::from_blob(&second.weights()).unwrap().mean_actions(&data.images(&rows), &data.states(&rows));
        assert_eq!((again, second.version()), (means, 0));
        // Exact resume: restored weights and moments take the same next step.
        let mut restored = Student::restore(&blob.to_bytes(), &student.optimizer_state(), false).unwrap();
        assert_eq!(restored.train_step(&data, &rows, 1e-3), student.train_step(&data, &rows, 1e-3));
        assert_eq!(restored.weights(), student.weights());
    }

    /// A data set of 32 states of one flight, state `k` labelled `label(k)`.
    fn flown_states(arch: &Architecture, label: impl Fn(usize) -> [f32; 4]) -> DistillDataset {
        let mut data = DistillDataset::new(64, arch.observation_dim, FrameStack::default());
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        let mut env = RaceEnv::new(track(), EnvConfig::default(), 1, 0);
        for k in 0..32 {
            data.offer(&env, &env.observation_in(arch.observation), &label(k), &mut rng);
            env.step(&[0.3, 0.2, -0.1, 0.2]);
        }
        data
    }

    /// A vision student's parameter values in export order (every network built has its own
    /// parameter ids).
    fn parameter_values(student: &Student) -> Vec<Vec<f32>> {
        student.weights().vision_model(&Device::flex()).unwrap().export().into_iter().map(|p| p.values).collect()
    }

    #[test]
    fn a_gate_head_learns_where_the_gates_are_and_resumes_exactly() {
        let arch = Architecture { hidden: vec![16, 16], ..Architecture::paper() };
        let teacher_net = policy::ActorCritic::new(&arch, -0.5, 7, &Device::flex());
        let teacher = WeightsBlob::from_model(1, &arch, &ObsNormalizer::new(arch.observation_dim), &teacher_net);
        let data = flown_states(&arch, |_| [0.0; 4]);
        let rows: Vec<usize> = (0..data.len()).collect();
        let vision_arch = Architecture { agent: Agent::Vision, ..arch.clone() };
        let plain = Student::new(&vision_arch, Some(&teacher), None, 0.0, 2).unwrap();
        assert!(Student::new(&arch, Some(&teacher), None, 0.0, 2).unwrap().with_gate_head(1.0, None, 3).is_err(), "vision only");
        let mut student = Student::new(&vision_arch, Some(&teacher), None, 0.0, 2).unwrap().with_gate_head(1.0, None, 3).unwrap();
        let first = student.train_step(&data, &rows, 1e-3);
        // The head's loss is added, not mixed in: the imitation loss is the plain student's.
        assert_eq!(first.imitation, { plain }.train_step(&data, &rows, 1e-3).imitation);
        let first_gate = first.gate.unwrap();
        let mut last = first_gate;
        for _ in 0..40 {
            last = student.train_step(&data, &rows, 1e-3).gate.unwrap();
        }
        assert!(last < 0.5 * first_gate, "gate loss {first_gate} → {last}");
        // Resume: weights, optimiser moments and head give the same next step.
        let blob = student.weights();
        let mut restored = Student::restore(&blob.to_bytes(), &student.optimizer_state(), false)
            .unwrap()
            .with_gate_head(1.0, student.gate_head_bytes().as_deref(), 99)
            .unwrap();
        assert_eq!(restored.train_step(&data, &rows, 1e-3), student.train_step(&data, &rows, 1e-3));
        assert_eq!(restored.weights(), student.weights());
    }

    #[test]
    fn gate_steps_train_perception_alone_and_a_probe_leaves_the_cnn_as_it_was() {
        let arch = Architecture { hidden: vec![16, 16], agent: Agent::Vision, ..Architecture::paper() };
        let data = flown_states(&arch, |_| [0.0; 4]);
        let rows: Vec<usize> = (0..data.len()).collect();
        let without_head = Student::new(&arch, None, None, 0.0, 2).unwrap();
        assert!({ without_head }.gate_step(&data, &rows, 1e-3, true).is_err(), "a gate step needs a head");
        let start = Student::new(&arch, None, None, 0.0, 2).unwrap();
        let start_params = parameter_values(&start);
        let (start_cnn, start_actor) = (start_params[..8].to_vec(), start_params[8..14].to_vec());
        for train_cnn in [true, false] {
            let mut student = Student::new(&arch, None, None, 0.0, 2).unwrap().with_gate_head(1.0, None, 3).unwrap();
            let first = student.gate_step(&data, &rows, 1e-3, train_cnn).unwrap();
            let mut last = first;
            for _ in 0..40 {
                last = student.gate_step(&data, &rows, 1e-3, train_cnn).unwrap();
            }
            assert!(last < 0.5 * first, "train_cnn {train_cnn}: gate loss {first} → {last}");
            let now = parameter_values(&student);
            // The actor never moves; the CNN and embedding move only when they train.
            assert_eq!(now[8..14], start_actor[..], "train_cnn {train_cnn}: the actor");
            assert_eq!(now[..8] == start_cnn[..], !train_cnn, "train_cnn {train_cnn}: the CNN");
        }
    }

    #[test]
    fn a_student_with_a_frozen_encoder_fits_its_actor_and_keeps_its_cnn() {
        let arch = Architecture { hidden: vec![16, 16], ..Architecture::paper() };
        let data = flown_states(&arch, |k| [0.5, -0.3, 0.2 * (k % 3) as f32, 0.1]);
        let rows: Vec<usize> = (0..data.len()).collect();
        assert!(Student::new(&arch, None, None, 0.0, 2).unwrap().with_frozen_encoder().is_err(), "vision only");
        let vision_arch = Architecture { agent: Agent::Vision, ..arch };
        let mut student = Student::new(&vision_arch, None, None, 0.0, 2).unwrap().with_frozen_encoder().unwrap();
        let start = parameter_values(&student);
        let first = student.train_step(&data, &rows, 1e-3).imitation;
        let mut last = first;
        for _ in 0..60 {
            last = student.train_step(&data, &rows, 1e-3).imitation;
        }
        assert!(last < 0.5 * first, "imitation loss {first} → {last}");
        let now = parameter_values(&student);
        // Convolutions and embedding layer (the first 8 parameters) as they were; the actor moved.
        assert_eq!(now[..8], start[..8]);
        assert_ne!(now[8..14], start[8..14]);
    }

    #[test]
    fn a_vision_student_starts_from_one_taught_in_another_layout_and_takes_the_new_teachers_critic() {
        let arch = Architecture { hidden: vec![16, 16], ..Architecture::paper() };
        let mut line_arch = arch.clone();
        line_arch.set_observation_layout(sim::ObservationLayout { line_points: 4, ..arch.observation });
        let teacher_of = |a: &Architecture, seed| {
            let net = policy::ActorCritic::new(a, -0.5, seed, &Device::flex());
            WeightsBlob::from_model(1, a, &ObsNormalizer::new(a.observation_dim), &net)
        };
        let (old_teacher, new_teacher) = (teacher_of(&arch, 1), teacher_of(&line_arch, 2));
        let vision = |a: &Architecture| Architecture { agent: Agent::Vision, ..a.clone() };
        let first = Student::new(&vision(&arch), Some(&old_teacher), None, 0.0, 3).unwrap().weights();
        let second = Student::new(&vision(&line_arch), Some(&new_teacher), Some(&first), 0.0, 4).unwrap().weights();
        assert_eq!(second.architecture, vision(&line_arch));
        // Same CNN and actor: the same actions on the same image and proprioception.
        let env = RaceEnv::new(track(), EnvConfig::default(), 1, 0);
        let mut image = vec![0u8; IMAGE_PIXELS];
        env.render_camera(&mut image);
        let act =
            |blob: &WeightsBlob, layout| policy::VisionPolicy::from_blob(blob).unwrap().mean_actions(&image, &env.observation_in(layout));
        assert_eq!(act(&first, arch.observation), act(&second, line_arch.observation));
        // The critic is the new teacher's.
        let states = Tensor::<2>::from_data(TensorData::new(env.observation_in(line_arch.observation), [1, 52]), &Device::flex());
        let teacher_value = new_teacher.model(&Device::flex()).unwrap().forward(states.clone()).1.into_data();
        let student_value = second.vision_model(&Device::flex()).unwrap().critic.forward(states).squeeze_dim::<1>(1).into_data();
        assert_eq!(teacher_value, student_value);
        // A state student still needs its start's exact shape.
        assert!(Student::new(&line_arch, None, Some(&old_teacher), -0.5, 5).is_err());
    }

    #[test]
    fn a_state_student_imitates_the_pilot_and_learns_its_normaliser() {
        let arch = Architecture { hidden: vec![32, 32], ..Architecture::paper() };
        let layout = arch.observation;
        let mut env = RaceEnv::new(track(), EnvConfig::default(), 1, 0);
        let mut pilot = sim::ReferencePilot::default();
        pilot.reset(&env);
        let mut student = Student::new(&arch, None, None, -0.5, 3).unwrap();
        let mut data = DistillDataset::new(256, arch.observation_dim, FrameStack::default());
        let mut rng = ChaCha8Rng::seed_from_u64(4);
        let mut shown = Vec::new();
        for _ in 0..128 {
            let state = env.observation_in(layout);
            let label = pilot.act(&env);
            data.offer(&env, &state, &label, &mut rng);
            student.observe(&state);
            shown.extend(state);
            env.step(&label);
            if env.stats().crash.is_some() {
                env.reset();
                pilot.reset(&env);
            }
        }
        // The normaliser is the states' own: a teacher-less student learns it from what it sees.
        let mut expected = ObsNormalizer::new(arch.observation_dim);
        expected.update(&shown);
        let learnt = student.weights().normalizer;
        assert_eq!(learnt.count, expected.count);
        // Row by row and all at once agree up to rounding.
        for (a, b) in learnt.mean.iter().zip(&expected.mean).chain(learnt.var.iter().zip(&expected.var)) {
            assert!((a - b).abs() <= 1e-9 * (1.0 + b.abs()), "{a} vs {b}");
        }
        let rows: Vec<usize> = (0..data.len()).collect();
        let first = student.train_step(&data, &rows, 3e-3).imitation;
        let mut last = first;
        for _ in 0..150 {
            last = student.train_step(&data, &rows, 3e-3).imitation;
        }
        assert!(last < 0.25 * first, "loss {first} → {last}");
        // The blob is a state policy whose deterministic actions are the pilot's, roughly.
        let blob = student.weights();
        assert_eq!(blob.architecture.agent, Agent::State);
        let actions = policy::Policy::from_blob(&blob).unwrap().deterministic_actions(&data.states(&rows));
        let mse: f32 = actions.iter().zip(data.labels(&rows)).map(|(a, l)| (a - l).powi(2)).sum::<f32>() / actions.len() as f32;
        assert!(f64::from(mse) < 0.3 * first, "{mse} against {first}");
        // Exact resume, the normaliser still learning.
        let mut restored = Student::restore(&blob.to_bytes(), &student.optimizer_state(), true).unwrap();
        restored.observe(&shown[..40]);
        student.observe(&shown[..40]);
        assert_eq!(restored.train_step(&data, &rows, 1e-3), student.train_step(&data, &rows, 1e-3));
        assert_eq!(restored.weights(), student.weights());
    }
}
