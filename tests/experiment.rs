//! Experiments as files: two variants × two seeds of a tiny run, interrupted part-way, then run
//! again (finished runs skipped, the interrupted one resumed), then reported (Markdown and plot);
//! two runners on one directory share the grid out.

// Test code: a panic is how a failure is reported.
#![allow(clippy::unwrap_used, clippy::expect_used, clippy::print_stdout, clippy::print_stderr)]

use std::path::Path;
use std::process::Command;
use std::sync::atomic::{AtomicBool, Ordering};

use runtime::experiment::{Experiment, RunLog, run_experiment};

const FILE: &str = r#"
description = "tiny frames"
seeds = [0, 1]

[base]
total_env_steps = 384          # 3 iterations of 4 environments × 32 steps
envs = 4
checkpoint_every = 1
ppo = { n_steps = 32, batch_size = 64, n_epochs = 1 }
eval = { every = 1, tracks = 2, runs = 2, steps = 100 }

[test]
runs = 1
steps = 50
validation_tracks = 3

[[variant]]
name = "world"

[[variant]]
name = "heading"
set = { env.observation.frame = "heading" }
"#;

/// Runs the experiment, raising the stop flag after `stop_after` iterations (none: to the end).
fn run(experiment: &Experiment, out: &Path, stop_after: Option<usize>) -> RunLog {
    let stop = AtomicBool::new(false);
    let mut iterations = 0;
    run_experiment(experiment, out, &stop, &mut |_, _| {
        iterations += 1;
        if stop_after.is_some_and(|n| iterations >= n) {
            stop.store(true, Ordering::SeqCst);
        }
    })
    .unwrap()
}

#[test]
fn an_interrupted_experiment_resumes_without_redoing_finished_runs_and_reports() {
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("tiny.toml");
    std::fs::write(&file, FILE).unwrap();
    let out = dir.path().join("out");
    let experiment = Experiment::read(&file).unwrap();
    let run_dir = |variant: &str, seed: u64| Experiment::run_dir(&out, variant, seed);

    // Stop during the second run (seed-major order: world/0 then heading/0).
    let first = run(&experiment, &out, Some(5));
    assert!(first.interrupted);
    assert_eq!(first.finished, vec![run_dir("world", 0)]);
    assert_eq!(first.started, vec![run_dir("world", 0), run_dir("heading", 0)]);
    assert!(!run_dir("heading", 0).join("test.json").exists());
    let finished_result = std::fs::read(run_dir("world", 0).join("test.json")).unwrap();

    let second = run(&experiment, &out, None);
    assert!(!second.interrupted);
    assert_eq!(second.skipped, vec![run_dir("world", 0)]);
    assert_eq!(second.resumed, vec![run_dir("heading", 0)]);
    assert_eq!(second.started, vec![run_dir("world", 1), run_dir("heading", 1)]);
    assert_eq!(second.finished.len(), 3);
    assert_eq!(std::fs::read(run_dir("world", 0).join("test.json")).unwrap(), finished_result, "a done run is not redone");
    let resumed: serde_json::Value = serde_json::from_slice(&std::fs::read(run_dir("heading", 0).join("test.json")).unwrap()).unwrap();
    assert_eq!(resumed["iterations"], 3, "the resumed run finished its budget, not more");
    assert_eq!(resumed["final_policy"]["outcomes"]["deployments"], 40, "40 test tracks × 1 deployment");
    // Every deployment's ending is kept, for failure analyses without re-flying the policies.
    let kept: usize = resumed["best_policy"]["tracks"].as_array().unwrap().iter().map(|t| t["deployments"].as_array().unwrap().len()).sum();
    assert_eq!(kept, 40);
    // best.bin also flew the fresh validation tracks the variants are chosen by: 3 × 10, the
    // validation range's tracks after the 2 the run validated on while training.
    assert_eq!(resumed["fresh_validation"]["outcomes"]["deployments"], 30);
    assert_eq!(resumed["fresh_validation"]["controller"], "best");
    let fresh: Vec<&str> = resumed["fresh_validation"]["tracks"].as_array().unwrap().iter().map(|t| t["track"].as_str().unwrap()).collect();
    assert_eq!(fresh, ["val-8000002", "val-8000003", "val-8000004"]);

    // A third call has nothing left to do.
    let third = run(&experiment, &out, None);
    assert_eq!((third.skipped.len(), third.started.len(), third.resumed.len()), (4, 0, 0));

    // `experiment report FILE --out DIR`, the arguments of `experiment run`.
    let o = Command::new(env!("CARGO_BIN_EXE_dronerace"))
        .args(["experiment", "report", file.to_str().unwrap(), "--out", out.to_str().unwrap()])
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let report = std::fs::read_to_string(out.join("report.md")).unwrap();
    for needle in ["| world | 2 of 2 |", "| heading | 2 of 2 |", "ground", "gate frame", "## The thesis' columns"] {
        assert!(report.contains(needle), "report lacks {needle:?}:\n{report}");
    }
    // The thesis' columns: both runs of each variant have a validation curve and a switch count.
    let columns = report.split("## The thesis' columns").nth(1).unwrap();
    assert!(columns.lines().any(|l| l.starts_with("| world | 2 | ")), "{columns}");
    let png = std::fs::read(out.join("curves.png")).unwrap();
    assert_eq!(&png[1..4], b"PNG");
}

#[test]
fn two_runners_on_one_directory_split_the_grid() {
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("tiny.toml");
    std::fs::write(&file, FILE).unwrap();
    let out = dir.path().join("out");
    let experiment = Experiment::read(&file).unwrap();
    let (a, b) = std::thread::scope(|s| {
        let a = s.spawn(|| run(&experiment, &out, None));
        let b = s.spawn(|| run(&experiment, &out, None));
        (a.join().unwrap(), b.join().unwrap())
    });
    let mut trained: Vec<_> = a.started.iter().chain(&b.started).cloned().collect();
    trained.sort();
    let mut all: Vec<_> =
        [("heading", 0), ("heading", 1), ("world", 0), ("world", 1)].iter().map(|&(v, s)| Experiment::run_dir(&out, v, s)).collect();
    all.sort();
    assert_eq!(trained, all, "every run trained by exactly one runner: {a:?} {b:?}");
    assert_eq!(a.finished.len() + b.finished.len(), 4);
    for run in &all {
        assert!(run.join("test.json").exists() && !run.join(runtime::run_lock::LOCK_FILE).exists(), "{}", run.display());
    }
}

#[test]
fn an_experiment_with_an_unknown_override_key_is_refused_naming_it() {
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("bad.toml");
    std::fs::write(&file, FILE.replace("env.observation.frame", "env.observation_fram")).unwrap();
    let o = Command::new(env!("CARGO_BIN_EXE_dronerace"))
        .args(["experiment", "run", file.to_str().unwrap(), "--out", dir.path().join("out").to_str().unwrap()])
        .output()
        .unwrap();
    assert!(!o.status.success());
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("observation_fram") && err.contains("bad.toml") && err.contains("heading"), "{err}");
    assert!(!dir.path().join("out").join("world").exists(), "nothing ran");
}

#[test]
fn every_shipped_experiment_file_resolves_for_every_variant() {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("experiments");
    let mut count = 0;
    for entry in std::fs::read_dir(&dir).unwrap() {
        let path = entry.unwrap().path();
        if path.extension().is_some_and(|e| e == "toml") {
            let experiment = Experiment::read(&path).unwrap_or_else(|e| panic!("{e}"));
            assert!(experiment.variants.len() >= 2, "{}: an experiment compares", path.display());
            count += 1;
        }
    }
    assert!(count >= 6, "found {count} experiment files");
}

/// The single-run configs of `docs/experiments/*/` (the full-scale runs BENCHMARKS.md cites):
/// training runs, and distillations (the files that name a `teacher`).
#[test]
fn every_documented_run_config_resolves() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("docs/experiments");
    let mut count = 0;
    for study in std::fs::read_dir(&root).unwrap() {
        for entry in std::fs::read_dir(study.unwrap().path()).unwrap() {
            let path = entry.unwrap().path();
            if path.extension().is_some_and(|e| e == "toml") {
                let text = std::fs::read_to_string(&path).unwrap();
                if text.lines().any(|line| line.starts_with("teacher =")) {
                    distill::DistillConfig::read(&path).unwrap_or_else(|e| panic!("{e:#}"));
                    continue;
                }
                let config = runtime::TrainConfig::read(&path).unwrap_or_else(|e| panic!("{e}"));
                config.clone().resolve().unwrap_or_else(|e| panic!("{}: {e}", path.display()));
                count += 1;
            }
        }
    }
    assert!(count >= 10, "found {count} run configs");
}

#[test]
fn the_paper_profile_with_specs_ppo_column_is_spec_section_10_as_is() {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("docs/bench/paper-spec-ppo.toml");
    let resolved = runtime::ResolvedRun::read(&path).unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(resolved.learner().ppo, learner::PpoConfig::default(), "SPEC §10's state-based column");
    assert_eq!((resolved.learner().architecture.hidden.as_slice(), resolved.envs()), ([512, 512].as_slice(), 96));
}

const SEQUENTIAL: &str = r#"
description = "tiny sequential curriculum"
seeds = [0]
sequential = true

[base]
total_env_steps = 256          # 2 iterations of 4 environments × 32 steps per stage
envs = 4
checkpoint_every = 1
switching = { policy = "none" }
ppo = { n_steps = 32, batch_size = 64, n_epochs = 1 }
eval = { every = 1, runs = 1, steps = 50, library = ["Figure8", "BigS"] }

[test]
runs = 1
steps = 20
validation_tracks = 0

[[variant]]
name = "first"
set = { tracks = { kind = "library", names = ["Figure8"] } }

[[variant]]
name = "second"
set = { tracks = { kind = "library", names = ["BigS"] } }
"#;

#[test]
fn a_sequential_experiment_starts_each_stage_from_the_last_and_tracks_every_validation_track() {
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("sequential.toml");
    std::fs::write(&file, SEQUENTIAL).unwrap();
    let out = dir.path().join("out");
    let experiment = Experiment::read(&file).unwrap();
    let log = run(&experiment, &out, None);
    assert_eq!(log.finished.len(), 2);
    let second: runtime::TrainConfig =
        toml::from_str(&std::fs::read_to_string(Experiment::run_dir(&out, "second", 0).join("config.toml")).unwrap()).unwrap();
    let first_end = Experiment::run_dir(&out, "first", 0).join("checkpoints").join("ckpt-000000002.bin");
    assert_eq!(second.init_from, Some(first_end), "stage 2 starts from stage 1's last checkpoint");
    let first: runtime::TrainConfig =
        toml::from_str(&std::fs::read_to_string(Experiment::run_dir(&out, "first", 0).join("config.toml")).unwrap()).unwrap();
    assert_eq!(first.init_from, None, "stage 1 starts fresh");
    let result: serde_json::Value =
        serde_json::from_slice(&std::fs::read(Experiment::run_dir(&out, "first", 0).join("test.json")).unwrap()).unwrap();
    assert!(result["fresh_validation"].is_null(), "validation_tracks = 0 skips the fresh validation");

    let (curves, boundaries) = runtime::experiment::sequential_track_curves(&experiment, &out, 0).unwrap();
    assert_eq!(boundaries, vec![256]);
    let names: Vec<&str> = curves.iter().map(|c| c.track.as_str()).collect();
    assert_eq!(names, vec!["BigS", "Figure8"]);
    for c in &curves {
        let steps: Vec<u64> = c.points.iter().map(|p| p.0).collect();
        assert_eq!(steps, vec![128, 256, 384, 512], "{}: both stages, laid end to end", c.track);
    }
    let o = Command::new(env!("CARGO_BIN_EXE_dronerace"))
        .args(["experiment", "report", file.to_str().unwrap(), "--out", out.to_str().unwrap()])
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert_eq!(&std::fs::read(out.join("tracks-seed-0.png")).unwrap()[1..4], b"PNG");
}
