//! How long a vision policy would have to remember a gate: on a state-based teacher's flights,
//! the steps between the last time the target gate's corners were on the camera's image and
//! the passage through that gate.
//!
//! `cargo run --release -p runtime --example corner_memory -- TEACHER`
//!
//! 32 environments on the first 32 validation tracks (evaluation settings, the teacher's
//! observation layout) are flown by the teacher for 1,500 steps. At every gate passage it
//! records how many steps had gone by since all four corners of that gate were last on the
//! image, and since any was; percentiles over all passages, in steps of 20 ms.

#![allow(clippy::print_stdout, reason = "the table on stdout is what this analysis is for")]

use std::path::Path;
use std::sync::Arc;

use anyhow::{Context, bail};
use learner::checkpoint::read_policy;
use policy::Policy;
use sim::camera::point_in_view;
use sim::{EnvConfig, VecEnv};

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let [teacher] = args.as_slice() else {
        bail!("usage: corner_memory TEACHER");
    };
    let blob = read_policy(Path::new(teacher)).with_context(|| format!("teacher {teacher}"))?;
    let teacher = Policy::from_blob(&blob)?;
    let mut config = EnvConfig::evaluation();
    config.set_observation_layout(blob.architecture.observation_layout());
    let tracks = racetracks::validation_set(32)?.into_iter().map(Arc::new).collect();
    let mut env = VecEnv::new(tracks, config, 7);
    let n = env.len();
    // Per environment: its target gate, and the steps since all / any of its corners were seen.
    let mut target: Vec<usize> = env.envs().iter().map(|e| e.target_gate()).collect();
    let mut since = vec![[0usize; 2]; n];
    let mut length = vec![0u32; n];
    let (mut all_gaps, mut any_gaps) = (Vec::new(), Vec::new());
    for _ in 0..1500 {
        let actions = teacher.deterministic_actions(&env.observations);
        env.step(&actions);
        for (i, e) in env.envs().iter().enumerate() {
            let restarted = e.stats().length < length[i];
            length[i] = e.stats().length;
            if restarted || e.target_gate() != target[i] {
                // A passage is counted; a new episode only starts the count again.
                if !restarted {
                    all_gaps.push(since[i][0]);
                    any_gaps.push(since[i][1]);
                }
                target[i] = e.target_gate();
                since[i] = [0, 0];
            }
            let body = e.body();
            let rotation = body.rotation();
            let seen = e.track().gates[target[i]].corners().map(|c| point_in_view(&c, &body.position, &rotation));
            since[i][0] = if seen.iter().all(|s| *s) { 0 } else { since[i][0] + 1 };
            since[i][1] = if seen.iter().any(|s| *s) { 0 } else { since[i][1] + 1 };
        }
    }
    println!("{} gate passages; steps (20 ms) since the gate's corners were last on the image", all_gaps.len());
    println!("{:>12} {:>8} {:>8} {:>8} {:>8}", "corners", "median", "75 %", "90 %", "max");
    for (name, gaps) in [("all four", &mut all_gaps), ("any", &mut any_gaps)] {
        gaps.sort_unstable();
        let at = |q: f64| gaps.get(((gaps.len() as f64 - 1.0) * q).round() as usize).copied().unwrap_or(0);
        println!("{name:>12} {:>8} {:>8} {:>8} {:>8}", at(0.5), at(0.75), at(0.9), at(1.0));
    }
    Ok(())
}
