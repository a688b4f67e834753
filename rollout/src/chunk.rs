//! The rollout chunk: what an actor sends the learner after each rollout, tagged with the
//! policy version that produced it, and its wire format.
//!
//! Wire layout: a frame (`frames`: magic `DRCHUNK`, format 2, length, CRC-32) whose body is,
//! little-endian: policy_version u64, first_env u64, envs u32, steps u32, observation_dim u32,
//! action_dim u32; observations, actions, log_probs, values, rewards as f32; terminated,
//! truncated as one byte each; truncation_values f32, last_values f32[envs]; episode count u32
//! and per episode env u64, return f64, length u32, laps u32, fastest lap f64 (NaN for none),
//! crashed u8; then the camera images of a vision agent's rollout (`[step][env]`, 84×84 bytes
//! each) run-length coded (`run_length`): code length u64 (0: no images), code.

use frames::{FrameError, FrameKind, Reader, Truncated, put_f32s};
use serde::{Deserialize, Serialize};
use sim::camera::IMAGE_PIXELS;

/// The rollout chunk's frame.
const FRAME: FrameKind = FrameKind { magic: b"DRCHUNK\0", format: 3, name: "dronerace rollout chunk" };

/// Encoded rollout bytes that cannot be used.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum RolloutWireError {
    /// Not an intact rollout-chunk frame (magic, format, length or checksum).
    #[error(transparent)]
    Frame(#[from] FrameError),
    /// The bytes end before the layout does.
    #[error("rollout chunk is truncated at offset {at} ({needed} more bytes needed)")]
    Truncated {
        /// Bytes missing.
        needed: usize,
        /// Where they were needed.
        at: usize,
    },
    /// Anything else malformed inside.
    #[error("rollout chunk is malformed: {0}")]
    Malformed(String),
}

impl From<Truncated> for RolloutWireError {
    fn from(t: Truncated) -> Self {
        Self::Truncated { needed: t.needed, at: t.at }
    }
}

/// What a receiver accepts, checked against a chunk's header before any of its arrays is
/// allocated: a rollout's decoded size is then bounded by what the run itself produces
/// (`max_envs × max_steps` transitions), whatever its header or image code claims.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ChunkLimits {
    /// Observation length of the policy being trained.
    pub observation_dim: usize,
    /// Action length of the policy being trained.
    pub action_dim: usize,
    /// Most environments one chunk may hold (the run's).
    pub max_envs: usize,
    /// Most steps per environment (the run's rollout length).
    pub max_steps: usize,
    /// Camera images are expected (a vision agent); otherwise a chunk carrying them is refused.
    pub images: bool,
}

impl ChunkLimits {
    /// Bytes the decoded arrays of a chunk of `transitions` take at most (what a receiver must
    /// budget for before decoding it).
    pub fn decoded_bytes(&self, transitions: usize) -> usize {
        let per = 4 * (self.observation_dim + self.action_dim + 5) + 2 + if self.images { IMAGE_PIXELS } else { 0 };
        transitions.saturating_mul(per)
    }
}

/// What a healthy actor can send, field by field: the physical envelope a rollout must lie in
/// before any of it reaches the normaliser or the update (one rollout of 1e9s from an actor
/// once moved the normaliser's mean to 5e8, so that every real observation normalised to −1).
/// Observations: distances across the largest arena a track may have (±1 km a side, 3.5 km
/// corner to corner), speeds and rates far below that, rotations and actions ±1.
pub const OBSERVATION_LIMIT: f32 = 4.0e3;
/// Actions: Gaussian samples around means that the clip to [-1, 1] keeps near it.
pub const ACTION_LIMIT: f32 = 1.0e2;
/// Log-probabilities: a 4-d Gaussian sample 20 σ from its mean is at −800.
pub const LOG_PROB_LIMIT: f32 = 1.0e3;
/// Rewards: SPEC §5's terms are O(1) a step (a crash −4).
pub const REWARD_LIMIT: f32 = 1.0e4;
/// Values: returns of such rewards, O(100); small enough that f32 advantage sums over a whole
/// rollout cannot overflow.
pub const VALUE_LIMIT: f32 = 1.0e6;

/// One finished episode, for metrics.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct EpisodeRecord {
    /// Global environment index.
    pub env: usize,
    /// Sum of rewards.
    pub episode_return: f64,
    /// Steps.
    pub length: u32,
    /// Completed laps.
    pub laps: u32,
    /// Fastest lap (s).
    pub fastest_lap: Option<f64>,
    /// Ended in a crash (not by the time limit).
    pub crashed: bool,
}

/// `steps` consecutive policy steps of environments `first_env .. first_env + envs`, all
/// step-major (`[step][env]`, then the feature).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct RolloutChunk {
    /// Version of the policy that chose every action here.
    pub policy_version: u64,
    /// Global index of the first environment.
    pub first_env: usize,
    /// Environments in the chunk.
    pub envs: usize,
    /// Steps per environment.
    pub steps: usize,
    /// Raw (un-normalised) observations at decision time.
    pub observations: Vec<f32>,
    /// Sampled actions, before clipping.
    pub actions: Vec<f32>,
    /// Log-probabilities of those samples.
    pub log_probs: Vec<f32>,
    /// Value estimates at decision time.
    pub values: Vec<f32>,
    /// Rewards.
    pub rewards: Vec<f32>,
    /// The step crashed.
    pub terminated: Vec<bool>,
    /// The step hit the time limit.
    pub truncated: Vec<bool>,
    /// V(final observation) where truncated, else 0.
    pub truncation_values: Vec<f32>,
    /// V(observation after the last step), per environment.
    pub last_values: Vec<f32>,
    /// Episodes that ended in this rollout.
    pub episodes: Vec<EpisodeRecord>,
    /// Camera images at decision time (`transitions × 84 × 84` bytes) of a vision agent's
    /// rollout; empty for a state-based one.
    #[serde(default)]
    pub images: Vec<u8>,
}

impl RolloutChunk {
    /// Sum of each environment's rewards in this rollout (what the task controller scores).
    pub fn cumulative_rewards(&self) -> Vec<f64> {
        let mut sums = vec![0.0; self.envs];
        for (i, r) in self.rewards.iter().enumerate() {
            sums[i % self.envs] += f64::from(*r);
        }
        sums
    }

    /// A chunk of the given shape with every value zero and no episodes (for tests and
    /// benchmarks of what carries chunks).
    pub fn zeroed(policy_version: u64, first_env: usize, envs: usize, steps: usize, observation_dim: usize, action_dim: usize) -> Self {
        let t = envs * steps;
        Self {
            policy_version,
            first_env,
            envs,
            steps,
            observations: vec![0.0; t * observation_dim],
            actions: vec![0.0; t * action_dim],
            log_probs: vec![0.0; t],
            values: vec![0.0; t],
            rewards: vec![0.0; t],
            terminated: vec![false; t],
            truncated: vec![false; t],
            truncation_values: vec![0.0; t],
            last_values: vec![0.0; envs],
            episodes: Vec::new(),
            images: Vec::new(),
        }
    }

    /// Number of transitions.
    pub fn transitions(&self) -> usize {
        self.envs * self.steps
    }

    /// Checks every array's length against `envs × steps` and the given dimensions, that the
    /// camera images are there exactly when the agent acts on them (`images`: a vision agent),
    /// and that all numbers are finite and within their field's envelope ([`OBSERVATION_LIMIT`]
    /// and the limits beside it).
    pub fn check(&self, observation_dim: usize, action_dim: usize, images: bool) -> Result<(), RolloutCheckError> {
        let t = self.transitions();
        let expect = [
            ("observations", self.observations.len(), t * observation_dim),
            ("actions", self.actions.len(), t * action_dim),
            ("log_probs", self.log_probs.len(), t),
            ("values", self.values.len(), t),
            ("rewards", self.rewards.len(), t),
            ("terminated", self.terminated.len(), t),
            ("truncated", self.truncated.len(), t),
            ("truncation_values", self.truncation_values.len(), t),
            ("last_values", self.last_values.len(), self.envs),
            ("images", self.images.len(), if images { t * IMAGE_PIXELS } else { 0 }),
        ];
        for (field, got, expected) in expect {
            if got != expected {
                return Err(RolloutCheckError::Length { field, got, expected });
            }
        }
        let arrays = [
            ("observations", &self.observations, OBSERVATION_LIMIT),
            ("actions", &self.actions, ACTION_LIMIT),
            ("log_probs", &self.log_probs, LOG_PROB_LIMIT),
            ("values", &self.values, VALUE_LIMIT),
            ("rewards", &self.rewards, REWARD_LIMIT),
            ("truncation_values", &self.truncation_values, VALUE_LIMIT),
            ("last_values", &self.last_values, VALUE_LIMIT),
        ];
        for (field, values, limit) in arrays {
            if let Some(index) = values.iter().position(|x| !x.is_finite() || x.abs() > limit) {
                return Err(RolloutCheckError::Value { field, index, value: values[index], limit });
            }
        }
        // Episode records feed the metrics and, with validation off, the choice of best.bin:
        // each must be one an environment of this chunk could have flown.
        if self.episodes.len() > t {
            return Err(RolloutCheckError::Episode { index: t, reason: format!("more episodes than the {t} steps of the chunk") });
        }
        for (index, e) in self.episodes.iter().enumerate() {
            let reason = if e.env.checked_sub(self.first_env).is_none_or(|i| i >= self.envs) {
                format!("env {} is not one of the chunk's", e.env)
            } else if !e.episode_return.is_finite() || e.episode_return.abs() > f64::from(REWARD_LIMIT) * f64::from(e.length) {
                format!("return {} is beyond ±{REWARD_LIMIT:e} a step over {} steps", e.episode_return, e.length)
            } else if e.fastest_lap.is_some_and(|lap| !(lap.is_finite() && lap > 0.0)) {
                format!("fastest lap {:?} is not a positive time", e.fastest_lap)
            } else {
                continue;
            };
            return Err(RolloutCheckError::Episode { index, reason });
        }
        Ok(())
    }
}

/// What [`RolloutChunk::check`] refuses, naming the field.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum RolloutCheckError {
    /// An array of the wrong length; for `images`, camera images a state-based agent does not
    /// act on (expected 0) or a vision agent's rollout without them (got 0).
    #[error("{field} has {got} values, expected {expected}{}", images_note(field, *got, *expected))]
    Length {
        /// The array.
        field: &'static str,
        /// Its length.
        got: usize,
        /// The length the run's shapes give.
        expected: usize,
    },
    /// A number that is not finite, or outside the envelope of its field ([`OBSERVATION_LIMIT`]
    /// and the limits beside it).
    #[error("{field}[{index}] is {value}, not a finite number within ±{limit:e} (what a healthy actor sends)")]
    Value {
        /// The array.
        field: &'static str,
        /// Index within it.
        index: usize,
        /// The number.
        value: f32,
        /// The bound of its field.
        limit: f32,
    },
    /// An episode record no environment of the chunk could have produced.
    #[error("episodes[{index}]: {reason}")]
    Episode {
        /// Index of the record.
        index: usize,
        /// What is wrong with it.
        reason: String,
    },
}

/// What a wrong `images` length means, for the error message.
fn images_note(field: &str, got: usize, expected: usize) -> &'static str {
    match (field, got, expected) {
        ("images", 0, _) => " (a vision agent's rollout without its camera images)",
        ("images", _, 0) => " (camera images in a state-based agent's rollout)",
        _ => "",
    }
}

/// A chunk's header: who made it and its shape.
struct Header {
    policy_version: u64,
    first_env: usize,
    envs: usize,
    steps: usize,
}

impl Header {
    /// Reads the header and checks its shape against `limits`.
    fn read(r: &mut Reader, limits: &ChunkLimits) -> Result<Self, RolloutWireError> {
        let malformed = RolloutWireError::Malformed;
        let policy_version = r.u64()?;
        let first_env = usize::try_from(r.u64()?).map_err(|_| malformed("first_env overflows".into()))?;
        let (envs, steps, obs_dim, act_dim) = (r.u32()? as usize, r.u32()? as usize, r.u32()? as usize, r.u32()? as usize);
        if envs == 0 || steps == 0 {
            return Err(malformed(format!("{envs} environments × {steps} steps holds no transitions")));
        }
        if (obs_dim, act_dim) != (limits.observation_dim, limits.action_dim) {
            return Err(malformed(format!(
                "observations of {obs_dim} and actions of {act_dim} values, where the policy has {} and {}",
                limits.observation_dim, limits.action_dim
            )));
        }
        if envs > limits.max_envs || steps > limits.max_steps {
            return Err(malformed(format!(
                "{envs} environments × {steps} steps, more than the run's {} × {}",
                limits.max_envs, limits.max_steps
            )));
        }
        Ok(Self { policy_version, first_env, envs, steps })
    }
}

impl RolloutChunk {
    /// The transitions (environments × steps) a chunk's header announces, checked against
    /// `limits` and the frame's checksum, without decoding anything else: what a receiver
    /// budgets for before [`RolloutChunk::from_bytes`].
    pub fn announced_transitions(bytes: &[u8], limits: &ChunkLimits) -> Result<usize, RolloutWireError> {
        let header = Header::read(&mut Reader::new(FRAME.decode(bytes)?, 0), limits)?;
        Ok(header.envs * header.steps)
    }

    /// Encodes the chunk in the wire layout.
    pub fn to_bytes(&self) -> Vec<u8> {
        let t = self.transitions().max(1);
        let (obs_dim, act_dim) = (self.observations.len() / t, self.actions.len() / t);
        let mut out = Vec::with_capacity(64 + 4 * (self.observations.len() + self.actions.len() + 6 * t));
        out.extend_from_slice(&self.policy_version.to_le_bytes());
        out.extend_from_slice(&(self.first_env as u64).to_le_bytes());
        for n in [self.envs, self.steps, obs_dim, act_dim] {
            out.extend_from_slice(&(n as u32).to_le_bytes());
        }
        for values in [&self.observations, &self.actions, &self.log_probs, &self.values, &self.rewards] {
            put_f32s(&mut out, values);
        }
        out.extend(self.terminated.iter().map(|&b| u8::from(b)));
        out.extend(self.truncated.iter().map(|&b| u8::from(b)));
        put_f32s(&mut out, &self.truncation_values);
        put_f32s(&mut out, &self.last_values);
        out.extend_from_slice(&(self.episodes.len() as u32).to_le_bytes());
        for e in &self.episodes {
            out.extend_from_slice(&(e.env as u64).to_le_bytes());
            out.extend_from_slice(&e.episode_return.to_le_bytes());
            out.extend_from_slice(&e.length.to_le_bytes());
            out.extend_from_slice(&e.laps.to_le_bytes());
            out.extend_from_slice(&e.fastest_lap.unwrap_or(f64::NAN).to_le_bytes());
            out.push(u8::from(e.crashed));
        }
        let mut code = Vec::new();
        crate::run_length::encode(&self.images, &mut code);
        out.extend_from_slice(&(code.len() as u64).to_le_bytes());
        out.extend_from_slice(&code);
        FRAME.encode(&out)
    }

    /// Decodes and verifies a chunk: checksum, the header's shape against `limits`, every
    /// array's length against the header, no trailing bytes. Everything is checked against the
    /// limits and the input before anything is allocated, so a decode never allocates more than
    /// `limits.decoded_bytes(limits.max_envs * limits.max_steps)` (plus the episodes, which the
    /// input's length bounds).
    pub fn from_bytes(bytes: &[u8], limits: &ChunkLimits) -> Result<Self, RolloutWireError> {
        let malformed = RolloutWireError::Malformed;
        let mut r = Reader::new(FRAME.decode(bytes)?, 0);
        let Header { policy_version, first_env, envs, steps } = Header::read(&mut r, limits)?;
        let (obs_dim, act_dim) = (limits.observation_dim, limits.action_dim);
        // Per transition: obs + act + 5 more f32 and 2 flag bytes; refuse before allocating.
        let t = envs * steps;
        let per = obs_dim.checked_add(act_dim).and_then(|d| d.checked_add(4)).and_then(|d| d.checked_mul(4)).map(|b| b + 2);
        if per.and_then(|p| p.checked_mul(t)).is_none_or(|need| need > r.remaining()) {
            return Err(RolloutWireError::Malformed(format!(
                "header announces {envs} × {steps} transitions of {obs_dim}+{act_dim} values, more than the {} bytes sent",
                r.remaining()
            )));
        }
        let observations = r.f32s(t * obs_dim)?;
        let actions = r.f32s(t * act_dim)?;
        let log_probs = r.f32s(t)?;
        let values = r.f32s(t)?;
        let rewards = r.f32s(t)?;
        let flags = |v: Option<Vec<bool>>, name: &str| {
            v.ok_or_else(|| RolloutWireError::Malformed(format!("{name}: a flag byte is neither 0 nor 1")))
        };
        let terminated = flags(r.bools(t)?, "terminated")?;
        let truncated = flags(r.bools(t)?, "truncated")?;
        let truncation_values = r.f32s(t)?;
        let last_values = r.f32s(envs)?;
        let count = r.u32()? as usize;
        const EPISODE_BYTES: usize = 8 + 8 + 4 + 4 + 8 + 1;
        if count.checked_mul(EPISODE_BYTES).is_none_or(|need| need > r.remaining()) {
            return Err(RolloutWireError::Malformed(format!("{count} episodes announced, more than the bytes sent")));
        }
        let mut episodes = Vec::with_capacity(count);
        for _ in 0..count {
            let env = r.u64()? as usize;
            let episode_return = r.f64()?;
            let (length, laps) = (r.u32()?, r.u32()?);
            let fastest = r.f64()?;
            let crashed = flags(r.bools(1)?, "episode.crashed")?[0];
            episodes.push(EpisodeRecord {
                env,
                episode_return,
                length,
                laps,
                fastest_lap: (!fastest.is_nan()).then_some(fastest),
                crashed,
            });
        }
        let code_len = usize::try_from(r.u64()?).map_err(|_| malformed("image code length overflows".into()))?;
        let code = r.take(code_len)?;
        let images = match code_len {
            0 => Vec::new(),
            _ if !limits.images => return Err(malformed("images: camera images in a state-based agent's rollout".into())),
            // t is within the limits here, so this allocates at most what the run's images take.
            _ => crate::run_length::decode(code, t * IMAGE_PIXELS).ok_or_else(|| {
                RolloutWireError::Malformed(format!("the image code does not decode to {t} images of {IMAGE_PIXELS} bytes"))
            })?,
        };
        if r.remaining() != 0 {
            return Err(RolloutWireError::Malformed(format!("{} bytes after the images", r.remaining())));
        }
        Ok(Self {
            policy_version,
            first_env,
            envs,
            steps,
            observations,
            actions,
            log_probs,
            values,
            rewards,
            terminated,
            truncated,
            truncation_values,
            last_values,
            episodes,
            images,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// What the test chunks fit exactly.
    const LIMITS: ChunkLimits = ChunkLimits { observation_dim: 5, action_dim: 2, max_envs: 3, max_steps: 4, images: false };
    const VISION: ChunkLimits = ChunkLimits { images: true, ..LIMITS };

    fn chunk() -> RolloutChunk {
        let (envs, steps, obs, act) = (3, 4, 5, 2);
        let t = envs * steps;
        let f = |n: usize, k: f32| (0..n).map(|i| i as f32 * k - 1.5).collect::<Vec<_>>();
        RolloutChunk {
            policy_version: 42,
            first_env: 9,
            envs,
            steps,
            observations: f(t * obs, 0.25),
            actions: f(t * act, -0.125),
            log_probs: f(t, 0.5),
            values: f(t, 0.75),
            rewards: f(t, 0.0625),
            terminated: (0..t).map(|i| i == 4).collect(),
            truncated: (0..t).map(|i| i == 7).collect(),
            truncation_values: f(t, 0.0),
            last_values: f(envs, 2.0),
            episodes: vec![
                EpisodeRecord { env: 10, episode_return: 3.25, length: 17, laps: 1, fastest_lap: Some(4.5), crashed: true },
                EpisodeRecord { env: 11, episode_return: -1.0, length: 1500, laps: 0, fastest_lap: None, crashed: false },
            ],
            images: Vec::new(),
        }
    }

    #[test]
    fn wire_format_round_trips_exactly() {
        let c = chunk();
        assert_eq!(RolloutChunk::from_bytes(&c.to_bytes(), &LIMITS).unwrap(), c);
        // With a vision agent's images: a bar of gate pixels in every image.
        let mut v = chunk();
        v.images = vec![0; v.transitions() * IMAGE_PIXELS];
        for (i, image) in v.images.chunks_mut(IMAGE_PIXELS).enumerate() {
            image[100 + i..140 + i].fill(155);
        }
        v.check(5, 2, true).unwrap();
        assert!(v.check(5, 2, false).unwrap_err().to_string().contains("state-based"));
        let missing = c.check(5, 2, true).unwrap_err();
        assert!(matches!(missing, RolloutCheckError::Length { field: "images", got: 0, .. }), "{missing}");
        assert!(missing.to_string().contains("without its camera images"));
        let bytes = v.to_bytes();
        assert!(bytes.len() < c.to_bytes().len() + v.transitions() * 20, "images are run-length coded");
        assert_eq!(RolloutChunk::from_bytes(&bytes, &VISION).unwrap(), v);
        assert!(matches!(RolloutChunk::from_bytes(&bytes, &LIMITS), Err(RolloutWireError::Malformed(m)) if m.contains("state-based")));
        v.images.pop();
        assert!(v.check(5, 2, true).unwrap_err().to_string().starts_with("images has"));
    }

    #[test]
    fn truncated_altered_foreign_and_lying_chunks_are_refused() {
        let bytes = chunk().to_bytes();
        let frame_error = |b: &[u8]| match RolloutChunk::from_bytes(b, &LIMITS) {
            Err(RolloutWireError::Frame(e)) => Some(e),
            _ => None,
        };
        assert!(matches!(frame_error(&bytes[..bytes.len() - 10]), Some(FrameError::Length { .. })));
        let mut flipped = bytes.clone();
        flipped[60] ^= 1;
        assert!(matches!(frame_error(&flipped), Some(FrameError::Checksum { .. })));
        assert!(matches!(frame_error(b"DRPOLICY........"), Some(FrameError::BadMagic { .. })));
        // A header announcing a huge rollout (with a valid checksum) is refused, not allocated.
        let mut lying = bytes[..bytes.len() - 4].to_vec();
        let envs_at = frames::OVERHEAD - 4 + 16; // after the frame header, policy_version and first_env
        lying[envs_at..envs_at + 4].copy_from_slice(&u32::MAX.to_le_bytes());
        let crc = crc32fast::hash(&lying);
        lying.extend_from_slice(&crc.to_le_bytes());
        let unlimited = ChunkLimits { max_envs: usize::MAX, max_steps: usize::MAX, ..LIMITS };
        assert!(matches!(RolloutChunk::from_bytes(&lying, &unlimited), Err(RolloutWireError::Malformed(m)) if m.contains("more than")));
    }

    /// The amplifying rollout: 18 bytes per transition on the wire (no observations, no
    /// actions; the images one zero run per 65,535 bytes) that would decode to 7,056 image
    /// bytes each. Built without ever holding the images.
    fn amplifying(envs: usize, steps: usize) -> Vec<u8> {
        let c = RolloutChunk::zeroed(1, 0, envs, steps, 0, 0);
        let mut body = FRAME.decode(&c.to_bytes()).unwrap().to_vec();
        body.truncate(body.len() - 8); // the empty image code's length
        let mut code = Vec::new();
        let mut left = c.transitions() * IMAGE_PIXELS;
        while left > 0 {
            let run = left.min(u16::MAX as usize);
            code.push(0);
            code.extend_from_slice(&(run as u16).to_le_bytes());
            left -= run;
        }
        body.extend_from_slice(&(code.len() as u64).to_le_bytes());
        body.extend_from_slice(&code);
        FRAME.encode(&body)
    }

    #[test]
    fn a_header_beyond_the_limits_is_refused_before_its_arrays_are_allocated() {
        // Within what a vision run of 8 × 16 produces: decoded as announced.
        let small = amplifying(8, 16);
        let fits = ChunkLimits { observation_dim: 0, action_dim: 0, max_envs: 8, max_steps: 16, images: true };
        assert_eq!(RolloutChunk::from_bytes(&small, &fits).unwrap().images.len(), 8 * 16 * IMAGE_PIXELS);
        // 64 × 4,096 transitions in under 5 MB would be 1.85 GB of images: refused by its header.
        let big = amplifying(64, 4096);
        assert!(big.len() < 5 << 20, "{} bytes on the wire", big.len());
        let error = RolloutChunk::from_bytes(&big, &fits).unwrap_err().to_string();
        assert!(error.contains("more than the run's 8 × 16"), "{error}");
        // The wrong observation length, and images a state agent does not take, also by name.
        let state = ChunkLimits { observation_dim: 52, ..fits };
        assert!(RolloutChunk::from_bytes(&small, &state).unwrap_err().to_string().contains("observations of 0"));
        let no_images = ChunkLimits { images: false, ..fits };
        assert!(RolloutChunk::from_bytes(&small, &no_images).unwrap_err().to_string().contains("state-based"));
        assert_eq!(fits.decoded_bytes(8 * 16), 8 * 16 * (4 * 5 + 2 + IMAGE_PIXELS));
    }

    #[test]
    fn numbers_beyond_any_healthy_run_are_refused_by_field() {
        let mut c = chunk();
        c.rewards[3] = 2.0e9;
        assert_eq!(c.check(5, 2, false), Err(RolloutCheckError::Value { field: "rewards", index: 3, value: 2.0e9, limit: REWARD_LIMIT }));
        let mut c = chunk();
        c.last_values[1] = -1.0e10;
        assert!(c.check(5, 2, false).unwrap_err().to_string().starts_with("last_values[1] is -10000000000"));
    }

    /// The rollouts that blinded the learner and stopped a run: observations of 1e9 (which
    /// moved the normaliser's mean to 5e8) and old log-probs of −1e9 (an infinite ratio). Each
    /// is refused naming its field; the largest numbers a healthy run sends pass.
    #[test]
    fn observations_and_log_probs_outside_the_physical_envelope_are_refused() {
        let mut c = chunk();
        c.observations[7] = 1.0e9;
        let e = c.check(5, 2, false).unwrap_err();
        assert_eq!(e, RolloutCheckError::Value { field: "observations", index: 7, value: 1.0e9, limit: OBSERVATION_LIMIT });
        let mut c = chunk();
        c.log_probs[0] = -1.0e9;
        assert!(matches!(c.check(5, 2, false), Err(RolloutCheckError::Value { field: "log_probs", index: 0, .. })));
        let mut c = chunk();
        c.actions[1] = 500.0;
        assert!(matches!(c.check(5, 2, false), Err(RolloutCheckError::Value { field: "actions", .. })));
        let mut c = chunk();
        c.episodes[0].episode_return = 1.0e12;
        assert!(c.check(5, 2, false).unwrap_err().to_string().starts_with("episodes[0]: return 1000000000000"));
        c.episodes[0].episode_return = 12.0;
        c.observations.fill(3464.0); // corner to corner of a 2 km arena
        c.log_probs.fill(-800.0);
        c.actions.fill(-5.0);
        assert_eq!(c.check(5, 2, false), Ok(()));
    }
}
