//! Distillation end to end: an interrupted DAgger run resumes bit for bit, the teacher's share
//! of the flying follows β = decay^round, teachers with longer observations teach in their own
//! layout, and the command refuses a teacher that cannot teach.

// Test code: a panic is how a failure is reported.
#![allow(clippy::unwrap_used, clippy::expect_used, clippy::print_stdout, clippy::print_stderr)]

use std::path::{Path, PathBuf};
use std::process::Command;

use distill::{DistillConfig, Distiller};
use policy::WeightsBlob;
use runtime::EvalSettings;

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

    // A student that reads its previous action, which the checkpoint's architecture must keep.
    let config = || DistillConfig { previous_action: true, ..tiny_config() };
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
    assert!(last.loss.is_finite(), "the regression's loss is reported");
    let err = Distiller::start(DistillConfig { takeover: Some(-1.0), ..tiny_config() }, &dir.path().join("negative")).err().unwrap();
    assert!(format!("{err:#}").contains("takeover"), "{err:#}");
    assert!(student(&b) == student(&a), "data set, environments, curriculum and optimiser continue exactly");
    assert!(b.finished());
    // A row per round in metrics.csv, and the validated student kept as best.bin.
    let rows = std::fs::read_to_string(resumed.join("metrics.csv")).unwrap().lines().count();
    assert_eq!(rows, 1 + 4);
    let best = learner::checkpoint::read_policy(&resumed.join("checkpoints/best.bin")).unwrap();
    assert_eq!((best.architecture.agent, best.architecture.vision_previous_action), (policy::Agent::Vision, true));
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
fn a_state_student_of_the_pilot_resumes_bit_for_bit_with_its_pilots_mid_flight() {
    let config = || DistillConfig {
        teacher: distill::PILOT_TEACHER.into(),
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
        teacher: distill::PILOT_TEACHER.into(),
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

#[test]
fn a_student_started_from_one_blind_to_its_previous_action_learns_to_read_it() {
    let dir = tempfile::tempdir().unwrap();
    let start = dir.path().join("start.bin");
    let first = Distiller::start(DistillConfig { rounds: 2, ..tiny_config() }, &dir.path().join("first")).unwrap().student();
    std::fs::write(&start, first.to_bytes()).unwrap();
    assert!(!first.architecture.vision_previous_action);

    let config = || DistillConfig { init_from: Some(start.clone()), previous_action: true, ..tiny_config() };
    let later = dir.path().join("later");
    let mut b = Distiller::start(config(), &later).unwrap();
    assert!(b.student().architecture.vision_previous_action, "the start is widened to read the previous action");
    b.round_step().unwrap();
    b.round_step().unwrap();
    drop(b);
    let b = Distiller::resume(&later).unwrap();
    assert!(b.student().architecture.vision_previous_action, "and resumes as it was");
    // A state student reads the whole observation: the option is refused by name.
    let err = Distiller::start(DistillConfig { student: policy::Agent::State, init_from: None, ..config() }, &dir.path().join("state"))
        .err()
        .unwrap();
    assert!(format!("{err:#}").contains("previous_action"), "{err:#}");
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
        assert_eq!(config.clone().resolve().unwrap().learner().architecture.agent, policy::Agent::Vision, "{}", path.display());
        if let Some(start) = &config.init_from {
            assert!(root.join(start).exists(), "{}: init_from {}", path.display(), start.display());
        }
    }
}
