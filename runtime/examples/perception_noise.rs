//! How much of a state-based teacher's skill survives a camera's imprecision: the teacher flies
//! the test set (SPEC §9: 40 tracks × 25 deployments) with noise on the gate corners of its observation, of the size a vision
//! student's estimate of them might have.
//!
//! `cargo run --release -p runtime --example perception_noise -- TEACHER [SIGMA …]`
//!
//! Each corner the observation shows (SPEC §5's target-gate corners, and the next gate's,
//! written relative to them) is moved by `σ · d · n`: `d` the distance from the drone to that
//! corner, `n` a standard normal 3-vector per corner that changes slowly (AR(1), ρ = 0.9 a step,
//! ~0.2 s of memory), so the error is a drifting misjudgement rather than jitter the policy
//! would average away. One pixel of the 84-pixel, 90° camera is 1.9 % of the distance
//! sideways. Prints the test report's S_pw and success for each σ (default 0, 0.02, 0.05, 0.1).

#![allow(clippy::print_stdout, reason = "the table on stdout is what this analysis is for")]

use std::path::Path;
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};

use anyhow::{Context, bail};
use learner::checkpoint::read_policy;
use policy::Policy;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use sim::eval::{EvalConfig, evaluate};
use sim::{Controller, ObservationLayout, RaceEnv};

/// Where the target gate's corners sit in the state observation (SPEC §5 order), and the next
/// gate's (relative to the target's).
const TARGET_CORNERS: usize = 16;
const NEXT_CORNERS: usize = 28;
/// Step-to-step correlation of the noise.
const RHO: f64 = 0.9;

/// The teacher, reading a noisy observation.
struct NoisyTeacher {
    policy: Arc<Policy>,
    layout: ObservationLayout,
    sigma: f64,
    rng: ChaCha8Rng,
    /// The slowly changing standard normal per corner: target's 4, then the next gate's 4.
    noise: [[f64; 3]; 8],
}

impl NoisyTeacher {
    fn normal(&mut self) -> f64 {
        // Box–Muller; 1 − u keeps the logarithm finite.
        let (u, v): (f64, f64) = (self.rng.random(), self.rng.random());
        (-2.0 * (1.0 - u).ln()).sqrt() * (std::f64::consts::TAU * v).cos()
    }
}

impl Controller for NoisyTeacher {
    fn reset(&mut self, _env: &RaceEnv) {
        for c in 0..8 {
            for k in 0..3 {
                self.noise[c][k] = self.normal();
            }
        }
    }

    fn act(&mut self, env: &RaceEnv) -> [f32; 4] {
        let mut observation = env.observation_in(self.layout);
        let innovation = (1.0 - RHO * RHO).sqrt();
        for c in 0..8 {
            for k in 0..3 {
                self.noise[c][k] = RHO * self.noise[c][k] + innovation * self.normal();
            }
        }
        for c in 0..4 {
            let target = TARGET_CORNERS + 3 * c..TARGET_CORNERS + 3 * c + 3;
            let next = NEXT_CORNERS + 3 * c..NEXT_CORNERS + 3 * c + 3;
            let to_target: Vec<f64> = observation[target.clone()].iter().map(|v| f64::from(*v)).collect();
            let between: Vec<f64> = observation[next.clone()].iter().map(|v| f64::from(*v)).collect();
            // All zeros: the gate is out of the camera's view, and stays unseen.
            if to_target.iter().any(|v| *v != 0.0) {
                let d = to_target.iter().map(|v| v * v).sum::<f64>().sqrt();
                for k in 0..3 {
                    observation[target.start + k] += (self.sigma * d * self.noise[c][k]) as f32;
                }
            }
            if between.iter().any(|v| *v != 0.0) {
                let d = to_target.iter().zip(&between).map(|(a, b)| (a + b) * (a + b)).sum::<f64>().sqrt();
                for k in 0..3 {
                    observation[next.start + k] += (self.sigma * d * self.noise[4 + c][k]) as f32;
                }
            }
        }
        let action = self.policy.deterministic_actions(&observation);
        std::array::from_fn(|i| action[i])
    }
}

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let [teacher, sigmas @ ..] = args.as_slice() else {
        bail!("usage: perception_noise TEACHER [SIGMA …]");
    };
    let sigmas: Vec<f64> = match sigmas {
        [] => vec![0.0, 0.02, 0.05, 0.1],
        given => given.iter().map(|s| s.parse().with_context(|| format!("sigma {s:?}"))).collect::<anyhow::Result<_>>()?,
    };
    let blob = read_policy(Path::new(teacher)).with_context(|| format!("teacher {teacher}"))?;
    let policy = Arc::new(Policy::from_blob(&blob)?);
    let layout = policy.observation_layout();
    let tracks: Vec<Arc<sim::Track>> = racetracks::test_set(racetracks::track_sets::TEST_SEED)?.into_iter().map(Arc::new).collect();
    println!("{:>6} {:>8} {:>8}", "sigma", "success", "S_pw");
    for sigma in sigmas {
        let seeds = AtomicU64::new(0);
        let make = || -> Box<dyn Controller> {
            Box::new(NoisyTeacher {
                policy: policy.clone(),
                layout,
                sigma,
                rng: ChaCha8Rng::seed_from_u64(seeds.fetch_add(1, Ordering::Relaxed)),
                noise: [[0.0; 3]; 8],
            })
        };
        let report = evaluate("noisy teacher", &tracks, &make, &EvalConfig::default());
        println!("{sigma:>6.3} {:>7.1} % {:>8.4}", 100.0 * report.success_rate, report.s_pw);
    }
    Ok(())
}
