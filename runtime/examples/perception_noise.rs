//! How much of a state-based teacher's skill survives a camera's imprecision: the teacher flies
//! the test set (SPEC §9: 40 tracks × 25 deployments) with the gate-corner error of
//! `randomization.gate_perception` (`sim::perception`) in its observation, of the size a vision
//! student's estimate of the gates might have.
//!
//! `cargo run --release -p runtime --example perception_noise -- TEACHER [SIGMA[,FLOOR] …]`
//!
//! Each corner the observation shows moves by `σ · d · n`: `d` the distance from the drone to
//! that corner, `n` a standard normal 3-vector per corner that drifts (AR(1), ρ = 0.9 a step),
//! so the error is a lasting misjudgement rather than jitter the policy would average away. One
//! pixel of the 84-pixel, 90° camera is 1.9 % of the distance sideways. The noise is drawn after
//! each start's perturbation, so every σ flies the same starts. With a FLOOR (m,
//! `randomization.gate_perception_floor`) the error's scale is `hypot(σ · d, FLOOR)`. Prints the
//! test report's success and S_pw for each σ (default 0, 0.02, 0.05, 0.1).

#![allow(clippy::print_stdout, reason = "the table on stdout is what this analysis is for")]

use std::path::Path;
use std::sync::Arc;

use anyhow::{Context, bail};
use learner::checkpoint::read_policy;
use sim::eval::{EvalConfig, evaluate};

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let [teacher, sigmas @ ..] = args.as_slice() else {
        bail!("usage: perception_noise TEACHER [SIGMA[,FLOOR] …]");
    };
    let parse = |s: &str| -> anyhow::Result<(f64, f64)> {
        let (sigma, floor) = s.split_once(',').unwrap_or((s, "0"));
        Ok((sigma.parse().with_context(|| format!("sigma {s:?}"))?, floor.parse().with_context(|| format!("floor {s:?}"))?))
    };
    let sigmas: Vec<(f64, f64)> = match sigmas {
        [] => vec![(0.0, 0.0), (0.02, 0.0), (0.05, 0.0), (0.1, 0.0)],
        given => given.iter().map(|s| parse(s)).collect::<anyhow::Result<_>>()?,
    };
    let blob = read_policy(Path::new(teacher)).with_context(|| format!("teacher {teacher}"))?;
    let make = policy::controller_factory(&blob)?;
    let tracks: Vec<Arc<sim::Track>> = racetracks::test_set(racetracks::track_sets::TEST_SEED)?.into_iter().map(Arc::new).collect();
    println!("{:>6} {:>6} {:>8} {:>8}", "sigma", "floor", "success", "S_pw");
    for (sigma, floor) in sigmas {
        let mut config = EvalConfig::default();
        config.env.randomization.gate_perception = sigma;
        config.env.randomization.gate_perception_floor = floor;
        let report = evaluate("noisy teacher", &tracks, make.as_ref(), &config);
        println!("{sigma:>6.3} {floor:>6.2} {:>7.1} % {:>8.4}", 100.0 * report.success_rate, report.s_pw);
    }
    Ok(())
}
