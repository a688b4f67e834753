//! DAgger's aggregated data set (Ross, Gordon and Bagnell 2011): every visited state, labelled
//! with the teacher's action (a state-based policy's mean, or the reference pilot's).
//!
//! A sample keeps the camera's pose (track, target gate, position, attitude), not its image:
//! the renderer is deterministic, so a minibatch's images are rendered again when it is trained
//! on (~10 µs an image, against ~1 ms for the CNN's gradient on it). A sample then takes ~250
//! bytes instead of 7 kB, so a data set of a million samples and its checkpoint stay small.

use std::collections::HashMap;
use std::sync::Arc;

use learner::LearnerError;
use rand::Rng;
use rayon::prelude::*;
use sim::camera::IMAGE_PIXELS;
use sim::{ACTION_DIM, CameraPose, RaceEnv, Track};

/// The frame of a serialised data set (format 4: one camera pose a sample). Earlier formats
/// (3: a frame stack, written by every run before 71a070b; 2 and 1 before it) are not read, so
/// such a distillation resumes at 2482eeb only.
const DATASET_FRAME: frames::FrameKind = frames::FrameKind { magic: b"DRDAGGER", format: 4, name: "distillation data set" };

/// Bytes of a camera pose in a serialised data set: the target gate and seven f64s.
const POSE_BYTES: usize = 4 + 7 * 8;

/// One visited state: where the camera was and the teacher's label (its raw state observation
/// is the data set's row of the same index).
#[derive(Clone, Debug, PartialEq)]
struct Sample {
    /// Index into the data set's track table.
    track: u32,
    /// Where the camera was.
    pose: CameraPose,
    /// Teacher's deterministic action.
    label: [f32; ACTION_DIM],
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
    capacity: usize,
    seen: u64,
}

impl DistillDataset {
    /// An empty data set holding at most `capacity` samples of `state_dim`-number states.
    pub fn new(capacity: usize, state_dim: usize) -> Self {
        Self { capacity: capacity.max(1), state_dim, ..Self::default() }
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

    /// Offers the state `env` is in (its camera pose), its raw observation `state`
    /// (`state_dim` numbers) and the teacher's `label`.
    pub fn offer(&mut self, env: &RaceEnv, state: &[f32], label: &[f32], rng: &mut impl Rng) {
        assert_eq!(state.len(), self.state_dim, "a state of the data set's length");
        self.seen += 1;
        let slot = if self.samples.len() < self.capacity {
            None
        } else {
            match rng.random_range(0..self.seen) {
                j if j < self.capacity as u64 => Some(j as usize),
                _ => return,
            }
        };
        let sample = Sample { track: self.track_id(env.track()), pose: env.camera_pose(), label: std::array::from_fn(|i| label[i]) };
        match slot {
            Some(j) => {
                self.samples[j] = sample;
                let range = self.state_range(j);
                self.states[range].copy_from_slice(state);
            }
            None => {
                self.samples.push(sample);
                self.states.extend_from_slice(state);
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

    /// The camera images of samples `rows` (`rows.len() × 84 × 84` bytes), rendered again.
    pub fn images(&self, rows: &[usize]) -> Vec<u8> {
        let mut out = vec![0u8; rows.len() * IMAGE_PIXELS];
        out.par_chunks_mut(IMAGE_PIXELS).zip(rows.par_iter()).for_each(|(image, &row)| {
            let sample = &self.samples[row];
            sample.pose.render(&self.tracks[sample.track as usize], image);
        });
        out
    }

    /// Raw state observations of samples `rows`, row after row.
    pub fn states(&self, rows: &[usize]) -> Vec<f32> {
        rows.iter().flat_map(|&r| &self.states[self.state_range(r)]).copied().collect()
    }

    /// Teacher labels of samples `rows`, row after row.
    pub fn labels(&self, rows: &[usize]) -> Vec<f32> {
        rows.iter().flat_map(|&r| self.samples[r].label).collect()
    }

    /// The data set as bytes (a `frames` frame): capacity, count seen, state length, the
    /// tracks (JSON), the samples.
    #[allow(clippy::expect_used, reason = "tracks serialise")]
    pub fn to_bytes(&self) -> Vec<u8> {
        let tracks: Vec<&Track> = self.tracks.iter().map(Arc::as_ref).collect();
        let tracks = serde_json::to_vec(&tracks).expect("tracks serialise");
        let mut body = Vec::with_capacity(32 + tracks.len() + self.samples.len() * 256);
        body.extend_from_slice(&(self.capacity as u64).to_le_bytes());
        body.extend_from_slice(&self.seen.to_le_bytes());
        body.extend_from_slice(&(self.state_dim as u64).to_le_bytes());
        body.extend_from_slice(&(tracks.len() as u64).to_le_bytes());
        body.extend_from_slice(&tracks);
        body.extend_from_slice(&(self.samples.len() as u64).to_le_bytes());
        for (i, s) in self.samples.iter().enumerate() {
            body.extend_from_slice(&s.track.to_le_bytes());
            body.extend_from_slice(&s.pose.target.to_le_bytes());
            for v in s.pose.position.iter().chain(&s.pose.attitude) {
                body.extend_from_slice(&v.to_le_bytes());
            }
            frames::put_f32s(&mut body, &self.states[self.state_range(i)]);
            frames::put_f32s(&mut body, &s.label);
        }
        DATASET_FRAME.encode(&body)
    }

    /// Reads [`DistillDataset::to_bytes`]' output; errors say what is wrong.
    pub fn from_bytes(bytes: &[u8]) -> Result<Self, LearnerError> {
        let body = DATASET_FRAME.decode(bytes).map_err(|e| match e {
            frames::FrameError::UnsupportedFormat { found: 1..4, .. } => LearnerError::State(format!(
                "{e}: this data set holds frame stacks (written before 71a070b); resume the distillation at 2482eeb or start it again"
            )),
            e => LearnerError::State(e.to_string()),
        })?;
        let bad = |what: String| LearnerError::State(format!("distillation data set: {what}"));
        let short = |t: frames::Truncated| bad(format!("ends {} bytes short at byte {}", t.needed, t.at));
        let mut r = frames::Reader::new(body, 0);
        let capacity = r.u64().map_err(short)? as usize;
        let seen = r.u64().map_err(short)?;
        let state_dim = r.u64().map_err(short)? as usize;
        let json_len = r.u64().map_err(short)? as usize;
        let tracks: Vec<Track> = serde_json::from_slice(r.take(json_len).map_err(short)?).map_err(|e| bad(format!("track table: {e}")))?;
        let tracks: Vec<Arc<Track>> = tracks.into_iter().map(Arc::new).collect();
        let count = r.u64().map_err(short)? as usize;
        // Sizes come from the file: every capacity is bounded by the bytes that are really there.
        let per_sample = state_dim.saturating_add(ACTION_DIM).saturating_mul(4).saturating_add(4 + POSE_BYTES);
        let mut samples = Vec::with_capacity(r.capacity_for(count, per_sample));
        let mut states = Vec::with_capacity(samples.capacity().saturating_mul(state_dim));
        for i in 0..count {
            let track = r.u32().map_err(short)?;
            let gates = tracks.get(track as usize).map(|t| t.gates.len()).ok_or_else(|| bad(format!("sample {i}: no track {track}")))?;
            let target = r.u32().map_err(short)?;
            if target as usize >= gates {
                return Err(bad(format!("sample {i}: target gate {target} of a {gates}-gate track")));
            }
            let mut p = [0f64; 7];
            for v in &mut p {
                *v = r.f64().map_err(short)?;
            }
            let pose = CameraPose { target, position: [p[0], p[1], p[2]], attitude: [p[3], p[4], p[5], p[6]] };
            states.extend(r.f32s(state_dim).map_err(short)?);
            let label = r.f32s(ACTION_DIM).map_err(short)?;
            samples.push(Sample { track, pose, label: std::array::from_fn(|k| label[k]) });
        }
        if r.remaining() != 0 || samples.len() > capacity.max(1) {
            return Err(bad(format!("{} bytes after {count} samples, capacity {capacity}", r.remaining())));
        }
        // Reservoir sampling keeps at most what it was offered: fewer offers than samples would
        // skew every later replacement's odds.
        if seen < count as u64 {
            return Err(bad(format!("{count} samples kept of {seen} offered")));
        }
        let track_index = tracks.iter().enumerate().map(|(i, t)| (Arc::as_ptr(t) as usize, i as u32)).collect();
        Ok(Self { tracks, track_index, samples, states, state_dim, capacity: capacity.max(1), seen })
    }
}

/// A two-gate track for the tests of this crate.
#[cfg(test)]
pub(crate) fn two_gate_track() -> Arc<Track> {
    use sim::nalgebra::Vector3;
    let gates = vec![sim::Gate::new(Vector3::new(4.0, 0.0, 2.0), 0.0), sim::Gate::new(Vector3::new(-4.0, 0.0, 2.0), 3.0)];
    Arc::new(Track::new("two", gates, None, sim::Arena::default()).unwrap())
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;
    use sim::{EnvConfig, STATE_OBS_DIM};

    #[test]
    fn the_reservoir_keeps_its_cap_and_a_uniform_sample_and_the_bytes_round_trip() {
        // Line points make the state longer than SPEC §5's; the data set keeps whatever it is given.
        let layout = sim::ObservationLayout { line_points: 3, ..sim::ObservationLayout::spec(sim::ObservationFrame::Heading) };
        let mut data = DistillDataset::new(100, layout.dim());
        let mut rng = ChaCha8Rng::seed_from_u64(0);
        let mut env = RaceEnv::new(two_gate_track(), EnvConfig::default(), 0, 0);
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
        data.seen = 99;
        let e = DistillDataset::from_bytes(&data.to_bytes()).unwrap_err().to_string();
        assert!(e.contains("100 samples kept of 99 offered"), "{e}");
        // A data set of the frame-stack layout is refused with the commit that still reads it.
        let old = frames::FrameKind { format: 3, ..DATASET_FRAME }.encode(b"");
        let e = DistillDataset::from_bytes(&old).unwrap_err().to_string();
        assert!(e.contains("format 3") && e.contains("2482eeb"), "{e}");
    }

    #[test]
    fn a_sample_renders_the_image_its_environment_showed() {
        let mut data = DistillDataset::new(10, STATE_OBS_DIM);
        let mut env = RaceEnv::new(two_gate_track(), EnvConfig::default(), 3, 1);
        for _ in 0..20 {
            env.step(&[0.2, 0.1, 0.0, 0.3]);
        }
        data.offer(&env, &[0.0; STATE_OBS_DIM], &[0.0; 4], &mut ChaCha8Rng::seed_from_u64(0));
        let mut shown = vec![0u8; IMAGE_PIXELS];
        env.render_camera(&mut shown);
        assert!(shown.iter().any(|&p| p > 0), "a gate is in view");
        assert_eq!(data.images(&[0]), shown);
    }
}
