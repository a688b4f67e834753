//! The actor and learner process loops driven in one process over in-memory links: the
//! learner's drop-and-rejoin rule, without spawning or killing processes.

// Test code: a panic is how a failure is reported.
#![allow(clippy::unwrap_used, clippy::expect_used)]

use std::sync::atomic::AtomicBool;
use std::time::{Duration, Instant};

use learner::PpoConfig;
use runtime::LearnerSettings;
use runtime::actor_process::{ActorLoop, ActorSettings, Pass};
use runtime::learner_process::{LearnerProcess, learner_only};
use runtime::{Run, TrainConfig};
use taskctl::LocalTasks;
use transport::ActorLink;
use transport::board::LearnerBoard;
use transport::memory::memory_link;

/// Two registered actors (a0 on environments 0..2, a1 on 2..4) of a 4-environment run, each
/// with its end of an in-memory link, and a learner expecting both.
struct TwoActors {
    _dir: tempfile::TempDir,
    config: runtime::ResolvedRun,
    tasks: LocalTasks,
    stop: AtomicBool,
    links: [transport::memory::MemoryActorLink; 2],
    actors: [ActorLoop; 2],
    status: std::sync::Arc<LearnerBoard>,
    learner: LearnerProcess<transport::memory::MemoryLearnerLink>,
}

impl TwoActors {
    fn start() -> Self {
        let dir = tempfile::tempdir().unwrap();
        let config = TrainConfig {
            profile: "cpu".into(),
            envs: Some(4),
            ppo: Some(PpoConfig { n_steps: 16, batch_size: 32, n_epochs: 1, ..PpoConfig::default() }),
            ..TrainConfig::default()
        }
        .resolve()
        .unwrap();
        let tasks = LocalTasks::new(config.task_controller().unwrap(), None);
        let stop = AtomicBool::new(false);
        let settings = |name: &str| ActorSettings {
            name: name.into(),
            envs: 2,
            seed: 1,
            env: config.config().env,
            n_steps: 16,
            weights_timeout: Duration::from_secs(60),
            max_rollouts: None,
        };
        let (link0, learner_end) = memory_link();
        let link1 = link0.clone();
        let a0 = ActorLoop::register(&settings("a0"), &tasks, &stop).unwrap().unwrap();
        let a1 = ActorLoop::register(&settings("a1"), &tasks, &stop).unwrap().unwrap();
        let status = std::sync::Arc::new(LearnerBoard::default());
        let learner_settings = LearnerSettings { expected_actors: 2, actor_timeout_seconds: 0.3, ..LearnerSettings::default() };
        let run = Run::create(config.clone(), dir.path()).unwrap();
        let learner = LearnerProcess::start(run, None, learner_end, status.clone(), learner_settings).unwrap();
        Self { _dir: dir, config, tasks, stop, links: [link0, link1], actors: [a0, a1], status, learner }
    }
}

#[test]
fn an_actor_that_misses_an_iteration_is_dropped_and_rejoins_with_its_next_rollout() {
    let TwoActors { config, tasks, stop, links: [mut link0, mut link1], actors: [mut a0, mut a1], status, mut learner, .. } =
        TwoActors::start();
    let members = || status.status().connected_actors;

    // Iteration 1: both deliver; the learner waits for the two it expects.
    assert_eq!(a0.pass(&mut link0, &tasks, &stop).unwrap(), Pass::Sent);
    assert_eq!(a1.pass(&mut link1, &tasks, &stop).unwrap(), Pass::Sent);
    learner.iteration_step(&stop, Some(&tasks), &learner_only).unwrap().unwrap();
    assert_eq!(members(), ["a0", "a1"]);

    // Iteration 2: a1 is silent; the learner waits out the timeout, drops it and trains on a0.
    assert_eq!(a0.pass(&mut link0, &tasks, &stop).unwrap(), Pass::Sent);
    let waited = Instant::now();
    let summary = learner.iteration_step(&stop, Some(&tasks), &learner_only).unwrap().unwrap();
    assert!(waited.elapsed() >= Duration::from_millis(300), "waited {:?} for a1", waited.elapsed());
    assert_eq!(summary.report.env_steps, 4 * 16 + 2 * 16, "iteration 2 trained on a0's two environments only");
    assert_eq!(members(), ["a0"]);
    assert_eq!(a0.pass(&mut link0, &tasks, &stop).unwrap(), Pass::Sent);

    // a1 picks up the newest weights and is back in the next iteration; a0 has no new version yet.
    assert_eq!(a1.pass(&mut link1, &tasks, &stop).unwrap(), Pass::Sent);
    assert_eq!(a0.pass(&mut link0, &tasks, &stop).unwrap(), Pass::Waiting, "one rollout per version");
    learner.iteration_step(&stop, Some(&tasks), &learner_only).unwrap().unwrap();
    assert_eq!(members(), ["a0", "a1"]);
    assert_eq!(learner.learner().version(), 3);

    // a1 falls silent again and is dropped; then a rollout of an old version from it arrives:
    // unusable, but a sign of life, so the next iteration waits for a1 again.
    assert_eq!(a0.pass(&mut link0, &tasks, &stop).unwrap(), Pass::Sent);
    learner.iteration_step(&stop, Some(&tasks), &learner_only).unwrap().unwrap();
    assert_eq!(members(), ["a0"]);
    let observation_dim = config.learner().architecture.observation_dim;
    let stale = rollout::RolloutChunk::zeroed(3, 2, 2, 16, observation_dim, sim::ACTION_DIM);
    link1.send_rollout("a1", status.status().learner_epoch, &stale).unwrap();
    assert_eq!(a0.pass(&mut link0, &tasks, &stop).unwrap(), Pass::Sent);
    let waited = Instant::now();
    learner.iteration_step(&stop, Some(&tasks), &learner_only).unwrap().unwrap();
    assert!(waited.elapsed() >= Duration::from_millis(300), "a1 was waited for again");
}

#[test]
fn an_actor_left_without_a_newer_version_resends_after_its_timeout_then_waits_twice_as_long() {
    let config = TrainConfig {
        profile: "cpu".into(),
        envs: Some(2),
        ppo: Some(PpoConfig { n_steps: 16, batch_size: 32, n_epochs: 1, ..PpoConfig::default() }),
        ..TrainConfig::default()
    }
    .resolve()
    .unwrap();
    let dir = tempfile::tempdir().unwrap();
    let tasks = LocalTasks::new(config.task_controller().unwrap(), None);
    let stop = AtomicBool::new(false);
    let timeout = Duration::from_millis(1000);
    let settings = ActorSettings {
        name: "a0".into(),
        envs: 2,
        seed: 1,
        env: config.config().env,
        n_steps: 16,
        weights_timeout: timeout,
        max_rollouts: None,
    };
    let (mut link, learner_end) = memory_link();
    let mut actor = ActorLoop::register(&settings, &tasks, &stop).unwrap().unwrap();
    // The learner publishes version 0 and never trains: no newer version comes.
    let run = Run::create(config.clone(), dir.path()).unwrap();
    let _learner =
        LearnerProcess::start(run, None, learner_end, std::sync::Arc::new(LearnerBoard::default()), LearnerSettings::default()).unwrap();

    assert_eq!(actor.pass(&mut link, &tasks, &stop).unwrap(), Pass::Sent);
    assert_eq!(actor.pass(&mut link, &tasks, &stop).unwrap(), Pass::Waiting, "one rollout per version");
    std::thread::sleep(timeout + Duration::from_millis(100));
    assert_eq!(actor.pass(&mut link, &tasks, &stop).unwrap(), Pass::Sent, "overdue after the timeout: resent");
    // The next resend waits twice the timeout (this fails only if the sleep overshoots 0.9 s).
    std::thread::sleep(timeout + Duration::from_millis(100));
    assert_eq!(actor.pass(&mut link, &tasks, &stop).unwrap(), Pass::Waiting, "the second resend waits 2× the timeout");
    std::thread::sleep(timeout);
    assert_eq!(actor.pass(&mut link, &tasks, &stop).unwrap(), Pass::Sent);
    assert_eq!(actor.sent(), 3);
}

/// Two rollouts that could poison training, each refused and counted while training goes on:
/// one of 1e9s from an actor that never registered (it moved the normaliser's mean to 5e8, so
/// every real observation normalised to −1), and a well-formed one from a registered actor for
/// the other actor's environments.
#[test]
fn a_poisoned_rollout_and_one_for_another_actors_environments_are_refused_and_training_goes_on() {
    let TwoActors { config, tasks, stop, links: [mut link0, mut link1], actors: [mut a0, mut a1], status, mut learner, .. } =
        TwoActors::start();
    let observation_dim = config.learner().architecture.observation_dim;
    let epoch = status.status().learner_epoch;

    let mut poisoned = rollout::RolloutChunk::zeroed(0, 0, 2, 8, observation_dim, sim::ACTION_DIM);
    poisoned.observations.fill(1.0e9);
    link1.send_rollout("ghost", epoch, &poisoned).unwrap();
    // a1 holds environments 2..4: a rollout of 0..2 under its name is not its to send.
    let borrowed = rollout::RolloutChunk::zeroed(0, 0, 2, 16, observation_dim, sim::ACTION_DIM);
    link1.send_rollout("a1", epoch, &borrowed).unwrap();
    assert_eq!(a0.pass(&mut link0, &tasks, &stop).unwrap(), Pass::Sent);
    assert_eq!(a1.pass(&mut link1, &tasks, &stop).unwrap(), Pass::Sent);
    let summary = learner.iteration_step(&stop, Some(&tasks), &learner_only).unwrap().unwrap();
    assert_eq!(summary.report.env_steps, 4 * 16, "trained on the two actors' own rollouts only");
    assert_eq!(status.refused(), 2, "both refused and counted");
    assert_eq!(summary.report.refused_update, None);
    let normalizer = &learner.learner().weights().normalizer;
    assert!(normalizer.mean.iter().all(|m| m.abs() < 100.0), "the normaliser never saw the 1e9s: {:?}", normalizer.mean);
}
