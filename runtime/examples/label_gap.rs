//! How far a vision student is from its state-based teacher, and how much of the teacher's
//! label rests on its previous action, which SPEC §5's vision actor does not read.
//!
//! `cargo run --release -p runtime --example label_gap -- TEACHER STUDENT DISTILL_CONFIG [teacher|student]`
//!
//! 32 environments on the first 32 validation tracks (the distillation config's environment settings
//! with the teacher's observation layout)
//! fly 1,500 steps, by the teacher or by the student (deterministic actions). On every step it
//! compares the teacher's label with (a) the teacher's action when the previous-action slot of
//! its observation is zeroed, (b) when that slot holds another environment's previous action,
//! and (c) the student's action; mean squared error per action component, by distance from the
//! drone to the target gate's centre, and by whether the target gate's corners are in the
//! teacher's observation (with `gate_sight = "camera"`, only while the camera sees it). Half of (b) is the label's variance over previous actions
//! drawn from all flights: a rough upper estimate of what a student blind to the slot cannot fit.
//! Last, how far the label and the student's action each are from the previous action flown: a
//! student that copied its previous action (the copycat problem of behaviour cloning with
//! histories) would sit near it while the labels move away.

#![allow(clippy::print_stdout, reason = "the table on stdout is what this analysis is for")]

use std::path::Path;
use std::sync::Arc;

use anyhow::{Context, bail};
use learner::checkpoint::read_policy;
use policy::{Policy, VisionPolicy};
use runtime::distill::DistillConfig;
use sim::{ACTION_DIM, PREVIOUS_ACTION_RANGE, TARGET_CORNERS_RANGE, VecEnv};

#[path = "support/gate_errors.rs"]
mod gate_errors;
use gate_errors::{BINS, bin_of};

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let [teacher, student, config, rest @ ..] = args.as_slice() else {
        bail!("usage: label_gap TEACHER STUDENT DISTILL_CONFIG [teacher|student]");
    };
    let student_flies = match rest.first().map(String::as_str) {
        None | Some("teacher") => false,
        Some("student") => true,
        Some(other) => bail!("who flies: `teacher` or `student`, not {other:?}"),
    };
    let teacher_blob = read_policy(Path::new(teacher)).with_context(|| format!("teacher {teacher}"))?;
    let teacher = Policy::from_blob(&teacher_blob)?;
    let student = VisionPolicy::from_blob(&read_policy(Path::new(student)).with_context(|| format!("student {student}"))?)?;
    let frame_stack = student.frame_stack();
    let mut config = DistillConfig::read(Path::new(config))?;
    // The teacher reads what it was trained on, as in `distill`.
    config.env.set_observation_layout(teacher_blob.architecture.observation_layout());
    let tracks = racetracks::validation_set(32)?.into_iter().map(Arc::new).collect();
    let mut env = VecEnv::new(tracks, config.env, 7).with_frame_stack(frame_stack);
    let (n, dim) = (env.len(), env.observation_dim());
    // Per bin: summed squared errors of (zeroed, another's, student) and the count of states.
    let mut sums = [[0f64; 4]; BINS.len()];
    // The same, for states whose observation shows the target gate (0) or does not (1).
    let mut by_sight = [[0f64; 4]; 2];
    // How far the label and the student's action each are from the previous action flown.
    let (mut label_change, mut student_change, mut count) = (0f64, 0f64, 0f64);
    for _ in 0..1500 {
        let observations = env.observations.clone();
        let labels = teacher.deterministic_actions(&observations);
        let (mut zeroed, mut swapped) = (observations.clone(), observations.clone());
        for i in 0..n {
            let other = (i + 1) % n;
            for k in PREVIOUS_ACTION_RANGE {
                zeroed[i * dim + k] = 0.0;
                swapped[i * dim + k] = observations[other * dim + k];
            }
        }
        let compared = [
            teacher.deterministic_actions(&zeroed),
            teacher.deterministic_actions(&swapped),
            student.deterministic_actions(&env.images, &observations),
        ];
        for (i, e) in env.envs().iter().enumerate() {
            let distance = (e.body().position - e.track().gates[e.target_gate()].position).norm();
            let bin = bin_of(distance);
            let rows = i * ACTION_DIM..(i + 1) * ACTION_DIM;
            let hidden = observations[i * dim..(i + 1) * dim][TARGET_CORNERS_RANGE].iter().all(|v| *v == 0.0);
            for (k, actions) in compared.iter().enumerate() {
                let error = labels[rows.clone()].iter().zip(&actions[rows.clone()]).map(|(a, b)| f64::from(a - b).powi(2)).sum::<f64>()
                    / ACTION_DIM as f64;
                sums[bin][k] += error;
                by_sight[usize::from(hidden)][k] += error;
            }
            sums[bin][3] += 1.0;
            by_sight[usize::from(hidden)][3] += 1.0;
            for (k, previous) in PREVIOUS_ACTION_RANGE.enumerate() {
                let previous = f64::from(observations[i * dim + previous]);
                label_change += (f64::from(labels[i * ACTION_DIM + k]) - previous).powi(2);
                student_change += (f64::from(compared[2][i * ACTION_DIM + k]) - previous).powi(2);
                count += 1.0;
            }
        }
        let [_, _, student_actions] = compared;
        env.step(if student_flies { &student_actions } else { &labels });
    }
    println!("flown by the {}; mean squared difference from the teacher's label", if student_flies { "student" } else { "teacher" });
    println!("{:>8} {:>7} {:>14} {:>18} {:>9}", "to gate", "states", "slot zeroed", "another's slot", "student");
    let mut total = [0f64; 4];
    for ((_, name), s) in BINS.iter().zip(&sums) {
        total.iter_mut().zip(s).for_each(|(t, v)| *t += v);
        println!("{name:>8} {:>7} {:>14.4} {:>18.4} {:>9.4}", s[3], s[0] / s[3], s[1] / s[3], s[2] / s[3]);
    }
    println!("{:>8} {:>7} {:>14.4} {:>18.4} {:>9.4}", "all", total[3], total[0] / total[3], total[1] / total[3], total[2] / total[3]);
    for (name, s) in ["in view", "unseen"].iter().zip(&by_sight) {
        println!("{name:>8} {:>7} {:>14.4} {:>18.4} {:>9.4}", s[3], s[0] / s[3], s[1] / s[3], s[2] / s[3]);
    }
    println!(
        "mean squared difference from the previous action: teacher's label {:.4}, student's action {:.4}",
        label_change / count,
        student_change / count
    );
    Ok(())
}
