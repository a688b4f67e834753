//! The Python package against the Rust side: `RaceVecEnv` flies the trajectories of `sim::VecEnv`
//! (training's environment) for the same seed and actions, and `Policy`, `Racer` and
//! `dronerace.evaluate` reproduce `dronerace eval`'s deployments of the shipped generalist.
//! Needs `python3` importing the package built from this checkout (`tests/run.sh` runs
//! `pip install ./python` into `.venv` first); the checks are `python/tests/against_rust.py`.

// Test code: a panic is how a failure is reported.
#![allow(clippy::unwrap_used, clippy::expect_used)]

mod support;

use std::path::Path;
use std::process::Command;
use std::sync::Arc;

use sim::{EnvConfig, VecEnv};
use support::prerequisites::{Need, available};

const NEEDS: [Need; 1] = [Need::Python { modules: &["dronerace", "gymnasium"], packages: "./python" }];

fn root() -> &'static Path {
    Path::new(env!("CARGO_MANIFEST_DIR"))
}

/// Runs `python/tests/against_rust.py` with `args`; its output, or a panic with it.
fn against_rust(args: &[&str]) -> String {
    let out = Command::new("python3").arg(root().join("python/tests/against_rust.py")).args(args).output().expect("python3 runs");
    let text = format!("{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
    assert!(out.status.success(), "against_rust.py {args:?}:\n{text}");
    text
}

#[test]
fn race_vec_env_flies_the_trajectories_of_the_training_environment() {
    if !available("race_vec_env_flies_the_trajectories_of_the_training_environment", &NEEDS) {
        return;
    }
    let (n, steps, seed) = (4, 300, 11);
    let names = ["Figure8", "Kidney"];
    let library = racetracks::library().unwrap();
    let tracks: Vec<Arc<sim::Track>> =
        (0..n).map(|i| Arc::new(library.iter().find(|t| t.name == names[i % names.len()]).unwrap().clone())).collect();
    let mut env = VecEnv::new(tracks, EnvConfig::state_agent(), seed);
    let initial = env.observations.clone();
    // Smooth, different per environment and strong enough to crash: episodes end and restart.
    let actions: Vec<Vec<f32>> = (0..steps).map(|t| (0..n * 4).map(|j| (0.05 * t as f32 + j as f32).sin() * 0.9).collect()).collect();
    let (mut observations, mut final_observations, mut rewards, mut terminated, mut truncated) = (vec![], vec![], vec![], vec![], vec![]);
    let dim = env.observation_dim();
    let rows = |v: &[f32]| v.chunks(dim).map(<[f32]>::to_vec).collect::<Vec<_>>();
    for a in &actions {
        env.step(a);
        observations.push(rows(&env.observations));
        final_observations.push(rows(&env.final_observations));
        rewards.push(env.rewards.clone());
        terminated.push(env.terminated.clone());
        truncated.push(env.truncated.clone());
    }
    let reference = serde_json::json!({
        "num_envs": n, "seed": seed, "tracks": names,
        "initial_observations": rows(&initial),
        "actions": actions.iter().map(|a| a.chunks(4).map(<[f32]>::to_vec).collect::<Vec<_>>()).collect::<Vec<_>>(),
        "observations": observations, "final_observations": final_observations,
        "rewards": rewards, "terminated": terminated, "truncated": truncated,
    });
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("reference.json");
    std::fs::write(&path, reference.to_string()).unwrap();
    let report = against_rust(&["vecenv", path.to_str().unwrap()]);
    assert!(report.contains("identical"), "{report}");
}

#[test]
fn python_flies_the_shipped_generalist_as_dronerace_eval_does() {
    if !available("python_flies_the_shipped_generalist_as_dronerace_eval_does", &NEEDS) {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let (policy, track) = (root().join("policies/generalist.bin"), root().join("tracks/figure8.toml"));
    let (out, trajectories) = (dir.path().join("eval"), dir.path().join("trajectories"));
    let status = Command::new(env!("CARGO_BIN_EXE_dronerace"))
        .args(["eval", "--runs", "3", "--policy"])
        .arg(&policy)
        .arg("--tracks")
        .arg(&track)
        .arg("--out")
        .arg(&out)
        .arg("--trajectories")
        .arg(&trajectories)
        .status()
        .unwrap();
    assert!(status.success());
    let report: serde_json::Value = serde_json::from_slice(&std::fs::read(out.join("eval.json")).unwrap()).unwrap();
    assert_eq!(report["success_rate"], 1.0, "the generalist laps Figure8: {}", report["tracks"][0]["outcomes"]);
    let report_file = out.join("eval.json");
    let files = [&policy, &track, &report_file, &trajectories].map(|p| p.to_str().unwrap());
    let checked = against_rust(&["eval", files[0], files[1], files[2], files[3]]);
    assert!(checked.contains("laps as dronerace eval"), "{checked}");
}
