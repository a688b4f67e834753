//! The direct ceiling of a vision student on a given CNN: a state-based teacher flies the test
//! set (SPEC §9: 40 tracks × 25 deployments) on the gates that CNN places — every step the
//! camera image is rendered, the CNN and its gate head (`gate_localisation`'s OUT and its `.head`)
//! predict the target and next gates' corners, and those replace the true corners in the
//! teacher's observation. `perception_noise` models a camera's errors as drifting noise; this
//! flies the errors a real CNN makes, correlated between corners and gates as they are.
//!
//! `cargo run --release -p runtime --example cnn_perception -- TEACHER STUDENT HEAD [PART] [SCALE …]`
//!
//! A gate's corners are replaced wherever the teacher's observation shows them (its
//! `gate_sight` decides, as in training), so the teacher acts on what it was trained to see,
//! only placed by the CNN. PART says which predictions replace the truth: `all` (default),
//! `directions` (to the corners; the distances stay true) or `distances` — which part of the
//! CNN's error costs the teacher most. Each SCALE `k` (default 1) flies the predictions
//! `truth + k · (CNN − truth)`: how much smaller this CNN's errors must get for the teacher to
//! fly a given score on them. Prints the test report's success and S_pw, exact and per scale.

#![allow(clippy::print_stdout, reason = "the table on stdout is what this analysis is for")]

use std::path::Path;
use std::sync::Arc;

use anyhow::{Context, bail};
use burn::module::Module;
use learner::checkpoint::read_policy;
use policy::gate_head::{GateHead, PER_GATE, gate_targets};
use policy::vision::VisionActorCritic;
use policy::{Device, Policy, PolicyController};
use sim::camera::IMAGE_PIXELS;
use sim::eval::{EvalConfig, evaluate};
use sim::nalgebra::Vector3;
use sim::quadrotor::BodyState;
use sim::{CameraPose, Controller, NEXT_CORNERS_RANGE, ObservationFrame, RaceEnv, TARGET_CORNERS_RANGE};

/// A CNN and its gate head, shared by every deployment.
struct Eyes {
    model: VisionActorCritic,
    head: GateHead,
    device: Device,
}

/// Which of the gate head's predictions replace the truth.
#[derive(Clone, Copy)]
enum Predicted {
    /// Directions to the corners and distances.
    All,
    /// Directions only; the distances are true.
    Directions,
    /// Distances only; the directions are true.
    Distances,
}

/// The teacher acting on the gates `eyes` place.
struct CnnPerception {
    teacher: Arc<Policy>,
    eyes: Arc<Eyes>,
    predicted: Predicted,
    /// Factor on the CNN's errors.
    scale: f32,
    image: Vec<u8>,
}

impl Controller for CnnPerception {
    fn reset(&mut self, _env: &RaceEnv) {}

    fn act(&mut self, env: &RaceEnv) -> [f32; 4] {
        let layout = self.teacher.observation_layout();
        let mut observation = env.observation_in(layout);
        CameraPose::of(env).render(env.track(), &mut self.image);
        let mut predicted = self.eyes.head.predict(&self.eyes.model, &self.image, &self.eyes.device);
        let body = env.body();
        let truth = gate_targets(env.track(), env.target_gate(), &body.position, &body.rotation());
        for (k, (p, t)) in predicted.iter_mut().zip(truth).enumerate() {
            let is_distance = k % PER_GATE == PER_GATE - 1;
            let replaced = match self.predicted {
                Predicted::All => true,
                Predicted::Directions => !is_distance,
                Predicted::Distances => is_distance,
            };
            *p = if replaced { t + self.scale * (*p - t) } else { t };
        }
        replace_gates(&mut observation, &predicted, body, layout.frame);
        let action = self.teacher.deterministic_actions(&observation);
        std::array::from_fn(|i| action[i])
    }
}

/// Writes the gate head's `predicted` corners (body-frame directions times the distance,
/// `policy::gate_head::gate_targets`) into `observation`'s δp1 and δp2, in `frame`, wherever
/// the observation shows a corner (non-zero).
fn replace_gates(observation: &mut [f32], predicted: &[f32], body: &BodyState, frame: ObservationFrame) {
    let body_to_frame = frame.rotation_from_world(body) * body.rotation();
    let corners = |gate: usize| -> [Vector3<f64>; 4] {
        let chunk = &predicted[gate * PER_GATE..(gate + 1) * PER_GATE];
        let distance = f64::from(chunk[PER_GATE - 1]).exp();
        std::array::from_fn(|c| body_to_frame * Vector3::from_fn(|k, _| f64::from(chunk[3 * c + k])) * distance)
    };
    let (target, next) = (corners(0), corners(1));
    for c in 0..4 {
        for (start, value) in [(TARGET_CORNERS_RANGE.start + 3 * c, target[c]), (NEXT_CORNERS_RANGE.start + 3 * c, next[c] - target[c])] {
            let slot = &mut observation[start..start + 3];
            if slot.iter().any(|v| *v != 0.0) {
                slot.iter_mut().zip(value.iter()).for_each(|(o, v)| *o = *v as f32);
            }
        }
    }
}

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let [teacher, student, head, rest @ ..] = args.as_slice() else {
        bail!("usage: cnn_perception TEACHER STUDENT HEAD [all|directions|distances] [SCALE …]");
    };
    let (predicted, scales) = match rest.split_first() {
        Some((part, scales)) if part.parse::<f32>().is_err() => {
            let predicted = match part.as_str() {
                "all" => Predicted::All,
                "directions" => Predicted::Directions,
                "distances" => Predicted::Distances,
                other => bail!("PART {other:?}: all, directions or distances"),
            };
            (predicted, scales)
        }
        _ => (Predicted::All, rest),
    };
    let scales: Vec<f32> = scales.iter().map(|s| s.parse().with_context(|| format!("SCALE {s:?}"))).collect::<anyhow::Result<_>>()?;
    let scales = if scales.is_empty() { vec![1.0] } else { scales };
    let teacher_blob = read_policy(Path::new(teacher)).with_context(|| format!("teacher {teacher}"))?;
    let student_blob = read_policy(Path::new(student)).with_context(|| format!("student {student}"))?;
    let device = Device::flex();
    let model = student_blob.vision_model(&device)?.valid();
    let head_bytes = std::fs::read(head).with_context(|| format!("gate head {head}"))?;
    let head = GateHead::from_bytes(&head_bytes, &device).map_err(anyhow::Error::msg).with_context(|| format!("gate head {head}"))?;
    let eyes = Arc::new(Eyes { model, head, device });
    let teacher = Arc::new(Policy::from_blob(&teacher_blob)?);
    let tracks: Vec<Arc<sim::Track>> = racetracks::test_set(racetracks::track_sets::TEST_SEED)?.into_iter().map(Arc::new).collect();
    let config = EvalConfig::default();
    println!("{:>12} {:>8} {:>8}", "error scale", "success", "S_pw");
    let exact_teacher = teacher.clone();
    let exact = evaluate("teacher", &tracks, &move || Box::new(PolicyController::new(exact_teacher.clone())), &config);
    println!("{:>12} {:>7.1} % {:>8.4}", "exact", 100.0 * exact.success_rate, exact.s_pw);
    for scale in scales {
        let (teacher, eyes) = (teacher.clone(), eyes.clone());
        let make = move || -> Box<dyn Controller> {
            Box::new(CnnPerception { teacher: teacher.clone(), eyes: eyes.clone(), predicted, scale, image: vec![0; IMAGE_PIXELS] })
        };
        let report = evaluate("teacher on the CNN", &tracks, &make, &config);
        println!("{scale:>12} {:>7.1} % {:>8.4}", 100.0 * report.success_rate, report.s_pw);
    }
    Ok(())
}
