//! Bad bytes never panic. Every decoder of bytes that cross a process or a disk is fed
//! [`CASES`] mutated and truncated copies of a valid input:
//! - the checksummed formats (weights blob, rollout chunk with and without camera images,
//!   checkpoint, task-controller snapshot, distillation data set) must refuse every one with an
//!   error;
//! - the same formats with the checksum recomputed after mutating (so the parser behind it is
//!   reached; for the safetensors files, blob and checkpoint, their metadata values, tensor
//!   shapes and data are mutated and the file re-sealed), and the formats without one (track
//!   files, run configs, gRPC messages: rollout parts, reports to a task controller,
//!   `ActRequest`s to a served policy, `RaceStart`s and drone states to a served race), may
//!   accept a mutation that still means something, but must never panic.
//!
//! `cargo test --test decoders -- --nocapture` prints the counts (BENCHMARKS.md).

// Test code: a panic is how a failure is reported.
#![allow(clippy::unwrap_used, clippy::expect_used, clippy::print_stdout, clippy::print_stderr)]

use std::cell::Cell;
use std::panic::{AssertUnwindSafe, catch_unwind};
use std::path::Path;
use std::sync::Once;

use learner::Learner;
use learner::checkpoint::Checkpoint;
use policy::WeightsBlob;
use prost::Message;
use racetracks::TrackGenerator;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rollout::{EpisodeRecord, RolloutChunk};
use runtime::TrainConfig;
use taskctl::TaskController;

/// Mutated inputs per decoder and mode.
const CASES: usize = 100_000;

/// Values that make length and count fields lie.
const EXTREMES: [u64; 6] = [u64::MAX, u32::MAX as u64, i64::MAX as u64, 1 << 31, 1 << 40, 0];

thread_local! {
    /// Set while this thread feeds a decoder: its panics are counted, not printed.
    static FUZZING: Cell<bool> = const { Cell::new(false) };
    /// The message and place of the last panic on a fuzzing thread.
    static LAST_PANIC: std::cell::RefCell<String> = const { std::cell::RefCell::new(String::new()) };
}

/// Installs (once) a panic hook that stays quiet for fuzzing threads only, so a real test
/// failure elsewhere still prints its message.
fn quiet_while_fuzzing() {
    static INSTALL: Once = Once::new();
    INSTALL.call_once(|| {
        let default = std::panic::take_hook();
        std::panic::set_hook(Box::new(move |info| {
            if FUZZING.get() {
                LAST_PANIC.set(info.to_string());
            } else {
                default(info);
            }
        }));
    });
}

/// A copy of `valid` that differs from it: truncated, bytes overwritten, inserted or removed,
/// or a 4- or 8-byte field set to an extreme.
fn mutate(rng: &mut ChaCha8Rng, valid: &[u8]) -> Vec<u8> {
    loop {
        let mut b = valid.to_vec();
        match rng.random_range(0..5) {
            0 => b.truncate(rng.random_range(0..valid.len())),
            1 => {
                for _ in 0..rng.random_range(1..=8) {
                    let i = rng.random_range(0..b.len());
                    b[i] = rng.random();
                }
            }
            2 => {
                let at = rng.random_range(0..=b.len());
                let extra: Vec<u8> = (0..rng.random_range(1..=16)).map(|_| rng.random()).collect();
                b.splice(at..at, extra);
            }
            3 => {
                let at = rng.random_range(0..b.len());
                let end = (at + rng.random_range(1..=16)).min(b.len());
                b.drain(at..end);
            }
            _ => {
                let width = if rng.random_bool(0.5) { 4 } else { 8 };
                if b.len() >= width {
                    let at = rng.random_range(0..=b.len() - width);
                    let value = EXTREMES[rng.random_range(0..EXTREMES.len())].to_le_bytes();
                    b[at..at + width].copy_from_slice(&value[..width]);
                }
            }
        }
        if b != valid {
            return b;
        }
    }
}

/// Rewrites a frame's (`frames`) length field and trailing CRC-32 to match the mutated bytes,
/// so the parser of the body is reached.
fn reframe(mut b: Vec<u8>) -> Vec<u8> {
    if b.len() >= frames::OVERHEAD {
        let body = (b.len() - frames::OVERHEAD) as u64;
        b[12..20].copy_from_slice(&body.to_le_bytes());
        let end = b.len() - 4;
        let crc = crc32fast::hash(&b[..end]);
        b[end..].copy_from_slice(&crc.to_le_bytes());
    }
    b
}

/// A mutation behind the checksum of a safetensors file of ours: the valid file the mutated
/// bytes came from (`VALID_FILE`) with one metadata value, tensor shape or tensor's data
/// replaced by bytes taken from the mutation, then written out (and so sealed) again.
fn reseal(mutated: Vec<u8>) -> Vec<u8> {
    use policyfile::safetensors::TensorData;
    let Some(mut file) = VALID_FILE.with_borrow(Clone::clone) else { return mutated };
    let mut rng = ChaCha8Rng::seed_from_u64(crc32fast::hash(&mutated).into());
    let junk = |rng: &mut ChaCha8Rng| {
        let start = rng.random_range(0..=mutated.len());
        let end = (start + rng.random_range(0..24)).min(mutated.len());
        String::from_utf8_lossy(&mutated[start..end]).into_owned()
    };
    let keys: Vec<String> = file.metadata.keys().cloned().collect();
    let names: Vec<String> = file.tensors.keys().cloned().collect();
    match rng.random_range(0..4) {
        0 => {
            let key = &keys[rng.random_range(0..keys.len())];
            let value = file.metadata.get_mut(key).unwrap();
            let at = rng.random_range(0..=value.len());
            let at = (0..=at).rev().find(|&i| value.is_char_boundary(i)).unwrap_or(0);
            if rng.random_bool(0.5) { value.truncate(at) } else { value.insert_str(at, &junk(&mut rng)) }
        }
        1 => {
            let tensor = file.tensors.get_mut(&names[rng.random_range(0..names.len())]).unwrap();
            let len = match &tensor.data {
                TensorData::F32(v) => v.len(),
                TensorData::F64(v) => v.len(),
                TensorData::U8(v) => v.len(),
            };
            // A shape that still matches the data (else the file would not be written consistently).
            tensor.shape = if len > 1 && rng.random_bool(0.5) { vec![1, len] } else { vec![len] };
        }
        2 => {
            let tensor = file.tensors.get_mut(&names[rng.random_range(0..names.len())]).unwrap();
            let keep = rng.random_range(0..4);
            match &mut tensor.data {
                TensorData::F32(v) => v.truncate(keep),
                TensorData::F64(v) => v.truncate(keep),
                TensorData::U8(v) => v.truncate(keep),
            }
            tensor.shape = vec![keep.min(tensor.shape.iter().product())];
        }
        _ => {
            if rng.random_bool(0.5) {
                file.metadata.remove(&keys[rng.random_range(0..keys.len())]);
            } else {
                file.tensors.remove(&names[rng.random_range(0..names.len())]);
            }
        }
    }
    file.to_bytes()
}

thread_local! {
    /// The valid safetensors file [`reseal`] mutates.
    static VALID_FILE: std::cell::RefCell<Option<policyfile::safetensors::TensorFile>> = const { std::cell::RefCell::new(None) };
}

/// What one decoder made of the mutated inputs.
#[derive(Debug, Default)]
struct Tally {
    refused: usize,
    accepted: usize,
}

/// Feeds `decode` `CASES` mutations of `valid` (passed through `fix` first); `decode` returns
/// whether it accepted. Panics, naming the decoder and the first input that made it panic.
fn fuzz(name: &str, seed: u64, valid: &[u8], fix: impl Fn(Vec<u8>) -> Vec<u8>, decode: impl Fn(&[u8]) -> bool) -> Tally {
    assert!(decode(valid), "{name}: the valid input must decode");
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut tally = Tally::default();
    quiet_while_fuzzing();
    FUZZING.set(true);
    let mut panicked = None;
    for case in 0..CASES {
        let input = fix(mutate(&mut rng, valid));
        match catch_unwind(AssertUnwindSafe(|| decode(&input))) {
            Ok(true) => tally.accepted += 1,
            Ok(false) => tally.refused += 1,
            Err(_) if panicked.is_none() => panicked = Some((case, input, LAST_PANIC.take())),
            Err(_) => {}
        }
    }
    FUZZING.set(false);
    if let Some((case, input, message)) = panicked {
        let shown: Vec<String> = input.iter().take(96).map(|b| format!("{b:02x}")).collect();
        panic!("{name}: mutation {case} ({} bytes) panicked the decoder ({message}); first bytes {}", input.len(), shown.join(""));
    }
    eprintln!("{name}: {CASES} mutated inputs, {} refused, {} accepted, 0 panics", tally.refused, tally.accepted);
    tally
}

fn tiny_learner() -> Learner {
    let config = TrainConfig { hidden: Some(vec![8]), envs: Some(2), ..TrainConfig::default() };
    config.resolve().unwrap().initial_learner().unwrap()
}

fn chunk() -> RolloutChunk {
    let (envs, steps) = (2, 3);
    let mut c = RolloutChunk::zeroed(4, 1, envs, steps, sim::STATE_OBS_DIM, sim::ACTION_DIM);
    c.observations.iter_mut().enumerate().for_each(|(i, x)| *x = i as f32 * 0.01);
    c.terminated[2] = true;
    c.episodes.push(EpisodeRecord { env: 1, episode_return: 2.5, length: 40, laps: 1, fastest_lap: Some(3.5), crashed: true });
    c
}

#[test]
fn every_mutated_weights_blob_is_refused_and_none_panics_the_parser() {
    let valid = tiny_learner().weights().to_bytes();
    VALID_FILE.set(Some(policyfile::safetensors::TensorFile::from_bytes(&valid).unwrap()));
    let decode = |b: &[u8]| WeightsBlob::from_bytes(b).is_ok();
    let raw = fuzz("weights blob", 1, &valid, |b| b, decode);
    assert_eq!(raw.accepted, 0);
    fuzz("weights blob, checksum recomputed", 2, &valid, reseal, decode);
}

/// What the learner of the fuzzed rollouts admits: 8 environments of 3-step rollouts.
const LIMITS: rollout::ChunkLimits =
    rollout::ChunkLimits { observation_dim: sim::STATE_OBS_DIM, action_dim: sim::ACTION_DIM, max_envs: 8, max_steps: 3, images: false };

#[test]
fn every_mutated_rollout_chunk_is_refused_and_none_panics_the_parser() {
    let valid = chunk().to_bytes();
    let decode = |b: &[u8]| RolloutChunk::from_bytes(b, &LIMITS).is_ok_and(|c| c.check(sim::STATE_OBS_DIM, sim::ACTION_DIM, false).is_ok());
    let raw = fuzz("rollout chunk", 3, &valid, |b| b, decode);
    assert_eq!(raw.accepted, 0);
    assert!(decode(&reframe(valid.clone())), "the rewritten frame matches the format");
    fuzz("rollout chunk, checksum recomputed", 4, &valid, reframe, decode);
}

#[test]
fn every_mutated_rollout_with_camera_images_is_refused_and_none_panics_the_parser() {
    // A vision rollout: its images carry a gate bar each, so the image code has many runs.
    let mut c = chunk();
    c.images = vec![0; c.transitions() * sim::camera::IMAGE_PIXELS];
    for (i, image) in c.images.chunks_mut(sim::camera::IMAGE_PIXELS).enumerate() {
        image[300 + 7 * i..380 + 7 * i].fill(155);
    }
    let vision = rollout::ChunkLimits { images: true, ..LIMITS };
    let valid = c.to_bytes();
    let decode = |b: &[u8]| RolloutChunk::from_bytes(b, &vision).is_ok_and(|c| c.check(sim::STATE_OBS_DIM, sim::ACTION_DIM, true).is_ok());
    let raw = fuzz("rollout chunk with images", 12, &valid, |b| b, decode);
    assert_eq!(raw.accepted, 0);
    fuzz("rollout chunk with images, checksum recomputed", 13, &valid, reframe, decode);
}

#[test]
fn every_mutated_distillation_data_set_is_refused_and_none_panics_the_parser() {
    use distill::DistillDataset;
    let track = std::sync::Arc::new(racetracks::library_track("Figure8").unwrap().unwrap());
    let mut env = sim::RaceEnv::new(track, sim::EnvConfig::default(), 1, 0);
    let mut data = DistillDataset::new(8, sim::STATE_OBS_DIM);
    let mut rng = ChaCha8Rng::seed_from_u64(0);
    for i in 0..8 {
        env.step(&[0.3, 0.0, 0.1, 0.0]);
        data.offer(&env, &[i as f32 * 0.1; sim::STATE_OBS_DIM], &[0.1, 0.2, 0.3, 0.4], &mut rng);
    }
    let valid = data.to_bytes();
    let decode = |b: &[u8]| DistillDataset::from_bytes(b).is_ok();
    let raw = fuzz("distillation data set", 14, &valid, |b| b, decode);
    assert_eq!(raw.accepted, 0);
    fuzz("distillation data set, checksum recomputed", 15, &valid, reframe, decode);
}

#[test]
fn no_mutated_run_config_panics_its_checks() {
    let text = "name = \"generalist\"\nprofile = \"cpu\"\nseed = 3\nenvs = 96\nhidden = [256, 256]\n\n[ppo]\ngamma = 0.998\nlearning_rate_start = 3e-4\nn_steps = 250\n\n[switching]\nwindow = 600\nalpha = 1000.0\n\n[learner]\nactor_timeout_seconds = 30.0\nrollout_memory_mib = 512\n";
    fuzz(
        "run config",
        16,
        text.as_bytes(),
        |b| b,
        |b| std::str::from_utf8(b).ok().and_then(|t| TrainConfig::from_toml(t).ok()).is_some_and(|c| c.resolve().is_ok()),
    );
}

#[test]
fn no_mutated_act_request_panics_the_served_policy() {
    use serving::Pilot;
    let blob = tiny_learner().weights();
    let pilot = serving::PolicyPilot::new(std::sync::Arc::new(policy::Policy::from_blob(&blob).unwrap()));
    let valid = proto::v1::ActRequest { observation: vec![0.25; blob.architecture.observation_dim] }.encode_to_vec();
    fuzz(
        "gRPC ActRequest",
        17,
        &valid,
        |b| b,
        |b| {
            let Ok(request) = proto::v1::ActRequest::decode(b) else { return false };
            pilot.act(&request.observation).is_ok_and(|action| action.iter().all(|a| a.is_finite()))
        },
    );
}

#[test]
fn every_mutated_checkpoint_is_refused_and_none_panics_the_restore() {
    let valid = tiny_learner().checkpoint().to_bytes();
    VALID_FILE.set(Some(policyfile::safetensors::TensorFile::from_bytes(&valid).unwrap()));
    let origin = Path::new("fuzzed.bin");
    let raw = fuzz("checkpoint", 5, &valid, |b| b, |b| Checkpoint::from_bytes(b, origin).is_ok());
    assert_eq!(raw.accepted, 0);
    // Past the checksum, the restore decodes every section (weights, optimiser, counters).
    fuzz("checkpoint, checksum recomputed", 6, &valid, reseal, |b| {
        Checkpoint::from_bytes(b, origin).is_ok_and(|c| Learner::from_checkpoint(&c).is_ok())
    });
}

#[test]
fn every_mutated_task_controller_snapshot_is_refused_and_none_panics_the_parser() {
    let controller = TaskController::new(3, TrackGenerator::default(), Default::default(), 7).unwrap();
    let valid = controller.to_snapshot_bytes();
    let origin = Path::new("taskctl.snapshot");
    let decode = |b: &[u8]| TaskController::from_snapshot_bytes(b, origin).is_ok();
    let raw = fuzz("task-controller snapshot", 7, &valid, |b| b, decode);
    assert_eq!(raw.accepted, 0);
    assert!(decode(&reframe(valid.clone())), "the rewritten frame matches the format");
    fuzz("task-controller snapshot, checksum recomputed", 8, &valid, reframe, decode);
}

#[test]
fn no_mutated_track_file_panics_the_parser() {
    let track = racetracks::library_track("BigS").unwrap().unwrap();
    let valid = racetracks::track_to_toml(&track).into_bytes();
    let file = Path::new("fuzzed.toml");
    fuzz("track file", 9, &valid, |b| b, |b| std::str::from_utf8(b).is_ok_and(|text| racetracks::parse_track(text, file).is_ok()));
}

#[test]
fn no_mutated_grpc_message_panics_its_decoders() {
    use proto::v1;
    // A rollout part: protobuf, then reassembly, then the chunk format, then admission.
    let admission = transport::Admission {
        learner_epoch: 1,
        version: 4,
        max_policy_lag: 2,
        observation_dim: sim::STATE_OBS_DIM,
        action_dim: sim::ACTION_DIM,
        images: false,
        total_envs: 8,
        rollout_steps: 3,
    };
    let part = v1::RolloutPart {
        actor: "actor-0".into(),
        learner_epoch: 1,
        policy_version: 4,
        part: 0,
        parts: 1,
        data: chunk().to_bytes().into(),
    };
    let valid = part.encode_to_vec();
    fuzz(
        "gRPC RolloutPart",
        10,
        &valid,
        |b| b,
        |b| {
            let Ok(p) = v1::RolloutPart::decode(b) else { return false };
            let Ok(Some(payload)) = transport::chunking::Reassembler::default().push(p.part, p.parts, &p.data) else { return false };
            RolloutChunk::from_bytes(&payload, &admission.limits()).is_ok_and(|c| admission.check(&p.actor, p.learner_epoch, &c).is_ok())
        },
    );
    // Reports go on to a task controller where actor-0 holds three environments: a mutated
    // rollout index (2^64 − 1 froze a curriculum) or name is refused, never a panic.
    let tasks = taskctl::LocalTasks::new(TaskController::new(3, TrackGenerator::default(), Default::default(), 7).unwrap(), None);
    taskctl::TaskService::register(&tasks, "actor-0", 3).unwrap();
    let report = v1::ReportRequest { actor: "actor-0".into(), rollout: 9, cumulative_rewards: vec![1.5, -2.0, 0.25] };
    fuzz(
        "gRPC ReportRequest → the task controller",
        11,
        &report.encode_to_vec(),
        |b| b,
        |b| {
            let Ok(r) = v1::ReportRequest::decode(b) else { return false };
            transport::link::check_actor_name(&r.actor).is_ok()
                && taskctl::TaskService::report(&tasks, &r.actor, r.rollout, &r.cumulative_rewards).is_ok()
        },
    );
}

#[test]
fn no_mutated_race_request_panics_the_served_race() {
    use proto::v1::race_request::Kind;
    use serving::{DroneState, Pilot};
    let blob = tiny_learner().weights();
    let pilot = serving::PolicyPilot::new(std::sync::Arc::new(policy::Policy::from_blob(&blob).unwrap()));
    let track = racetracks::track_to_toml(&racetracks::library_track("Figure8").unwrap().unwrap());
    let start = proto::v1::RaceRequest { kind: Some(Kind::Start(proto::v1::RaceStart { track_toml: track.clone() })) };
    fuzz(
        "gRPC RaceStart → the pilot",
        18,
        &start.encode_to_vec(),
        |b| b,
        |b| {
            let Ok(proto::v1::RaceRequest { kind: Some(Kind::Start(s)) }) = proto::v1::RaceRequest::decode(b) else { return false };
            pilot.start_race(&s.track_toml).is_ok()
        },
    );
    let state = proto::v1::DroneState {
        position: vec![-2.0, 0.5, 2.0],
        velocity: vec![1.0, 0.0, 0.0],
        orientation: vec![1.0, 0.0, 0.0, 0.0],
        angular_velocity: vec![0.0, 0.1, 0.0],
    };
    let state = proto::v1::RaceRequest { kind: Some(Kind::State(state)) };
    let racer = std::cell::RefCell::new(pilot.start_race(&track).unwrap());
    fuzz(
        "gRPC DroneState → the race (a finite command or a refusal)",
        19,
        &state.encode_to_vec(),
        |b| b,
        |b| {
            let Ok(proto::v1::RaceRequest { kind: Some(Kind::State(s)) }) = proto::v1::RaceRequest::decode(b) else { return false };
            let state = DroneState {
                position: &s.position,
                velocity: &s.velocity,
                orientation: &s.orientation,
                angular_velocity: &s.angular_velocity,
            };
            pilot.race_step(&mut racer.borrow_mut(), state).is_ok_and(|c| c.action.iter().all(|a| a.is_finite()))
        },
    );
}
