//! N race environments stepped in parallel into contiguous f32 buffers.
//!
//! Each environment owns its random stream, so results are bit-identical whatever the number
//! of rayon threads. Finished episodes reset automatically; the observation that ended them is
//! kept in `final_observations` so a learner can bootstrap truncated episodes. With images on,
//! each environment's camera observation (its current image, and the earlier frames of a
//! frame stack) is rendered after every step into `images`.

use std::sync::Arc;

use rayon::prelude::*;

use crate::frame_stack::{CameraHistory, CameraPose, FrameStack};
use crate::race::{EnvConfig, EpisodeStats, RaceEnv, StepOutcome};
use crate::track::Track;

/// Actions per environment.
pub const ACTION_DIM: usize = 4;

/// An episode that ended during the last step.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FinishedEpisode {
    /// Environment index.
    pub env: usize,
    /// Its statistics.
    pub stats: EpisodeStats,
}

/// Vectorised race environment with automatic reset.
pub struct VecEnv {
    envs: Vec<RaceEnv>,
    /// Length of one observation row (the environments' [`crate::ObservationLayout`]).
    observation_dim: usize,
    /// Current observations, `n × observation_dim`, row-major.
    pub observations: Vec<f32>,
    /// Rewards of the last step.
    pub rewards: Vec<f32>,
    /// Which environments terminated (crashed) in the last step.
    pub terminated: Vec<bool>,
    /// Which environments were truncated in the last step.
    pub truncated: Vec<bool>,
    /// Observation at the end of the last step before any reset; meaningful where done.
    pub final_observations: Vec<f32>,
    /// Episodes that finished in the last step, in environment order.
    pub finished: Vec<FinishedEpisode>,
    /// Current camera observations, `n × frames × 84 × 84` bytes (each environment's current
    /// image first); empty unless [`VecEnv::with_images`] or [`VecEnv::with_frame_stack`].
    pub images: Vec<u8>,
    /// Each environment's recent camera poses, when images are on.
    cameras: Vec<CameraHistory>,
}

impl VecEnv {
    /// One environment per track, environment `i` on random stream `i` of `seed`.
    pub fn new(tracks: Vec<Arc<Track>>, config: EnvConfig, seed: u64) -> Self {
        let envs: Vec<RaceEnv> = tracks.into_iter().enumerate().map(|(i, t)| RaceEnv::new(t, config, seed, i as u64)).collect();
        Self::from_envs(envs)
    }

    /// Renders a camera image for every environment after every step from now on (SPEC §5).
    pub fn with_images(self) -> Self {
        self.with_frame_stack(FrameStack::default())
    }

    /// Renders the frames of `stack` for every environment after every step from now on: the
    /// current image and earlier ones, each flight's first standing in for the steps before it.
    pub fn with_frame_stack(mut self, stack: FrameStack) -> Self {
        self.enable_images(stack);
        self
    }

    /// [`VecEnv::with_frame_stack`] in place: renders the current observations at once (a
    /// no-op when images are on already).
    pub fn enable_images(&mut self, stack: FrameStack) {
        if self.images.is_empty() {
            self.cameras = self
                .envs
                .iter()
                .map(|env| {
                    let mut camera = CameraHistory::new(stack);
                    camera.restart(CameraPose::of(env));
                    camera
                })
                .collect();
            self.images = vec![0; self.envs.len() * stack.image_len()];
            self.render_all_images();
        }
    }

    /// The environments' camera histories (empty with images off), e.g. for a checkpoint.
    pub fn cameras(&self) -> &[CameraHistory] {
        &self.cameras
    }

    /// Restores camera histories saved from [`VecEnv::cameras`] of environments restored by
    /// [`VecEnv::from_envs`], with images on in their frame stack; an error says what does
    /// not fit.
    pub fn restore_cameras(&mut self, cameras: Vec<CameraHistory>) -> Result<(), String> {
        let stack = self.cameras.first().map(CameraHistory::stack);
        if cameras.len() != self.envs.len() || cameras.iter().any(|c| Some(c.stack()) != stack) {
            return Err(format!("{} camera histories for {} environments seeing {stack:?}", cameras.len(), self.envs.len()));
        }
        self.cameras = cameras;
        self.render_all_images();
        Ok(())
    }

    /// Number of environments.
    pub fn len(&self) -> usize {
        self.envs.len()
    }

    /// True when there are no environments.
    pub fn is_empty(&self) -> bool {
        self.envs.is_empty()
    }

    /// Length of one observation row.
    pub fn observation_dim(&self) -> usize {
        self.observation_dim
    }

    /// Steps every environment with its row of `actions` (`n × 4`).
    pub fn step(&mut self, actions: &[f32]) {
        assert_eq!(actions.len(), self.envs.len() * ACTION_DIM, "one action row per environment");
        let results: Vec<(StepOutcome, Option<EpisodeStats>)> = self
            .envs
            .par_iter_mut()
            .zip(actions.par_chunks(ACTION_DIM))
            .zip(self.observations.par_chunks_mut(self.observation_dim))
            .zip(self.final_observations.par_chunks_mut(self.observation_dim))
            .with_min_len(4)
            .map(|(((env, action), obs), final_obs)| {
                let outcome = env.step(&[action[0], action[1], action[2], action[3]]);
                let mut finished = None;
                if outcome.done() {
                    env.observe(final_obs);
                    finished = Some(*env.stats());
                    env.reset();
                }
                env.observe(obs);
                (outcome, finished)
            })
            .collect();
        self.finished.clear();
        for (i, (outcome, finished)) in results.into_iter().enumerate() {
            self.rewards[i] = outcome.reward.total() as f32;
            self.terminated[i] = outcome.terminated;
            self.truncated[i] = outcome.truncated;
            if let Some(stats) = finished {
                self.finished.push(FinishedEpisode { env: i, stats });
            }
        }
        if !self.cameras.is_empty() {
            for (i, (camera, env)) in self.cameras.iter_mut().zip(&self.envs).enumerate() {
                match self.terminated[i] || self.truncated[i] {
                    true => camera.restart(CameraPose::of(env)),
                    false => camera.record(CameraPose::of(env)),
                }
            }
        }
        self.render_all_images();
    }

    /// Gives environment `i` a new track and starts a fresh episode on it; the interrupted
    /// episode is not reported as finished.
    pub fn set_track(&mut self, i: usize, track: Arc<Track>) {
        self.envs[i].set_track(track);
        let d = self.observation_dim;
        self.envs[i].observe(&mut self.observations[i * d..(i + 1) * d]);
        if let Some(camera) = self.cameras.get_mut(i) {
            camera.restart(CameraPose::of(&self.envs[i]));
            let len = camera.stack().image_len();
            camera.render(self.envs[i].track(), &mut self.images[i * len..(i + 1) * len]);
        }
    }

    /// The environments, for inspection.
    pub fn envs(&self) -> &[RaceEnv] {
        &self.envs
    }

    /// Rebuilds a vectorised environment from saved environments (see [`VecEnv::envs`]), which
    /// must share one observation layout.
    pub fn from_envs(envs: Vec<RaceEnv>) -> Self {
        let n = envs.len();
        let layout = envs.first().map(|e| e.config().observation).unwrap_or_default();
        assert!(envs.iter().all(|e| e.config().observation == layout), "environments of one VecEnv share an observation layout");
        let observation_dim = layout.dim();
        let mut v = Self {
            envs,
            observation_dim,
            observations: vec![0.0; n * observation_dim],
            rewards: vec![0.0; n],
            terminated: vec![false; n],
            truncated: vec![false; n],
            final_observations: vec![0.0; n * observation_dim],
            finished: Vec::new(),
            images: Vec::new(),
            cameras: Vec::new(),
        };
        v.write_all_observations();
        v
    }

    /// Renders every environment's camera observation in parallel (a no-op with images off);
    /// each depends on its own environment only, so the bytes do not depend on the thread count.
    fn render_all_images(&mut self) {
        let Some(len) = self.cameras.first().map(|c| c.stack().image_len()) else {
            return;
        };
        self.envs
            .par_iter()
            .zip(self.cameras.par_iter())
            .zip(self.images.par_chunks_mut(len))
            .with_min_len(4)
            .for_each(|((env, camera), images)| camera.render(env.track(), images));
    }

    fn write_all_observations(&mut self) {
        for (env, obs) in self.envs.iter().zip(self.observations.chunks_mut(self.observation_dim)) {
            env.observe(obs);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::IMAGE_PIXELS;
    use crate::track::{Arena, Gate};
    use nalgebra::Vector3;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    fn tracks(n: usize) -> Vec<Arc<Track>> {
        let track = Arc::new(
            Track::new(
                "square",
                vec![
                    Gate::new(Vector3::new(5.0, 0.0, 2.0), 1.57),
                    Gate::new(Vector3::new(0.0, 5.0, 3.0), std::f64::consts::PI),
                    Gate::new(Vector3::new(-5.0, 0.0, 2.0), -1.57),
                    Gate::new(Vector3::new(0.0, -5.0, 2.5), 0.0),
                ],
                None,
                Arena::default(),
            )
            .unwrap(),
        );
        vec![track; n]
    }

    /// Runs 300 steps of random actions and returns every buffer's bits.
    fn run(threads: usize) -> (Vec<u32>, Vec<u32>, Vec<bool>, usize) {
        let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
        pool.install(|| {
            let mut env = VecEnv::new(tracks(16), EnvConfig::default(), 42);
            let mut rng = ChaCha8Rng::seed_from_u64(3);
            let mut rewards = Vec::new();
            let mut dones = Vec::new();
            let mut episodes = 0;
            for _ in 0..300 {
                let actions: Vec<f32> = (0..16 * 4).map(|_| rng.random_range(-1.0..1.0)).collect();
                env.step(&actions);
                rewards.extend(env.rewards.iter().map(|r| r.to_bits()));
                dones.extend(env.terminated.iter().zip(&env.truncated).map(|(a, b)| *a || *b));
                episodes += env.finished.len();
            }
            let obs = env.observations.iter().map(|o| o.to_bits()).collect();
            (obs, rewards, dones, episodes)
        })
    }

    #[test]
    fn same_seed_gives_bit_identical_results_on_one_and_two_threads() {
        let one = run(1);
        let two = run(2);
        assert!(one.3 > 0, "random actions crash and reset some episodes");
        assert_eq!(one, two);
    }

    /// Every image of 100 random-action steps, concatenated.
    fn images(threads: usize) -> Vec<u8> {
        let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
        pool.install(|| {
            let mut env = VecEnv::new(tracks(8), EnvConfig::default(), 7).with_images();
            let mut rng = ChaCha8Rng::seed_from_u64(5);
            let mut all = env.images.clone();
            for _ in 0..100 {
                let actions: Vec<f32> = (0..8 * 4).map(|_| rng.random_range(-1.0..1.0)).collect();
                env.step(&actions);
                all.extend_from_slice(&env.images);
            }
            all
        })
    }

    #[test]
    fn images_are_bit_identical_on_one_and_two_threads_and_match_each_environment() {
        let one = images(1);
        assert!(one.contains(&crate::camera::TARGET_COLOUR), "the target gate is in view at times");
        assert_eq!(one, images(2));
        let env = VecEnv::new(tracks(3), EnvConfig::default(), 7).with_images();
        let mut single = vec![0; IMAGE_PIXELS];
        env.envs()[2].render_camera(&mut single);
        assert_eq!(&env.images[2 * IMAGE_PIXELS..], &single[..]);
    }

    #[test]
    fn a_frame_stack_shows_each_environment_its_earlier_frames_and_forgets_them_on_reset() {
        let stack = FrameStack { frames: 2, stride: 3 };
        let (len, image) = (stack.image_len(), IMAGE_PIXELS);
        let mut env = VecEnv::new(tracks(2), EnvConfig::default(), 1).with_frame_stack(stack);
        let mut shown = vec![env.images.clone()];
        // Full thrust straight up crashes environment 0 within a few dozen steps.
        let actions = [1.0f32, 0.0, 0.0, 0.0, 0.2, 0.0, 0.0, 0.0];
        while !env.terminated[0] {
            env.step(&actions);
            shown.push(env.images.clone());
            assert!(shown.len() < 200);
        }
        for e in 0..2 {
            let current = |t: usize| &shown[t][e * len..e * len + image];
            let earlier = |t: usize| &shown[t][e * len + image..(e + 1) * len];
            assert_eq!(earlier(1), current(0), "the first frame stands in for the steps before it");
            assert_eq!(earlier(5), current(2), "the frame of 3 steps before");
            assert_ne!(current(5), current(2), "the drones moved");
        }
        let last = shown.len() - 1;
        assert_eq!(&shown[last][image..len], &shown[last][..image], "a reset forgets the crashed flight");
        let mut restored = VecEnv::from_envs(env.envs().to_vec()).with_frame_stack(stack);
        restored.restore_cameras(env.cameras().to_vec()).unwrap();
        assert_eq!(restored.images, env.images, "restored histories show the same frames");
        assert!(restored.restore_cameras(Vec::new()).unwrap_err().contains("0 camera histories"));
    }

    #[test]
    fn done_environments_reset_and_keep_their_final_observation() {
        let mut env = VecEnv::new(tracks(2), EnvConfig::default(), 1);
        // Full thrust straight up leaves the 6 m arena within a few dozen steps.
        let actions = [1.0f32, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0];
        let mut steps = 0;
        while !env.terminated[0] {
            env.step(&actions);
            steps += 1;
            assert!(steps < 200);
        }
        let fin = &env.finished[0];
        assert_eq!(fin.env, 0);
        assert!(fin.stats.crash.is_some());
        assert_eq!(fin.stats.length, steps);
        // The reset observation differs from the final one and starts with zero previous action.
        let (obs, final_obs) = (&env.observations[..crate::STATE_OBS_DIM], &env.final_observations[..crate::STATE_OBS_DIM]);
        assert_ne!(obs, final_obs);
        assert_eq!(&obs[12..16], &[0.0; 4]);
        assert_eq!(&final_obs[12..16], &[1.0, 0.0, 0.0, 0.0]);
    }

    #[test]
    fn replacing_a_track_restarts_that_environment_only() {
        let mut env = VecEnv::new(tracks(2), EnvConfig::default(), 1);
        env.step(&[0.0; 8]);
        let other_before = env.observations[crate::STATE_OBS_DIM..].to_vec();
        let new_track = Arc::new(
            Track::new(
                "pair",
                vec![Gate::new(Vector3::new(-3.0, 0.0, 2.0), 0.0), Gate::new(Vector3::new(3.0, 0.0, 2.0), 0.0)],
                None,
                Arena::default(),
            )
            .unwrap(),
        );
        env.set_track(0, new_track.clone());
        assert_eq!(env.envs()[0].track().name, "pair");
        assert_eq!(env.envs()[0].stats().length, 0);
        assert_eq!(&env.observations[crate::STATE_OBS_DIM..], &other_before[..]);
        // δp1 now points at the new gate 0 (start 2 m behind it, ±0.8 m randomisation).
        let dx = env.observations[16];
        assert!((dx - 2.0).abs() < 1.0, "{dx}");
    }
}
