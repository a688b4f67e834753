//! Training end to end: in one process, resuming from a checkpoint continues exactly; and the
//! train (as processes) → resume → evaluate commands work together.

// Test code: a panic is how a failure is reported.
#![allow(clippy::unwrap_used, clippy::expect_used, clippy::print_stdout, clippy::print_stderr)]

use std::path::Path;
use std::process::Command;

use learner::PpoConfig;
use runtime::{TrainConfig, Trainer};
use taskctl::TaskService;

/// A tiny but complete run: generated tracks with adaptive switching on a short window.
fn tiny_config() -> TrainConfig {
    let mut config = TrainConfig {
        name: "tiny".into(),
        profile: "cpu".into(),
        total_env_steps: 10_000,
        seed: 3,
        envs: Some(4),
        ppo: Some(PpoConfig { n_steps: 32, batch_size: 48, n_epochs: 2, ..PpoConfig::default() }),
        checkpoint_every: 2,
        ..TrainConfig::default()
    };
    config.switching.window = 2;
    config
}

/// The policy's bytes with burn's process-unique parameter ids blanked: values, normaliser,
/// version and architecture, bit for bit.
fn weights(trainer: &Trainer) -> Vec<u8> {
    let mut blob = trainer.learner().weights();
    blob.params.iter_mut().for_each(|p| p.id = 0);
    blob.to_bytes()
}

/// Three iterations straight, and two, a "death" after the checkpoint of iteration 2, a resume
/// and one more, in sibling directories of a temporary one.
fn straight_and_resumed(config: fn() -> TrainConfig, dir: &Path) -> (Trainer, Trainer) {
    let (straight, resumed) = (dir.join("straight"), dir.join("resumed"));
    std::fs::create_dir_all(&straight).unwrap();
    std::fs::create_dir_all(&resumed).unwrap();
    let mut a = Trainer::start(config().resolve().unwrap(), &straight).unwrap();
    for _ in 0..3 {
        a.iteration_step().unwrap();
    }
    let mut b = Trainer::start(config().resolve().unwrap(), &resumed).unwrap();
    for _ in 0..2 {
        b.iteration_step().unwrap();
    }
    let before = weights(&b);
    drop(b); // the process "dies" after the checkpoint of iteration 2
    let mut b = Trainer::resume(&resumed).unwrap();
    assert_eq!(b.iteration(), 2);
    assert!(weights(&b) == before, "the checkpoint restores the weights bit for bit");
    b.iteration_step().unwrap();
    (a, b)
}

#[test]
fn resuming_from_a_checkpoint_gives_the_same_next_iteration_weights() {
    let dir = tempfile::tempdir().unwrap();
    let (a, b) = straight_and_resumed(tiny_config, dir.path());
    assert_eq!(b.learner().version(), a.learner().version());
    assert_eq!(b.learner().env_steps(), a.learner().env_steps());
    assert!(weights(&b) == weights(&a), "the next iteration's weights equal an uninterrupted run's");
    assert_eq!(b.tasks().switch_history(0).unwrap(), a.tasks().switch_history(0).unwrap());
    // metrics.csv continues where it stopped: a header and one row per iteration.
    let rows = std::fs::read_to_string(dir.path().join("resumed/metrics.csv")).unwrap().lines().count();
    assert_eq!(rows, 1 + 2 + 1);
}

#[test]
fn a_corrupt_newest_checkpoint_resumes_from_the_one_before_and_cut_off_writes_are_removed() {
    let dir = tempfile::tempdir().unwrap();
    let run = dir.path().join("run");
    let config = || TrainConfig { checkpoint_every: 1, ..tiny_config() };
    let mut t = Trainer::start(config().resolve().unwrap(), &run).unwrap();
    for _ in 0..3 {
        t.iteration_step().unwrap();
    }
    drop(t);
    let checkpoints = run.join("checkpoints");
    // The newest cut short (a disk fault), and what a kill in the middle of a write leaves.
    let newest = checkpoints.join("ckpt-000000003.bin");
    let bytes = std::fs::read(&newest).unwrap();
    std::fs::write(&newest, &bytes[..bytes.len() / 2]).unwrap();
    let stale = checkpoints.join("ckpt-000000004.bin.tmp");
    std::fs::write(&stale, b"half a checkpoint").unwrap();
    let resumed = Trainer::resume(&run).unwrap();
    assert_eq!(resumed.iteration(), 2, "the checkpoint before the corrupt one");
    assert!(!stale.exists(), "the cut-off write is removed at start");
    drop(resumed);
    // Nothing readable at all: the error names every checkpoint tried.
    for entry in std::fs::read_dir(&checkpoints).unwrap() {
        let path = entry.unwrap().path();
        if path.file_name().unwrap().to_str().unwrap().starts_with("ckpt-") {
            std::fs::write(&path, b"garbage").unwrap();
        }
    }
    let error = Trainer::resume(&run).err().unwrap().to_string();
    assert!(error.contains("no checkpoint") && error.contains("ckpt-000000001.bin") && error.contains("ckpt-000000003.bin"), "{error}");
}

#[test]
fn checkpoints_that_keep_failing_stop_the_run_with_a_fatal_error() {
    let dir = tempfile::tempdir().unwrap();
    let run = dir.path().join("run");
    let mut t = Trainer::start(TrainConfig { checkpoint_every: 1, ..tiny_config() }.resolve().unwrap(), &run).unwrap();
    t.iteration_step().unwrap();
    // A directory where a write's temporary file goes makes that write fail, as a full disk
    // would (root ignores permissions, so a read-only directory would not).
    let checkpoints = run.join("checkpoints");
    for name in ["best.bin.tmp", "ckpt-000000002.bin.tmp", "ckpt-000000003.bin.tmp", "ckpt-000000004.bin.tmp"] {
        std::fs::create_dir(checkpoints.join(name)).unwrap();
    }
    let error = (0..3).find_map(|_| t.iteration_step().err()).expect("the run stops within three failing iterations");
    assert!(error.is_fatal(), "{error}");
    let text = error.to_string();
    assert!(text.contains("writes of the run's state in a row failed") && text.contains(".bin"), "{text}");
    assert!(t.iteration() >= 2, "one failed write did not stop it: iteration {}", t.iteration());
}

#[test]
fn a_runs_wall_seconds_count_each_validation_once() {
    // A validation after every iteration, long beside the tiny iterations: counted twice, the
    // run's wall seconds would exceed the time that passed.
    let dir = tempfile::tempdir().unwrap();
    let eval = runtime::EvalSettings { every: 1, tracks: 4, runs: 2, steps: 1000, ..runtime::EvalSettings::default() };
    let mut trainer = Trainer::start(TrainConfig { eval, ..tiny_config() }.resolve().unwrap(), dir.path()).unwrap();
    let started = std::time::Instant::now();
    for _ in 0..3 {
        trainer.iteration_step().unwrap();
    }
    let elapsed = started.elapsed().as_secs_f64();
    assert!(trainer.wall_seconds() > 0.0 && trainer.wall_seconds() <= elapsed, "{} s counted in {elapsed} s", trainer.wall_seconds());
}

/// `tiny_config` validated after every iteration on two short tracks, `best.bin` averaging
/// the last two validated policies.
fn tiny_averaging_config() -> TrainConfig {
    let eval = runtime::EvalSettings { every: 1, average: 2, tracks: 2, runs: 1, steps: 100, ..runtime::EvalSettings::default() };
    TrainConfig { eval, checkpoint_every: 2, ..tiny_config() }
}

#[test]
fn best_bin_is_the_weight_average_of_the_last_validated_policies_and_resumes_bit_for_bit() {
    let dir = tempfile::tempdir().unwrap();
    let _ = straight_and_resumed(tiny_averaging_config, dir.path());
    let best_without_ids = |run: &str| {
        let mut blob = learner::checkpoint::read_policy(&dir.path().join(run).join("checkpoints/best.bin")).unwrap();
        blob.params.iter_mut().for_each(|p| p.id = 0);
        blob.to_bytes()
    };
    for run in ["straight", "resumed"] {
        let validated = dir.path().join(run).join("checkpoints/validated");
        let mut kept: Vec<_> = std::fs::read_dir(&validated).unwrap().map(|e| e.unwrap().path()).collect();
        kept.sort();
        let names: Vec<_> = kept.iter().map(|p| p.file_name().unwrap().to_str().unwrap().to_owned()).collect();
        assert_eq!(names, ["v-000000002.bin", "v-000000003.bin"], "{run}: the last two validations kept");
        let policies: Vec<_> = kept.iter().map(|p| learner::checkpoint::read_policy(p).unwrap()).collect();
        assert!(policies[0].params != policies[1].params, "{run}: two different policies");
        let average = policyfile::averaging::average(&policies).unwrap();
        let best = std::fs::read(dir.path().join(run).join("checkpoints/best.bin")).unwrap();
        assert!(best == average.to_bytes(), "{run}: best.bin is their weight average");
    }
    assert!(best_without_ids("straight") == best_without_ids("resumed"), "the resumed run's best.bin is the straight run's");
}

#[test]
fn two_identical_runs_are_identical() {
    let dir = tempfile::tempdir().unwrap();
    let (p, q) = (dir.path().join("p"), dir.path().join("q"));
    std::fs::create_dir_all(&p).unwrap();
    std::fs::create_dir_all(&q).unwrap();
    let mut a = Trainer::start(tiny_config().resolve().unwrap(), &p).unwrap();
    let mut b = Trainer::start(tiny_config().resolve().unwrap(), &q).unwrap();
    assert!(weights(&a) == weights(&b), "same initial weights");
    for i in 0..3 {
        a.iteration_step().unwrap();
        b.iteration_step().unwrap();
        assert!(weights(&a) == weights(&b), "iteration {i}");
    }
}

#[test]
fn fine_tuning_starts_from_the_given_policy_at_version_zero() {
    let dir = tempfile::tempdir().unwrap();
    let (source, tuned) = (dir.path().join("source"), dir.path().join("tuned"));
    std::fs::create_dir_all(&source).unwrap();
    std::fs::create_dir_all(&tuned).unwrap();
    let mut a = Trainer::start(tiny_config().resolve().unwrap(), &source).unwrap();
    for _ in 0..2 {
        a.iteration_step().unwrap();
    }
    let checkpoint = a.checkpoint().unwrap();
    let config = TrainConfig { init_from: Some(checkpoint), seed: 11, ..tiny_config() };
    let b = Trainer::start(config.clone().resolve().unwrap(), &tuned).unwrap();
    let (from, to) = (a.learner().weights(), b.learner().weights());
    assert_eq!(b.learner().version(), 0);
    assert_eq!(b.learner().env_steps(), 0);
    assert_eq!(to.normalizer, from.normalizer, "the normaliser travels with the weights");
    let values = |blob: &policy::WeightsBlob| blob.params.iter().map(|p| p.values.clone()).collect::<Vec<_>>();
    assert!(values(&to) == values(&from), "the network starts as the source policy");
    // A wider run (the paper profile's 512 × 512) starts from the policy's function.
    let paper =
        Trainer::start(TrainConfig { profile: "paper".into(), ..config.clone() }.resolve().unwrap(), &dir.path().join("paper")).unwrap();
    let wide = paper.learner().weights();
    assert_eq!(wide.architecture.hidden, [512, 512]);
    let observations: Vec<f32> = (0..3 * from.architecture.observation_dim).map(|i| (i as f32 * 0.61).sin()).collect();
    let act = |blob: &policy::WeightsBlob| policy::Policy::from_blob(blob).unwrap().deterministic_actions(&observations);
    for (a, b) in act(&from).iter().zip(act(&wide)) {
        assert!((a - b).abs() < 1e-5, "the widened policy acts as its source");
    }
    // A narrower run, or a policy of another shape, is refused, naming the file.
    let narrow = TrainConfig { hidden: Some(vec![8, 8]), ..config.clone() };
    let err = Trainer::start(narrow.resolve().unwrap(), &dir.path().join("narrow")).err().expect("refused").to_string();
    assert!(err.contains("init_from") && err.contains("cannot widen"), "{err}");
    let mut fewer_points = config;
    fewer_points.env.observation.line_points = 2;
    let err = Trainer::start(fewer_points.resolve().unwrap(), &dir.path().join("fewer-points")).err().expect("refused").to_string();
    assert!(err.contains("init_from") && err.contains("architecture"), "{err}");
}

/// The tiny run with two racing-line points in the observation (40 + 6 numbers).
fn tiny_line_config() -> TrainConfig {
    let mut config = tiny_config();
    config.env.observation.line_points = 2;
    config
}

#[test]
fn a_run_with_line_points_learns_from_46_numbers_and_resumes_bit_for_bit() {
    let dir = tempfile::tempdir().unwrap();
    let (a, b) = straight_and_resumed(tiny_line_config, dir.path());
    assert!(weights(&b) == weights(&a), "the next iteration's weights equal an uninterrupted run's");
    let arch = a.learner().weights().architecture;
    assert_eq!((arch.observation_dim, arch.observation.line_points), (46, 2));
    assert_eq!(a.learner().weights().normalizer.dim(), 46);
    // Its policy flies with the observation it learned (46 numbers, not the SPEC's 40).
    let policy = std::sync::Arc::new(policy::Policy::from_blob(&a.learner().weights()).unwrap());
    assert_eq!(policy.observation_layout().dim(), 46);
    // A line spacing that is no distance is refused, naming the field.
    let mut bad = tiny_line_config();
    bad.env.observation.line_spacing = f64::NAN;
    let err = bad.resolve().expect_err("refused").to_string();
    assert!(err.contains("env.observation.line_spacing"), "{err}");
    let track = std::sync::Arc::new(racetracks::library_track("Figure8").unwrap().unwrap());
    let config = sim::eval::EvalConfig { runs: 2, steps: 50, ..sim::eval::EvalConfig::default() };
    let report = sim::eval::evaluate("policy", &[track], &|| Box::new(policy::PolicyController::new(policy.clone())), &config);
    assert_eq!(report.outcomes.deployments, 2);
}

#[test]
fn a_run_directory_with_checkpoints_is_not_overwritten() {
    let dir = tempfile::tempdir().unwrap();
    let mut t = Trainer::start(tiny_config().resolve().unwrap(), dir.path()).unwrap();
    t.iteration_step().unwrap();
    t.checkpoint().unwrap();
    let err = Trainer::start(tiny_config().resolve().unwrap(), dir.path()).err().expect("refused");
    assert!(err.to_string().contains("already holds checkpoints"), "{err}");
}

fn dronerace(args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_dronerace")).args(args).output().expect("run dronerace")
}

/// `dronerace eval` of the policy at `policy` on Figure8, results in `out`.
fn eval_on_figure8(policy: &Path, runs: usize, steps: usize, out: &Path) -> std::process::Output {
    let figure8 = Path::new(env!("CARGO_MANIFEST_DIR")).join("tracks/figure8.toml");
    let (runs, steps) = (runs.to_string(), steps.to_string());
    let args = ["eval", "--controller", "policy", "--policy", policy.to_str().unwrap(), "--tracks", figure8.to_str().unwrap()];
    dronerace(&[&args[..], &["--runs", &runs, "--steps", &steps, "--out", out.to_str().unwrap()]].concat())
}

#[test]
fn train_resume_and_evaluate_from_the_command_line() {
    let dir = tempfile::tempdir().unwrap();
    let run = dir.path().join("run");
    let config = dir.path().join("train.toml");
    std::fs::write(
        &config,
        "name = \"cli\"\nprofile = \"cpu\"\nenvs = 4\ntotal_env_steps = 100000\n\n[ppo]\nn_steps = 16\nbatch_size = 32\nn_epochs = 1\n\n[tracks]\nkind = \"library\"\nnames = [\"Figure8\"]\n",
    )
    .unwrap();
    let o = dronerace(&["train", "--config", config.to_str().unwrap(), "--out", run.to_str().unwrap(), "--iterations", "2"]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let o = dronerace(&["train", "--resume", run.to_str().unwrap(), "--iterations", "1"]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        o.status.success() && err.contains("resuming the run") && err.contains("at iteration 2") && err.contains("iter     3"),
        "{err}"
    );
    for file in ["config.toml", "metrics.csv", "train.log", "checkpoints/ckpt-000000003.bin"] {
        assert!(run.join(file).exists(), "{file}");
    }
    let out = dir.path().join("eval");
    let o = eval_on_figure8(&run.join("checkpoints/ckpt-000000003.bin"), 2, 100, &out);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(String::from_utf8_lossy(&o.stdout).contains("policy v3"));
    // The exported weights blob flies exactly as the checkpoint it came from.
    let table = |json: &Path| {
        let mut v: serde_json::Value = serde_json::from_slice(&std::fs::read(json).unwrap()).unwrap();
        v["controller"] = serde_json::Value::Null;
        v
    };
    let from_checkpoint = table(&out.join("eval.json"));
    let blob = dir.path().join("policy.bin");
    let o = dronerace(&["export", run.join("checkpoints/ckpt-000000003.bin").to_str().unwrap(), "--out", blob.to_str().unwrap()]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let o = eval_on_figure8(&blob, 2, 100, &out);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert_eq!(table(&out.join("eval.json")), from_checkpoint);
    assert!(std::fs::metadata(&blob).unwrap().len() < std::fs::metadata(run.join("checkpoints/ckpt-000000003.bin")).unwrap().len());
    // A bad config names the field.
    std::fs::write(&config, "profile = \"huge\"\n").unwrap();
    let o = dronerace(&["train", "--config", config.to_str().unwrap(), "--out", dir.path().join("x").to_str().unwrap()]);
    assert!(!o.status.success() && String::from_utf8_lossy(&o.stderr).contains("profile"));
    std::fs::write(&config, "profil = \"cpu\"\n").unwrap();
    let o = dronerace(&["train", "--config", config.to_str().unwrap(), "--out", dir.path().join("y").to_str().unwrap()]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && err.contains("train.toml") && err.contains("profil"), "{err}");
}

#[test]
fn a_few_seconds_of_training_measurably_improve_the_mean_return() {
    // Easy task: 100-step episodes from 2 m behind Figure8's first gate. A random policy
    // crashes (−4) early; staying up and flying at the gate pays up to a few points.
    let mut config = TrainConfig {
        name: "smoke".into(),
        profile: "cpu".into(),
        total_env_steps: 100_000_000,
        seed: 1,
        envs: Some(32),
        ppo: Some(PpoConfig { n_steps: 64, batch_size: 512, n_epochs: 5, learning_rate_start: 1e-3, ..PpoConfig::default() }),
        tracks: runtime::TrackSource::Chosen { names: vec!["Figure8".into()], files: Vec::new() },
        checkpoint_every: 1000,
        ..TrainConfig::default()
    };
    config.switching.policy = taskctl::SwitchPolicy::None;
    config.env.race.max_episode_steps = 100;
    let dir = tempfile::tempdir().unwrap();
    let mut trainer = Trainer::start(config.resolve().unwrap(), dir.path()).unwrap();
    let returns: Vec<f64> = (0..25).map(|_| trainer.iteration_step().unwrap().mean_return).collect();
    let first = returns[..4].iter().sum::<f64>() / 4.0;
    let last = returns[returns.len() - 4..].iter().sum::<f64>() / 4.0;
    eprintln!("mean returns per iteration: {returns:.2?}");
    assert!(last > first + 1.0, "mean return {first:.2} → {last:.2}: {returns:.2?}");
}

/// A tiny vision run: SPEC's VB defaults, with small networks and rollouts so it runs in seconds.
fn tiny_vision_config() -> TrainConfig {
    let text = "agent = \"vision\"\nname = \"tiny-vision\"\nenvs = 4\nhidden = [16, 16]\ntotal_env_steps = 10000\nseed = 2\ncheckpoint_every = 2\n\n[ppo]\nn_steps = 16\nbatch_size = 32\nn_epochs = 1\n\n[switching]\nwindow = 2\n\n[eval]\nevery = 0\n";
    TrainConfig::from_toml(text).unwrap()
}

#[test]
fn a_vision_config_takes_the_vb_columns_for_whatever_it_does_not_set() {
    let config = tiny_vision_config();
    assert_eq!(config.agent, policy::Agent::Vision);
    let ppo = config.ppo.unwrap();
    // Set by the file.
    assert_eq!((ppo.n_steps, ppo.batch_size, ppo.n_epochs), (16, 32, 1));
    // Not set: SPEC §10's VB column, §3's VB randomisation, §8's α = 100.
    assert_eq!((ppo.initial_log_std, ppo.learning_rate_start), (0.0, 2e-4));
    assert_eq!(config.env.randomization, sim::RandomizationParams::vision_based());
    assert_eq!(config.env.reward, sim::RewardParams::vision_based());
    assert_eq!(config.switching.alpha, 100.0);
    assert_eq!(config.clone().resolve().unwrap().learner().architecture.agent, policy::Agent::Vision);
    // A state-based file is read as before.
    let state = TrainConfig::from_toml("envs = 4\n").unwrap();
    assert_eq!((state.agent, state.switching.alpha, state.ppo), (policy::Agent::State, 1000.0, None));
}

#[test]
fn a_vision_agent_trains_on_its_camera_images_and_resumes_bit_for_bit() {
    let dir = tempfile::tempdir().unwrap();
    let (a, b) = straight_and_resumed(tiny_vision_config, dir.path());
    let blob = a.learner().weights();
    assert_eq!((blob.architecture.agent, blob.version), (policy::Agent::Vision, 3));
    assert!(weights(&b) == weights(&a), "the CNN, its optimiser and the camera-equipped environments continue exactly");
    // The learner refuses a rollout without the camera images its agent acted on.
    let mut learner = tiny_vision_config().resolve().unwrap().initial_learner().unwrap();
    let mut chunk = rollout::RolloutChunk::zeroed(0, 0, 4, 16, sim::STATE_OBS_DIM, sim::ACTION_DIM);
    let err = learner.train(std::slice::from_ref(&chunk)).unwrap_err();
    assert!(err.to_string().contains("without its camera images"), "{err}");
    chunk.images = vec![0; chunk.transitions() * sim::camera::IMAGE_PIXELS];
    learner.train(std::slice::from_ref(&chunk)).unwrap();
    // … and a state-based learner refuses images.
    // SPEC §5's 40 numbers, as the vision chunk's rows: only the images are wrong for it.
    let mut spec_config = TrainConfig { hidden: Some(vec![8]), envs: Some(4), ..TrainConfig::default() };
    spec_config.env.observation.line_points = 0;
    let mut state_learner = spec_config.clone().resolve().unwrap().initial_learner().unwrap();
    let err = state_learner.train(std::slice::from_ref(&chunk)).unwrap_err();
    assert!(err.to_string().contains("camera images in a state-based"), "{err}");
}

#[test]
fn a_vision_run_trains_over_grpc_and_its_policy_is_evaluated_with_its_camera() {
    let dir = tempfile::tempdir().unwrap();
    let (run, config) = (dir.path().join("run"), dir.path().join("vision.toml"));
    std::fs::write(&config, toml::to_string(&tiny_vision_config()).unwrap()).unwrap();
    let o = dronerace(&[
        "train",
        "--config",
        config.to_str().unwrap(),
        "--out",
        run.to_str().unwrap(),
        "--iterations",
        "2",
        "--transport",
        "grpc",
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let o = eval_on_figure8(&run.join("checkpoints/ckpt-000000002.bin"), 1, 50, &dir.path().join("eval"));
    let out = String::from_utf8_lossy(&o.stdout);
    assert!(o.status.success() && out.contains("policy v2") && out.contains("vision-based"), "{out}");
}
