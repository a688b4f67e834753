//! Can the vision agent's CNN (SPEC §5) place the gates as precisely as a policy needs? Trains
//! it to do nothing else — the gate head's loss alone (`learner::distill::Student::gate_step`),
//! no imitation — on images of a teacher's flights, and reports its errors on held-out tracks
//! in the units of `perception_noise`'s table, so the answer reads against what the camera-sight
//! teachers fly with such errors.
//!
//! `cargo run --release -p runtime --example gate_localisation -- DISTILL_CONFIG MODE STEPS [LR[,LR_END]] [OUT]`
//!
//! The config's teacher flies 512 generated training tracks (64 environments at a time, 2,000
//! steps; a reservoir of 800,000 states whose image shows the target or the next gate) and the
//! first 32 validation tracks (1,500 steps; 30,000 states), with the config's environment
//! settings.
//! MODE says what learns: `probe` — a fresh linear gate head on the frozen CNN of the config's
//! `init_from` (what its embedding already holds); `tune` — that CNN and the head together;
//! `fresh` — a new CNN and head; `continue` — the CNN of OUT and the gate head beside it, both
//! training (a long run in pieces; the optimiser's moments and the minibatch draws start
//! afresh). STEPS gradient steps of 128 samples, learning rate LR (3e-4) falling linearly to
//! LR_END (LR if not given) at the last step;
//! every 500 a table for 30,000 training states and for the validation states: over those
//! whose image shows the target gate, by distance to it, the RMS angle between predicted and
//! true direction to each corner, the RMS error per axis of each corner's position (m;
//! `perception_noise`'s floor is per axis too), the RMS relative error of the distance, and the
//! RMS angle apart for corners on the image and off it (a corner off the image must be
//! inferred from the bars that are on it).
//! OUT, if given, receives the student's weights blob at every table, and OUT with the extension
//! `.head` its gate head (`policy::gate_head::GateHead::to_bytes`): what `cnn_perception` flies
//! a teacher on.

#![allow(clippy::print_stdout, reason = "the table on stdout is what this analysis is for")]

use std::path::Path;
use std::sync::Arc;

use anyhow::{Context, bail};
use learner::checkpoint::read_policy;
use learner::distill::{DistillDataset, Student};
use policy::gate_head::{GATE_TARGETS, PER_GATE};
use policy::{Device, Policy};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use runtime::distill::DistillConfig;
use sim::camera::{IMAGE_PIXELS, NEXT_COLOUR, TARGET_COLOUR, point_in_view};
use sim::nalgebra::{Matrix3, Vector3};
use sim::{EnvConfig, FrameStack, Track, VecEnv};

#[path = "support/gate_errors.rs"]
mod gate_errors;
use gate_errors::{BINS, angle_between, bin_of};

const MINIBATCH: usize = 128;
const REPORT_EVERY: usize = 500;
const SEED: u64 = 0;
/// Generated training tracks (seeds 1, 2, …), flown 64 at a time.
const TRAINING_TRACKS: u64 = 512;
/// Training states kept (a reservoir over all the flights offer).
const TRAINING_STATES: usize = 800_000;

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let (config, mode, steps, rest) = match args.as_slice() {
        [config, mode, steps, rest @ ..] if rest.len() <= 2 => (config, mode.as_str(), steps.parse::<usize>().context("STEPS")?, rest),
        _ => bail!("usage: gate_localisation DISTILL_CONFIG probe|tune|fresh|continue STEPS [LR[,LR_END]] [OUT]"),
    };
    let (learning_rate, final_rate) = match rest.first() {
        None => (3e-4, 3e-4),
        Some(given) => {
            let (start, end) = given.split_once(',').unwrap_or((given, given));
            (start.parse::<f64>().context("LR")?, end.parse::<f64>().context("LR_END")?)
        }
    };
    let train_cnn = match mode {
        "probe" => false,
        "tune" | "fresh" | "continue" => true,
        other => bail!("MODE {other:?}: probe, tune, fresh or continue"),
    };
    let out = rest.get(1).map(Path::new);
    let head_path = out.map(|out| out.with_extension("head"));
    let config = DistillConfig::read(Path::new(config))?;
    let teacher = read_policy(&config.teacher).with_context(|| format!("teacher {}", config.teacher.display()))?;
    let (start_path, saved_head) = match (mode, out, &head_path) {
        ("continue", Some(out), Some(head)) => (out, Some(std::fs::read(head).with_context(|| format!("gate head {}", head.display()))?)),
        ("continue", ..) => bail!("continue needs OUT (and the .head file beside it) to continue from"),
        _ => (config.init_from.as_deref().context("the config names the student's start (init_from)")?, None),
    };
    let start = read_policy(start_path).with_context(|| format!("student {}", start_path.display()))?;
    let from = (mode != "fresh").then_some(&start);
    let mut student = Student::new(&start.architecture, None, from, 0.0, SEED)?.with_gate_head(1.0, saved_head.as_deref(), SEED)?;

    let mut env = config.env;
    env.set_observation_layout(teacher.architecture.observation_layout());
    let pilot = Policy::from_blob(&teacher)?;
    let generator = racetracks::generator::TrackGenerator::default();
    let mut train = DistillDataset::new(TRAINING_STATES, env.observation_layout().dim(), FrameStack::default());
    for batch in 0..TRAINING_TRACKS / 64 {
        let seeds = 1 + 64 * batch..=64 * (batch + 1);
        let tracks = seeds.map(|seed| Ok(Arc::new(generator.generate(seed, &format!("train-{seed}"))?.track)));
        fly(tracks.collect::<anyhow::Result<_>>()?, env, &pilot, 2000, &mut train, batch);
    }
    let validation: Vec<Arc<Track>> = racetracks::validation_set(32)?.into_iter().map(Arc::new).collect();
    let mut held_out = DistillDataset::new(30_000, env.observation_layout().dim(), FrameStack::default());
    fly(validation, env, &pilot, 1500, &mut held_out, 1000);
    println!("{mode}: {} training states ({} offered), {} validation states", train.len(), train.seen(), held_out.len());
    // As many training states as validation ones, spread over the set, to tell fitting from
    // generalising.
    let train_rows: Vec<usize> = (0..held_out.len()).map(|k| k * train.len() / held_out.len()).collect();

    let mut rng = ChaCha8Rng::seed_from_u64(SEED);
    let (mut loss_sum, mut loss_count) = (0.0, 0);
    for step in 1..=steps {
        let rows: Vec<usize> = (0..MINIBATCH).map(|_| rng.random_range(0..train.len())).collect();
        let rate = learning_rate + (final_rate - learning_rate) * (step - 1) as f64 / (steps.max(2) - 1) as f64;
        loss_sum += student.gate_step(&train, &rows, rate, train_cnn)?;
        loss_count += 1;
        if step % REPORT_EVERY == 0 || step == steps {
            println!("step {step}: training loss {:.4}, learning rate {rate:.2e}", loss_sum / f64::from(loss_count));
            (loss_sum, loss_count) = (0.0, 0);
            println!("training states:");
            report(&student, &train, &train_rows);
            println!("validation states:");
            report(&student, &held_out, &(0..held_out.len()).collect::<Vec<_>>());
            if let (Some(out), Some(head_path), Some(head)) = (out, &head_path, student.gate_head_bytes()) {
                racetracks::files::write_atomic(out, &student.weights().to_bytes())
                    .with_context(|| format!("writing {}", out.display()))?;
                racetracks::files::write_atomic(head_path, &head).with_context(|| format!("writing {}", head_path.display()))?;
            }
        }
    }
    Ok(())
}

/// Offers `data` the states `pilot` visits on `tracks` (one environment each, `steps` steps)
/// whose image shows the target or the next gate; the labels are unused.
fn fly(tracks: Vec<Arc<Track>>, env: EnvConfig, pilot: &Policy, steps: usize, data: &mut DistillDataset, seed: u64) {
    let mut envs = VecEnv::new(tracks, env, seed).with_images();
    let dim = envs.observation_dim();
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    for _ in 0..steps {
        for (i, e) in envs.envs().iter().enumerate() {
            let image = &envs.images[i * IMAGE_PIXELS..(i + 1) * IMAGE_PIXELS];
            if image.contains(&TARGET_COLOUR) || image.contains(&NEXT_COLOUR) {
                data.offer(e, &envs.observations[i * dim..(i + 1) * dim], &[0.0; 4], &mut rng);
            }
        }
        let actions = pilot.deterministic_actions(&envs.observations);
        envs.step(&actions);
    }
}

/// Prints the table (module docs) of the student's gate head on samples `rows` of `data`.
fn report(student: &Student, data: &DistillDataset, rows: &[usize]) {
    let Some((model, head)) = student.vision_with_gate_head() else { return };
    let device = Device::flex();
    // Per bin: squared corner angles (rad²), squared corner position errors (m², 3 axes),
    // corners, squared relative distance errors, states; then squared angles and corners, on
    // the image and off it.
    let mut sums = [[0f64; 9]; BINS.len()];
    for chunk in rows.chunks(1024) {
        let images = data.images(chunk);
        let predicted = head.predict(&model, &images, &device);
        let truths = data.gate_targets(chunk);
        for (k, image) in images.chunks_exact(IMAGE_PIXELS).enumerate() {
            if !image.contains(&TARGET_COLOUR) {
                continue;
            }
            let (truth, guess) = (&truths[k * GATE_TARGETS..][..PER_GATE], &predicted[k * GATE_TARGETS..][..PER_GATE]);
            let (true_distance, guessed_distance) = (f64::from(truth[PER_GATE - 1]).exp(), f64::from(guess[PER_GATE - 1]).exp());
            let bin = &mut sums[bin_of(true_distance)];
            for (t, g) in truth[..PER_GATE - 1].chunks(3).zip(guess.chunks(3)) {
                let angle = angle_between(t, g).powi(2);
                bin[0] += angle;
                // The direction is in the body frame: the camera's view of it from the origin.
                let direction = Vector3::new(f64::from(t[0]), f64::from(t[1]), f64::from(t[2]));
                let on_image = usize::from(point_in_view(&direction, &Vector3::zeros(), &Matrix3::identity()));
                bin[7 - 2 * on_image] += angle;
                bin[8 - 2 * on_image] += 1.0;
                // A corner is its direction times the distance it was divided by.
                bin[1] +=
                    t.iter().zip(g).map(|(a, b)| (f64::from(*a) * true_distance - f64::from(*b) * guessed_distance).powi(2)).sum::<f64>();
                bin[2] += 1.0;
            }
            bin[3] += (guessed_distance / true_distance - 1.0).powi(2);
            bin[4] += 1.0;
        }
    }
    println!(
        "{:>8} {:>7} {:>16} {:>18} {:>13} {:>14} {:>15}",
        "to gate", "states", "corner angle (°)", "corner per axis (m)", "distance (%)", "on image (°)", "off image (°)"
    );
    let mut total = [0f64; 9];
    for ((_, name), s) in BINS.iter().zip(&sums) {
        total.iter_mut().zip(s).for_each(|(t, v)| *t += v);
        print_row(name, s);
    }
    print_row("all", &total);
}

/// One row of the table: states, RMS corner angle (°), RMS corner error per axis (m), RMS
/// relative distance error (%), RMS corner angle on the image and off it (°, with the share
/// of corners).
fn print_row(name: &str, s: &[f64; 9]) {
    let rms_degrees = |squares: f64, count: f64| (squares / count).sqrt().to_degrees();
    println!(
        "{name:>8} {:>7} {:>16.2} {:>18.3} {:>13.1} {:>7.2} ({:>3.0}%) {:>7.2} ({:>3.0}%)",
        s[4],
        rms_degrees(s[0], s[2]),
        (s[1] / (3.0 * s[2])).sqrt(),
        100.0 * (s[3] / s[4]).sqrt(),
        rms_degrees(s[5], s[6]),
        100.0 * s[6] / s[2],
        rms_degrees(s[7], s[8]),
        100.0 * s[8] / s[2],
    );
}
