//! `dronerace bench sim`: how many environment steps per second the training environments take.

use std::str::FromStr;
use std::sync::Arc;
use std::time::Instant;

use rand::{Rng, SeedableRng};
use sim::{Controller, EnvConfig, ReferencePilot, Track, VecEnv};

/// Where the benchmark's actions come from.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum BenchActions {
    /// Uniform in [-1, 1]⁴, with training randomisation (many early crashes).
    Random,
    /// The hover command without randomisation: every step runs all substeps and episodes end
    /// only by truncation (the worst case per step).
    Hover,
    /// The reference pilot racing each track: the images a racing policy sees.
    Pilot,
}

/// What the benchmark's environments observe.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum BenchObs {
    /// The state-based agent's observations.
    State,
    /// The vision agent's: the 84×84 camera image of every environment after every step too.
    Vision,
}

/// One measurement of the simulator.
#[derive(Clone, Copy, Debug)]
pub struct SimBench {
    /// Parallel environments.
    pub envs: usize,
    /// Worker threads.
    pub threads: usize,
    /// Vectorised steps timed.
    pub steps: usize,
    /// Action source.
    pub actions: BenchActions,
    /// Observations.
    pub obs: BenchObs,
}

/// What [`SimBench::measure`] found.
#[derive(Clone, Debug)]
pub struct SimBenchReport {
    /// Environment steps per second over all threads.
    pub rate: f64,
    /// Seconds spent in the simulator's steps.
    pub seconds: f64,
    /// Episodes that ended.
    pub episodes: usize,
    /// Run-length coded sizes (bytes) of a sample of the images, sorted: what rollout chunks
    /// carry of them. Empty for state observations.
    pub coded_image_bytes: Vec<usize>,
}

/// A benchmark setting the command line spelt wrong.
#[derive(Debug, thiserror::Error)]
pub enum SimBenchError {
    /// Nothing to step.
    #[error("--envs and --steps must be at least 1")]
    Empty,
    /// The worker pool could not start.
    #[error("starting {threads} worker threads: {source}")]
    Threads {
        /// Threads asked for.
        threads: usize,
        /// What rayon said.
        source: rayon::ThreadPoolBuildError,
    },
}

impl SimBench {
    /// Steps the environments on `tracks` (round robin) and times the simulator alone: the
    /// reference pilot's own time stays outside the timing.
    pub fn measure(&self, tracks: &[Arc<Track>]) -> Result<SimBenchReport, SimBenchError> {
        let Self { envs, threads, steps, actions: kind, obs } = *self;
        if envs == 0 || steps == 0 || tracks.is_empty() {
            return Err(SimBenchError::Empty);
        }
        let pool =
            rayon::ThreadPoolBuilder::new().num_threads(threads).build().map_err(|source| SimBenchError::Threads { threads, source })?;
        let tracks: Vec<Arc<Track>> = (0..envs).map(|i| tracks[i % tracks.len()].clone()).collect();
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(0);
        let hover = sim::quadrotor::Command::hover().to_action(&sim::QuadrotorParams::default()).map(|a| a as f32);
        let actions: Vec<Vec<f32>> = match kind {
            BenchActions::Random => (0..64).map(|_| (0..envs * 4).map(|_| rng.random_range(-1.0..1.0)).collect()).collect(),
            BenchActions::Hover | BenchActions::Pilot => vec![hover.repeat(envs)],
        };
        let mut pilots: Vec<ReferencePilot> = (0..envs).map(|_| ReferencePilot::default()).collect();
        let report = pool.install(|| {
            // The environments the agent trains in: what a training run steps.
            let agent = match obs {
                BenchObs::State => EnvConfig::state_agent(),
                BenchObs::Vision => EnvConfig::vision_agent(),
            };
            let config = match kind {
                BenchActions::Random | BenchActions::Pilot => agent,
                BenchActions::Hover => EnvConfig { randomization: sim::RandomizationParams::none(), ..agent },
            };
            let mut env = VecEnv::new(tracks, config, 0);
            if obs == BenchObs::Vision {
                env = env.with_images();
            }
            let (mut episodes, mut seconds, mut coded) = (0, 0.0, Vec::new());
            let mut pilot_actions = vec![0.0f32; envs * 4];
            for k in 0..steps {
                let mut step_actions = &actions[k % actions.len()];
                if kind == BenchActions::Pilot {
                    for (i, (pilot, row)) in pilots.iter_mut().zip(pilot_actions.chunks_mut(4)).enumerate() {
                        if env.envs()[i].stats().length == 0 {
                            pilot.reset(&env.envs()[i]);
                        }
                        row.copy_from_slice(&pilot.act(&env.envs()[i]));
                    }
                    step_actions = &pilot_actions;
                }
                let started = Instant::now();
                env.step(step_actions);
                seconds += started.elapsed().as_secs_f64();
                episodes += env.finished.len();
                if !env.images.is_empty() && k % 10 == 0 {
                    for image in env.images.chunks(sim::camera::IMAGE_PIXELS) {
                        let mut code = Vec::new();
                        rollout::run_length::encode(image, &mut code);
                        coded.push(code.len());
                    }
                }
            }
            coded.sort_unstable();
            SimBenchReport { rate: (envs * steps) as f64 / seconds, seconds, episodes, coded_image_bytes: coded }
        });
        Ok(report)
    }
}

impl FromStr for BenchActions {
    type Err = String;

    fn from_str(text: &str) -> Result<Self, String> {
        match text {
            "random" => Ok(Self::Random),
            "hover" => Ok(Self::Hover),
            "pilot" => Ok(Self::Pilot),
            other => Err(format!("{other:?} is not random, hover or pilot")),
        }
    }
}

impl FromStr for BenchObs {
    type Err = String;

    fn from_str(text: &str) -> Result<Self, String> {
        match text {
            "state" => Ok(Self::State),
            "vision" => Ok(Self::Vision),
            other => Err(format!("{other:?} is not state or vision")),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn hover_steps_every_environment_without_ending_an_episode() {
        let g = |x, y, yaw_deg: f64| sim::Gate::new(sim::nalgebra::Vector3::new(x, y, 2.5), yaw_deg.to_radians());
        let gates = vec![g(0.0, -6.0, 0.0), g(9.0, 0.0, 90.0), g(0.0, 6.0, 180.0), g(-9.0, 0.0, -90.0)];
        let track = Arc::new(Track::new("oval", gates, None, sim::Arena::default()).expect("a valid oval"));
        let bench = SimBench { envs: 3, threads: 1, steps: 20, actions: BenchActions::Hover, obs: BenchObs::State };
        let report = bench.measure(&[track]).expect("measures");
        assert_eq!(report.episodes, 0, "hovering from the start pose ends no episode in 20 steps");
        assert!(report.rate > 0.0 && report.seconds > 0.0);
        assert!(report.coded_image_bytes.is_empty(), "state observations carry no images");
        assert!(matches!(SimBench { envs: 0, ..bench }.measure(&[]), Err(SimBenchError::Empty)));
    }
}
