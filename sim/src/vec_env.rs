//! N race environments stepped in parallel into contiguous f32 buffers.
//!
//! Each environment owns its random stream, so results are bit-identical whatever the number
//! of rayon threads. Finished episodes reset automatically; the observation that ended them is
//! kept in `final_observations` so a learner can bootstrap truncated episodes. With images on,
//! each environment's camera image is rendered after every step into `images`.

use std::sync::Arc;

use rayon::prelude::*;

use crate::camera::IMAGE_PIXELS;
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
    /// Current camera images, `n × 84 × 84` bytes; empty unless [`VecEnv::with_images`].
    pub images: Vec<u8>,
}

impl VecEnv {
    /// One environment per track, environment `i` on random stream `i` of `seed`.
    pub fn new(tracks: Vec<Arc<Track>>, config: EnvConfig, seed: u64) -> Self {
        let envs: Vec<RaceEnv> = tracks.into_iter().enumerate().map(|(i, t)| RaceEnv::new(t, config, seed, i as u64)).collect();
        Self::from_envs(envs)
    }

    /// Renders a camera image for every environment after every step from now on (SPEC §5).
    pub fn with_images(mut self) -> Self {
        self.enable_images();
        self
    }

    /// [`VecEnv::with_images`] in place: renders the current images at once (a no-op when
    /// images are on already).
    pub fn enable_images(&mut self) {
        if self.images.is_empty() && !self.envs.is_empty() {
            self.images = vec![0; self.envs.len() * IMAGE_PIXELS];
            self.render_all_images();
        }
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
        self.render_all_images();
    }

    /// Gives environment `i` a new track and starts a fresh episode on it; the interrupted
    /// episode is not reported as finished.
    pub fn set_track(&mut self, i: usize, track: Arc<Track>) {
        self.envs[i].set_track(track);
        let d = self.observation_dim;
        self.envs[i].observe(&mut self.observations[i * d..(i + 1) * d]);
        if !self.images.is_empty() {
            self.envs[i].render_camera(&mut self.images[i * IMAGE_PIXELS..(i + 1) * IMAGE_PIXELS]);
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
        };
        v.write_all_observations();
        v
    }

    /// Renders every environment's camera image in parallel (a no-op with images off);
    /// each depends on its own environment only, so the bytes do not depend on the thread count.
    fn render_all_images(&mut self) {
        if self.images.is_empty() {
            return;
        }
        self.envs
            .par_iter()
            .zip(self.images.par_chunks_mut(IMAGE_PIXELS))
            .with_min_len(4)
            .for_each(|(env, image)| env.render_camera(image));
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
