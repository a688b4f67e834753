//! Distillation end to end: an interrupted DAgger run resumes bit for bit, the teacher's share
//! of the flying follows β = decay^round, teachers with longer observations teach in their own
//! layout, and the command refuses a teacher that cannot teach.

// Test code: a panic is how a failure is reported.
#![allow(clippy::unwrap_used, clippy::expect_used, clippy::print_stdout, clippy::print_stderr)]

use std::path::{Path, PathBuf};
use std::process::Command;

use policy::WeightsBlob;
use runtime::EvalSettings;
use runtime::distill::{DistillConfig, Distiller};

/// The shipped generalist: a real teacher, so the student sees real flights.
fn teacher() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("policies/generalist.bin")
}

fn tiny_config() -> DistillConfig {
    let mut config = DistillConfig {
        teacher: teacher(),
        seed: 5,
        envs: 4,
        steps_per_round: 16,
        rounds: 4,
        teacher_decay: 0.5,
        updates_per_round: 2,
        minibatch: 16,
        checkpoint_every: 2,
        eval: EvalSettings { every: 2, tracks: 1, runs: 1, steps: 100, ..EvalSettings::default() },
        ..DistillConfig::default()
    };
    config.switching.window = 2;
    config
}

/// The student's bytes with burn's process-unique parameter ids blanked.
fn student(d: &Distiller) -> Vec<u8> {
    let mut blob: WeightsBlob = d.student();
    blob.params.iter_mut().for_each(|p| p.id = 0);
    blob.to_bytes()
}

#[test]
fn an_interrupted_distillation_resumes_bit_for_bit() {
    let dir = tempfile::tempdir().unwrap();
    let (straight, resumed) = (dir.path().join("straight"), dir.path().join("resumed"));
    std::fs::create_dir_all(&straight).unwrap();
    std::fs::create_dir_all(&resumed).unwrap();

    // With a gate head, whose weights and moments the checkpoint must carry too, and stacked
    // camera frames, whose histories it must carry.
    let stack = sim::FrameStack { frames: 2, stride: 3 };
    let config = || DistillConfig { gate_loss_weight: 0.5, frame_stack: stack, ..tiny_config() };
    let mut a = Distiller::start(config(), &straight).unwrap();
    let shares: Vec<f64> = (0..4).map(|_| a.round_step().unwrap().teacher_share).collect();
    // β = 0.5^round of 64 steps per round: all of round 0, then about half, a quarter, an eighth.
    assert_eq!(shares[0], 1.0);
    assert!(shares[1] > 0.25 && shares[1] < 0.75 && shares[3] < shares[1], "{shares:?}");

    let mut b = Distiller::start(config(), &resumed).unwrap();
    b.round_step().unwrap();
    b.round_step().unwrap(); // the checkpoint of round 2 is written here
    let before = student(&b);
    drop(b); // the process "dies"
    let mut b = Distiller::resume(&resumed).unwrap();
    assert_eq!(b.round(), 2);
    assert!(student(&b) == before, "the checkpoint restores the student bit for bit");
    b.round_step().unwrap();
    let last = b.round_step().unwrap();
    assert_eq!(last.samples_seen, 4 * 4 * 16);
    assert!(last.gate_loss.is_finite(), "the gate head's loss is reported");
    let err = Distiller::start(DistillConfig { gate_loss_weight: -1.0, ..tiny_config() }, &dir.path().join("negative")).err().unwrap();
    assert!(format!("{err:#}").contains("gate_loss_weight"), "{err:#}");
    assert!(student(&b) == student(&a), "data set, environments, curriculum and optimiser continue exactly");
    assert!(b.finished());
    // A row per round in metrics.csv, and the validated student kept as best.bin.
    let rows = std::fs::read_to_string(resumed.join("metrics.csv")).unwrap().lines().count();
    assert_eq!(rows, 1 + 4);
    let best = learner::checkpoint::read_policy(&resumed.join("checkpoints/best.bin")).unwrap();
    assert_eq!((best.architecture.agent, best.architecture.frame_stack), (policy::Agent::Vision, stack));
}

#[test]
fn a_frozen_encoder_keeps_the_starts_cnn_through_rounds_and_a_resume() {
    let dir = tempfile::tempdir().unwrap();
    let start = dir.path().join("start.bin");
    std::fs::write(&start, Distiller::start(tiny_config(), &dir.path().join("first")).unwrap().student().to_bytes()).unwrap();
    let config = || DistillConfig { frozen_encoder: true, init_from: Some(start.clone()), ..tiny_config() };
    let run = dir.path().join("frozen");
    let mut d = Distiller::start(config(), &run).unwrap();
    d.round_step().unwrap();
    d.round_step().unwrap(); // the checkpoint of round 2 is written here
    drop(d);
    let mut d = Distiller::resume(&run).unwrap();
    d.round_step().unwrap();
    // The convolutions and the embedding layer (the first 8 parameters) are the start's; the actor learned.
    let values = |blob: &WeightsBlob| blob.params.iter().map(|p| p.values.clone()).collect::<Vec<_>>();
    let (before, after) = (values(&WeightsBlob::from_bytes(&std::fs::read(&start).unwrap()).unwrap()), values(&d.student()));
    assert_eq!(after[..8], before[..8]);
    assert_ne!(after[8..14], before[8..14]);
    let err = Distiller::start(DistillConfig { frozen_encoder: true, ..tiny_config() }, &dir.path().join("no-start")).err().unwrap();
    assert!(format!("{err:#}").contains("frozen_encoder"), "{err:#}");
}

#[test]
fn takeover_hands_the_steps_a_student_strays_on_back_to_the_teacher() {
    // β = 0 from round 1 on: without intervention the student flies every step.
    let share_after_round_0 = |takeover: Option<f64>| {
        let dir = tempfile::tempdir().unwrap();
        let mut d = Distiller::start(DistillConfig { teacher_decay: 0.0, takeover, ..tiny_config() }, dir.path()).unwrap();
        d.round_step().unwrap();
        d.round_step().unwrap().teacher_share
    };
    assert_eq!(share_after_round_0(None), 0.0);
    // A fresh student's actions are nowhere near the teacher's: any strictness takes every step.
    assert_eq!(share_after_round_0(Some(0.0)), 1.0);
    // Actions lie in [−1, 1], so no two differ by more than 2: the student keeps every step.
    assert_eq!(share_after_round_0(Some(2.0)), 0.0);
    let share = share_after_round_0(Some(0.05));
    assert!(share > 0.0 && share <= 1.0, "{share}");
}

#[test]
fn a_crash_margin_drops_the_run_up_to_each_crash_and_nothing_else() {
    // A fresh student flies from round 1 on and crashes within seconds.
    let config = |crash_margin| DistillConfig { teacher_decay: 0.0, steps_per_round: 100, crash_margin, ..tiny_config() };
    let rounds = |crash_margin| {
        let dir = tempfile::tempdir().unwrap();
        let mut d = Distiller::start(config(crash_margin), dir.path()).unwrap();
        (0..2).map(|_| d.round_step().unwrap()).collect::<Vec<_>>()
    };
    let (plain, margin) = (rounds(0), rounds(10));
    let mut dropped = 0;
    for (p, m) in plain.iter().zip(&margin) {
        assert_eq!(p.dropped, 0);
        let crashes =
            |r: &runtime::distill::RoundSummary| if r.episodes == 0 { 0 } else { (r.crash_rate * r.episodes as f64).round() as usize };
        assert_eq!((p.episodes, crashes(p)), (m.episodes, crashes(m)), "holding states back does not change the flights");
        let crashes = crashes(m);
        // Each crash drops its own step's state and at most the nine before it.
        assert!(m.dropped >= crashes && m.dropped <= 10 * crashes, "{} dropped for {crashes} crashes", m.dropped);
        dropped += m.dropped as u64;
        assert_eq!(m.samples_seen + dropped, p.samples_seen, "every other state is offered");
    }
    assert!(dropped > 0, "the fresh student crashed: {margin:?}");
}

#[test]
fn a_state_student_of_the_pilot_resumes_bit_for_bit_with_its_pilots_mid_flight() {
    let config = || DistillConfig {
        teacher: runtime::distill::PILOT_TEACHER.into(),
        student: policy::Agent::State,
        hidden: Some(vec![16, 16]),
        envs: 3,
        ..tiny_config()
    };
    let dir = tempfile::tempdir().unwrap();
    let (straight, resumed) = (dir.path().join("straight"), dir.path().join("resumed"));
    let mut a = Distiller::start(config(), &straight).unwrap();
    for _ in 0..4 {
        a.round_step().unwrap();
    }
    let mut b = Distiller::start(config(), &resumed).unwrap();
    b.round_step().unwrap();
    b.round_step().unwrap(); // checkpoint of round 2, every pilot somewhere in an episode
    drop(b);
    let mut b = Distiller::resume(&resumed).unwrap();
    b.round_step().unwrap();
    b.round_step().unwrap();
    assert!(student(&b) == student(&a), "recalled pilots label exactly as the remembered ones");
    let blob = b.student();
    assert_eq!((blob.architecture.agent, blob.architecture.hidden.clone()), (policy::Agent::State, vec![16, 16]));
    // Its normaliser learnt from the 3 × 4 × 16 states flown (no teacher to take one from).
    assert_eq!(blob.normalizer.count, (3 * 4 * 16) as f64 + policy::ObsNormalizer::new(40).count);
}

#[test]
fn teachers_that_observe_racing_line_points_teach_in_their_own_layout() {
    // The pilot teaches a state student that sees 4 line points (40 + 4 × 3 numbers)…
    let mut config = DistillConfig {
        teacher: runtime::distill::PILOT_TEACHER.into(),
        student: policy::Agent::State,
        hidden: Some(vec![16, 16]),
        rounds: 2,
        ..tiny_config()
    };
    config.env.observation.line_points = 4;
    let dir = tempfile::tempdir().unwrap();
    let mut d = Distiller::start(config, &dir.path().join("state")).unwrap();
    d.round_step().unwrap();
    d.round_step().unwrap();
    let teacher = d.student();
    assert_eq!((teacher.architecture.observation.line_points, teacher.architecture.observation_dim), (4, 52));
    let teacher_file = dir.path().join("line-teacher.bin");
    std::fs::write(&teacher_file, teacher.to_bytes()).unwrap();
    // …which teaches a vision student: its environments and data set take the teacher's layout
    // (not the distillation config's default), its critic reads all 52 numbers, and it resumes.
    let config = DistillConfig { teacher: teacher_file, ..tiny_config() };
    assert_eq!(config.env.observation.line_points, 0);
    let vision_dir = dir.path().join("vision");
    let mut v = Distiller::start(config, &vision_dir).unwrap();
    v.round_step().unwrap();
    v.round_step().unwrap();
    let blob = v.student();
    assert_eq!((blob.architecture.agent, blob.architecture.observation_dim), (policy::Agent::Vision, 52));
    assert_eq!(blob.architecture.observation, teacher.architecture.observation);
    let before = student(&v);
    drop(v);
    let mut v = Distiller::resume(&vision_dir).unwrap();
    assert!(student(&v) == before);
    v.round_step().unwrap();
    let written = DistillConfig::read(&vision_dir.join("config.toml")).unwrap();
    assert_eq!(written.env.observation.line_points, 4, "the run's config records the layout it flew");
}

/// A two-round run in `dir/earlier`, its checkpoint written (what `dataset_from` reads: a run's
/// newest checkpoint); the run and its last round.
fn earlier_run(dir: &Path) -> (PathBuf, Distiller, runtime::distill::RoundSummary) {
    let earlier = dir.join("earlier");
    let mut a = Distiller::start(DistillConfig { rounds: 2, ..tiny_config() }, &earlier).unwrap();
    a.round_step().unwrap();
    let last = a.round_step().unwrap();
    a.checkpoint().unwrap();
    (earlier, a, last)
}

#[test]
fn a_student_that_reads_its_previous_action_continues_an_earlier_runs_data_set() {
    let dir = tempfile::tempdir().unwrap();
    let (earlier, a, held) = earlier_run(dir.path());
    let start = dir.path().join("earlier-student.bin");
    std::fs::write(&start, a.student().to_bytes()).unwrap();

    let config =
        || DistillConfig { init_from: Some(start.clone()), dataset_from: Some(earlier.clone()), previous_action: true, ..tiny_config() };
    let later = dir.path().join("later");
    let mut b = Distiller::start(config(), &later).unwrap();
    assert!(b.student().architecture.vision_previous_action, "the start is widened to read the previous action");
    let first = b.round_step().unwrap();
    assert_eq!(first.samples_seen, held.samples_seen + 4 * 16, "the earlier run's samples, then this round's");
    assert_eq!(first.dataset, held.dataset + 4 * 16);
    b.round_step().unwrap();
    drop(b);
    let b = Distiller::resume(&later).unwrap();
    assert!(b.student().architecture.vision_previous_action, "and resumes as it was");

    // Labels of another teacher are refused, naming the run; so is a state student reading more.
    let other_teacher = Path::new(env!("CARGO_MANIFEST_DIR")).join("policies/camera-teacher.bin");
    let err = Distiller::start(DistillConfig { teacher: other_teacher, ..config() }, &dir.path().join("other")).err().unwrap();
    let err = format!("{err:#}");
    assert!(err.contains("dataset_from") && err.contains("earlier") && err.contains("another teacher"), "{err}");
    let err = Distiller::start(DistillConfig { student: policy::Agent::State, init_from: None, ..config() }, &dir.path().join("state"))
        .err()
        .unwrap();
    assert!(format!("{err:#}").contains("previous_action"), "{err:#}");

    // A student seeing stacked frames starts from the single-frame one, but cannot learn from
    // samples that hold one frame.
    let stack = sim::FrameStack { frames: 3, stride: 4 };
    let err = Distiller::start(DistillConfig { frame_stack: stack, ..config() }, &dir.path().join("stacked")).err().unwrap();
    assert!(format!("{err:#}").contains("camera frames"), "{err:#}");
    let stacked =
        Distiller::start(DistillConfig { frame_stack: stack, dataset_from: None, ..config() }, &dir.path().join("stacked-new")).unwrap();
    assert_eq!(stacked.student().architecture.frame_stack, stack, "the single-frame start is widened");
}

#[test]
fn a_new_teacher_relabels_an_earlier_runs_states_of_its_own_layout_only() {
    let dir = tempfile::tempdir().unwrap();
    let (earlier, _, _) = earlier_run(dir.path());
    // Another teacher of the same layout: the generalist with its action head halved.
    let mut other = learner::checkpoint::read_policy(&teacher()).unwrap();
    let names = policy::WeightsBlob::tensor_names(&other.architecture);
    let head = names.iter().position(|n| *n == format!("actor.{}.weight", other.architecture.hidden.len())).unwrap();
    other.params[head].values.iter_mut().for_each(|v| *v *= 0.5);
    let other_file = dir.path().join("other-teacher.bin");
    std::fs::write(&other_file, other.to_bytes()).unwrap();
    let config = |teacher: PathBuf, relabel| DistillConfig { teacher, dataset_from: Some(earlier.clone()), relabel, ..tiny_config() };

    let err = Distiller::start(config(other_file.clone(), false), &dir.path().join("kept")).err().unwrap();
    assert!(format!("{err:#}").contains("another teacher"), "{err:#}");
    let later = dir.path().join("later");
    let mut b = Distiller::start(config(other_file, true), &later).unwrap();
    let path = b.checkpoint().unwrap();
    let checkpoint = learner::checkpoint::Checkpoint::read(&path).unwrap();
    let data = learner::distill::DistillDataset::from_bytes(checkpoint.get("dataset").unwrap()).unwrap();
    let rows: Vec<usize> = (0..data.len()).collect();
    assert_eq!(data.len(), 4 * 16 * 2);
    let expected = policy::Policy::from_blob(&other).unwrap().deterministic_actions(&data.states(&rows));
    assert_eq!(data.labels(&rows), expected, "every state carries the new teacher's label");
    let original = policy::Policy::from_blob(&learner::checkpoint::read_policy(&teacher()).unwrap()).unwrap();
    assert_ne!(data.labels(&rows), original.deterministic_actions(&data.states(&rows)));

    // A teacher that observes other things in the same 40 numbers (the camera-sight teacher) may not.
    let camera = Path::new(env!("CARGO_MANIFEST_DIR")).join("policies/camera-teacher.bin");
    let err = Distiller::start(config(camera, true), &dir.path().join("camera")).err().unwrap();
    assert!(format!("{err:#}").contains("observation layout"), "{err:#}");
    // Nor is relabel meaningful without an earlier data set.
    let err = Distiller::start(DistillConfig { relabel: true, ..tiny_config() }, &dir.path().join("alone")).err().unwrap();
    assert!(format!("{err:#}").contains("relabel"), "{err:#}");
}

fn dronerace(args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_dronerace")).args(args).output().expect("run dronerace")
}

#[test]
fn the_command_refuses_a_teacher_that_cannot_teach() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("run");
    // No teacher at all.
    let o = dronerace(&["distill", "--out", out.to_str().unwrap()]);
    assert!(!o.status.success());
    assert!(String::from_utf8_lossy(&o.stderr).contains("--teacher"), "{}", String::from_utf8_lossy(&o.stderr));
    // A vision policy cannot label states: the error names the file and why.
    let vision = dir.path().join("vision.bin");
    let student = Distiller::start(tiny_config(), &dir.path().join("first")).unwrap().student();
    std::fs::write(&vision, student.to_bytes()).unwrap();
    let o = dronerace(&["distill", "--teacher", vision.to_str().unwrap(), "--out", out.to_str().unwrap()]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && err.contains("vision.bin") && err.contains("state-based"), "{err}");
    // A file that is no policy.
    let o = dronerace(&["distill", "--teacher", dir.path().join("missing.bin").to_str().unwrap(), "--out", out.to_str().unwrap()]);
    assert!(!o.status.success() && String::from_utf8_lossy(&o.stderr).contains("missing.bin"));
}

#[test]
fn every_shipped_distillation_and_vision_config_parses_and_names_files_that_exist() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let toml_files = |dir: &str| -> Vec<PathBuf> {
        let mut files: Vec<PathBuf> = std::fs::read_dir(root.join(dir)).unwrap().map(|e| e.unwrap().path()).collect();
        files.retain(|p| p.extension().is_some_and(|e| e == "toml"));
        files
    };
    let distill = toml_files("experiments/distill");
    assert!(distill.len() >= 2);
    for path in distill {
        let config = DistillConfig::read(&path).unwrap_or_else(|e| panic!("{e:#}"));
        assert!(root.join(&config.teacher).exists(), "{}: teacher {}", path.display(), config.teacher.display());
        if let Some(start) = &config.init_from {
            assert!(root.join(start).exists(), "{}: init_from {}", path.display(), start.display());
        }
    }
    for path in toml_files("experiments/vision") {
        let config = runtime::TrainConfig::read(&path).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(config.resolved_profile().unwrap().architecture.agent, policy::Agent::Vision, "{}", path.display());
        if let Some(start) = &config.init_from {
            assert!(root.join(start).exists(), "{}: init_from {}", path.display(), start.display());
        }
    }
}
