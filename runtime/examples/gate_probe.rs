//! How precisely a vision student judges where the target gate is, read from its embedding by
//! the gate head it was distilled with (`gate_loss_weight`; a linear read-out, so a lower bound
//! on what the embedding holds).
//!
//! `cargo run --release -p runtime --example gate_probe -- CHECKPOINT DISTILL_CONFIG`
//!
//! CHECKPOINT is a periodic checkpoint of a distillation with a gate head. 32 environments on
//! the first 32 validation tracks (the config's environment settings) are flown by the student
//! for 1,500 steps. For every state whose image shows the target gate it compares the head's
//! prediction with the truth: the angle between predicted and true direction to each corner,
//! and the error of the predicted distance, by distance to the gate. A teacher given drifting
//! errors of σ × distance per axis on the corners (`randomization.gate_perception`) misjudges
//! their directions by σ·√2 rad RMS, so `RMS angle / √2` is the σ at which that teacher sees as
//! badly as the student, to be read against `perception_noise`'s table.

#![allow(clippy::print_stdout, reason = "the table on stdout is what this analysis is for")]

use std::path::Path;
use std::sync::Arc;

use anyhow::{Context, bail};
use learner::checkpoint::Checkpoint;
use policy::gate_head::{GateHead, PER_GATE, gate_targets};
use policy::{Device, VisionPolicy, WeightsBlob};
use runtime::distill::DistillConfig;
use sim::VecEnv;
use sim::camera::{IMAGE_PIXELS, TARGET_COLOUR};

#[path = "support/gate_errors.rs"]
mod gate_errors;
use gate_errors::{BINS, angle_between, bin_of};

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let [checkpoint, config] = args.as_slice() else {
        bail!("usage: gate_probe CHECKPOINT DISTILL_CONFIG");
    };
    let checkpoint = Checkpoint::read(Path::new(checkpoint))?;
    let blob = WeightsBlob::from_bytes(checkpoint.get("weights")?)?;
    let device = Device::flex();
    let head = GateHead::from_bytes(checkpoint.get("gate_head").context("a checkpoint of a run with gate_loss_weight")?, &device)
        .map_err(anyhow::Error::msg)?;
    let model = blob.vision_model(&device)?;
    let student = VisionPolicy::from_blob(&blob)?;
    let mut config = DistillConfig::read(Path::new(config))?;
    config.env.set_observation_layout(blob.architecture.observation_layout());
    let tracks = racetracks::validation_set(32)?.into_iter().map(Arc::new).collect();
    let mut env = VecEnv::new(tracks, config.env, 7).with_frame_stack(blob.architecture.frame_stack);
    let observation = blob.architecture.frame_stack.image_len();
    // Per bin: summed squared corner angles (rad²), corners, summed squared relative distance
    // errors, states.
    let mut sums = [[0f64; 4]; BINS.len()];
    for _ in 0..1500 {
        let predicted = head.predict(&model, &env.images, &device);
        for (i, e) in env.envs().iter().enumerate() {
            // The current frame comes first.
            if !env.images[i * observation..i * observation + IMAGE_PIXELS].contains(&TARGET_COLOUR) {
                continue;
            }
            let body = e.body();
            let truth = gate_targets(e.track(), e.target_gate(), &body.position, &body.rotation());
            let guess = &predicted[i * truth.len()..(i + 1) * truth.len()];
            let distance = f64::from(truth[PER_GATE - 1]).exp();
            let bin = bin_of(distance);
            for (t, g) in truth[..PER_GATE - 1].chunks(3).zip(guess.chunks(3)) {
                sums[bin][0] += angle_between(t, g).powi(2);
                sums[bin][1] += 1.0;
            }
            sums[bin][2] += (f64::from(guess[PER_GATE - 1] - truth[PER_GATE - 1]).exp() - 1.0).powi(2);
            sums[bin][3] += 1.0;
        }
        let actions = student.deterministic_actions(&env.images, &env.observations);
        env.step(&actions);
    }
    println!("target gate in view, flown by the student: RMS errors of its gate head");
    println!("{:>8} {:>7} {:>16} {:>12} {:>14}", "to gate", "states", "corner angle (°)", "as σ", "distance (%)");
    let mut total = [0f64; 4];
    for ((_, name), s) in BINS.iter().zip(&sums) {
        total.iter_mut().zip(s).for_each(|(t, v)| *t += v);
        print_row(name, s);
    }
    print_row("all", &total);
    Ok(())
}

/// One row of the table: states, RMS corner angle in degrees, the σ it matches, RMS distance error.
fn print_row(name: &str, s: &[f64; 4]) {
    let angle = (s[0] / s[1]).sqrt();
    println!(
        "{name:>8} {:>7} {:>16.2} {:>12.3} {:>14.1}",
        s[3],
        angle.to_degrees(),
        angle / std::f64::consts::SQRT_2,
        100.0 * (s[2] / s[3]).sqrt()
    );
}
