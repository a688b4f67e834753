//! `dronerace serve`: a policy served over gRPC acts exactly as `dronerace eval`'s controller on
//! the same observations (unary and streamed, from Rust and from the Python client in
//! `docs/python/pilot_client.py`), refuses wrong sizes and non-finite values, and enforces the
//! token. The Python client's test needs `python3` with grpcio and grpcio-tools (`tests/run.sh`
//! installs them); the Rust checks need nothing beyond the build.

// Test code: a panic is how a failure is reported.
#![allow(clippy::unwrap_used, clippy::expect_used)]

mod support;

use policy::NetworkBlob;
use std::path::Path;
use std::sync::Arc;
use std::time::Duration;

use policy::{ActorCritic, Architecture, ObsNormalizer, Policy, PolicyController, WeightsBlob};
use proto::v1::pilot_client::PilotClient;
use proto::v1::{ActRequest, DescribeRequest};
use sim::{Controller, EnvConfig, RaceEnv, ReferencePilot};
use support::prerequisites::{Need, available};
use support::{Proc, args, free_port, serial, wait_until};

/// `message` with the bearer token.
fn with_token<T>(message: T) -> tonic::Request<T> {
    let mut request = tonic::Request::new(message);
    request.metadata_mut().insert("authorization", "Bearer pilot-s3cret".parse().unwrap());
    request
}

/// A heading-frame policy with a fitted normaliser, and observations of the reference pilot
/// flying Figure8 with the actions `dronerace eval`'s controller takes on them.
fn policy_and_flight(dir: &Path) -> (std::path::PathBuf, Vec<Vec<f32>>, Vec<[f32; 4]>) {
    let arch = Architecture {
        hidden: vec![32, 32],
        observation: sim::ObservationLayout::spec(sim::ObservationFrame::Heading),
        ..Architecture::cpu()
    };
    let model = ActorCritic::new(&arch, -0.5, 9, &policy::Device::flex());
    let track = Arc::new(racetracks::library_track("Figure8").unwrap().unwrap());
    let mut env = RaceEnv::new(track, EnvConfig::evaluation(), 0, 0);
    let mut pilot = ReferencePilot::default();
    pilot.reset(&env);
    let mut observations = Vec::new();
    for _ in 0..60 {
        observations.push(env.observation_in(arch.observation).to_vec());
        env.step(&pilot.act(&env));
    }
    let mut normalizer = ObsNormalizer::new(arch.observation_dim);
    normalizer.update(&observations.concat());
    let blob = WeightsBlob::from_model(7, &arch, &normalizer, &model);
    let path = dir.join("policy.bin");
    std::fs::write(&path, blob.to_bytes()).unwrap();
    // What evaluation does with each of those states.
    let mut controller = PolicyController::new(Arc::new(Policy::from_blob(&blob).unwrap()));
    let mut env = RaceEnv::new(Arc::new(racetracks::library_track("Figure8").unwrap().unwrap()), EnvConfig::evaluation(), 0, 0);
    let mut pilot = ReferencePilot::default();
    pilot.reset(&env);
    let mut expected = Vec::new();
    for _ in 0..60 {
        expected.push(controller.act(&env));
        env.step(&pilot.act(&env));
    }
    (path, observations, expected)
}

/// `dronerace serve` running a policy behind a token, with the observations it will be asked
/// about and the actions evaluation takes on them; the server is killed when dropped.
struct Served {
    dir: tempfile::TempDir,
    server: Proc,
    addr: String,
    token: std::path::PathBuf,
    observations: Vec<Vec<f32>>,
    expected: Vec<[f32; 4]>,
}

impl Served {
    fn start() -> Self {
        let dir = tempfile::tempdir().unwrap();
        let (policy, observations, expected) = policy_and_flight(dir.path());
        let token = dir.path().join("token");
        std::fs::write(&token, "pilot-s3cret\n").unwrap();
        let config = dir.path().join("serve.toml");
        std::fs::write(&config, format!("[network]\ntoken_file = {:?}\n", token.display().to_string())).unwrap();
        let addr = format!("127.0.0.1:{}", free_port());
        let server = Proc::start(
            dir.path(),
            "serve",
            &args(&["serve", "--policy", policy.to_str().unwrap(), "--listen", &addr, "--config", config.to_str().unwrap()]),
        );
        Self { dir, server, addr, token, observations, expected }
    }

    /// A client, once the server answers.
    fn client(&self, rt: &tokio::runtime::Runtime) -> PilotClient<tonic::transport::Channel> {
        let channel = tonic::transport::Endpoint::from_shared(format!("http://{}", self.addr)).unwrap();
        let mut client = None;
        wait_until(Duration::from_secs(30), "the pilot server answers", &[&self.server], || {
            client = rt.block_on(channel.connect()).ok().map(PilotClient::new);
            client.is_some()
        });
        client.unwrap()
    }
}

#[test]
fn a_served_policy_acts_as_evaluation_does_and_refuses_bad_requests() {
    let _serial = serial();
    let served = Served::start();
    let (observations, expected) = (&served.observations, &served.expected);
    let rt = tokio::runtime::Runtime::new().unwrap();
    let mut client = served.client(&rt);
    rt.block_on(async {
        let info = client.describe(with_token(DescribeRequest {})).await.unwrap().into_inner();
        assert_eq!((info.observation_dim, info.action_dim, info.observation_frame.as_str(), info.policy_version), (40, 4, "heading", 7));
        assert_eq!(info.observation_layout, "raw 40-number state observation in the heading frame");
        // Unary: every action equals the evaluation controller's on the same state.
        for (o, e) in observations.iter().zip(expected) {
            let action = client.act(with_token(ActRequest { observation: o.clone() })).await.unwrap().into_inner().action;
            assert_eq!(action, e.to_vec());
        }
        // A control loop over one stream: the same actions, in order.
        let requests: Vec<ActRequest> = observations.iter().map(|o| ActRequest { observation: o.clone() }).collect();
        let mut stream = client.fly(with_token(tokio_stream::iter(requests))).await.unwrap().into_inner();
        let mut streamed = Vec::new();
        while let Some(reply) = stream.message().await.unwrap() {
            streamed.push(reply.action);
        }
        assert_eq!(streamed, expected.iter().map(|e| e.to_vec()).collect::<Vec<_>>());
        // Wrong sizes and non-finite values are refused, naming the problem.
        let refused = client.act(with_token(ActRequest { observation: vec![0.0; 39] })).await.unwrap_err();
        assert_eq!(refused.code(), tonic::Code::InvalidArgument);
        assert!(refused.message().contains("39 values") && refused.message().contains("reads 40"), "{}", refused.message());
        let mut nan = observations[0].clone();
        nan[17] = f32::NAN;
        let refused = client.act(with_token(ActRequest { observation: nan })).await.unwrap_err();
        assert_eq!(refused.code(), tonic::Code::InvalidArgument);
        assert!(refused.message().contains("observation[17]"), "{}", refused.message());
        // Without the token, nothing.
        let refused = client.act(tonic::Request::new(ActRequest { observation: observations[0].clone() })).await.unwrap_err();
        assert_eq!(refused.code(), tonic::Code::Unauthenticated);
    });
}

#[test]
fn the_python_client_gets_the_actions_evaluation_takes() {
    let needs = [Need::Python { modules: &["grpc", "grpc_tools"], packages: "grpcio grpcio-tools" }];
    if !available("the_python_client_gets_the_actions_evaluation_takes", &needs) {
        return;
    }
    let _serial = serial();
    let served = Served::start();
    let rt = tokio::runtime::Runtime::new().unwrap();
    drop(served.client(&rt));
    // The Python client from docs/ gets the same actions, unary and streamed.
    let observations_file = served.dir.path().join("observations.json");
    std::fs::write(&observations_file, serde_json::to_string(&served.observations).unwrap()).unwrap();
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("docs/python/pilot_client.py");
    let out = std::process::Command::new("python3")
        .arg(&script)
        .args([
            "--addr",
            &served.addr,
            "--token-file",
            served.token.to_str().unwrap(),
            "--observations",
            observations_file.to_str().unwrap(),
        ])
        .output()
        .expect("python3 runs");
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let reply: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    for key in ["act", "fly"] {
        let actions: Vec<Vec<f32>> = serde_json::from_value(reply[key].clone()).unwrap();
        assert_eq!(actions, served.expected.iter().map(|e| e.to_vec()).collect::<Vec<_>>(), "python {key}");
    }
}

/// A `DroneState` message of the simulated drone's state.
fn drone_state(body: &sim::quadrotor::BodyState) -> proto::v1::RaceRequest {
    let q = body.attitude;
    proto::v1::RaceRequest {
        kind: Some(proto::v1::race_request::Kind::State(proto::v1::DroneState {
            position: body.position.iter().copied().collect(),
            velocity: body.velocity.iter().copied().collect(),
            orientation: vec![q.w, q.i, q.j, q.k],
            angular_velocity: body.body_rates.iter().copied().collect(),
        })),
    }
}

/// A `RaceStart` with `track_toml`.
fn race_start(track_toml: &str) -> proto::v1::RaceRequest {
    proto::v1::RaceRequest { kind: Some(proto::v1::race_request::Kind::Start(proto::v1::RaceStart { track_toml: track_toml.into() })) }
}

/// The shipped generalist flown through `Pilot/Race` from nothing but the drone's states: the
/// simulator plays the drone, the server keeps the race. Every command equals the action
/// `dronerace eval`'s controller takes at that step, and the flight ends as eval's does.
#[test]
fn the_shipped_generalist_races_from_drone_states_as_eval_flies_it_step_for_step() {
    let _serial = serial();
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let (policy_path, track_path) = (root.join("policies/generalist.bin"), root.join("tracks/figure8.toml"));
    let dir = tempfile::tempdir().unwrap();
    let addr = format!("127.0.0.1:{}", free_port());
    let server = Proc::start(
        dir.path(),
        "serve",
        &args(&["serve", "--policy", policy_path.to_str().unwrap(), "--listen", &addr, "--track", track_path.to_str().unwrap()]),
    );
    let rt = tokio::runtime::Runtime::new().unwrap();
    let channel = tonic::transport::Endpoint::from_shared(format!("http://{addr}")).unwrap();
    let mut client = None;
    wait_until(Duration::from_secs(30), "the pilot server answers", &[&server], || {
        client = rt.block_on(channel.connect()).ok().map(PilotClient::new);
        client.is_some()
    });
    let mut client = client.unwrap();
    // Eval's deterministic flights of Figure8, from the same track file's text.
    let text = std::fs::read_to_string(&track_path).unwrap();
    let track = Arc::new(racetracks::parse_track(&text, &track_path).unwrap());
    let blob = learner::checkpoint::read_policy(&policy_path).unwrap();
    let policy = Arc::new(Policy::from_blob(&blob).unwrap());
    let config = sim::eval::EvalConfig::default();
    // The first of eval's deployments that completes a lap, so that lap counting is exercised.
    let (stream, reference) = (0..config.runs as u64)
        .map(|k| (k, sim::eval::deploy(track.clone(), &mut PolicyController::new(policy.clone()), &config, k)))
        .find(|(_, d)| d.success)
        .expect("the generalist completes a lap of Figure8 in some deployment");
    let mut env_config = config.env;
    env_config.race.max_episode_steps = config.steps;
    let mut env = RaceEnv::new(track, env_config, config.seed, stream);
    let mut controller = PolicyController::new(policy);
    rt.block_on(async {
        let (tx, rx) = tokio::sync::mpsc::channel(4);
        let mut commands = client.race(tokio_stream::wrappers::ReceiverStream::new(rx)).await.unwrap().into_inner();
        tx.send(race_start(&text)).await.unwrap();
        for step in 0..config.steps {
            tx.send(drone_state(env.body())).await.unwrap();
            let command = commands.message().await.unwrap().expect("a command per state");
            assert_eq!(command.action, controller.act(&env).to_vec(), "step {step}");
            assert_eq!((command.target_gate as usize, command.laps), (env.target_gate(), env.stats().laps), "step {step}");
            let action: [f32; 4] = command.action.as_slice().try_into().unwrap();
            if env.step(&action).done() {
                break;
            }
        }
        assert_eq!((env.stats().length, env.stats().laps as usize), (reference.steps, reference.lap_times.len()), "the flight eval flew");
        // The server's own track when the start names none: the same first command.
        let (tx, rx) = tokio::sync::mpsc::channel(4);
        let mut commands = client.race(tokio_stream::wrappers::ReceiverStream::new(rx)).await.unwrap().into_inner();
        tx.send(race_start("")).await.unwrap();
        let start = RaceEnv::new(Arc::new(racetracks::parse_track(&text, &track_path).unwrap()), env_config, config.seed, stream);
        tx.send(drone_state(start.body())).await.unwrap();
        let first = commands.message().await.unwrap().unwrap();
        assert_eq!(first.action, PolicyController::new(Arc::new(Policy::from_blob(&blob).unwrap())).act(&start).to_vec());
        // Refusals name what is wrong, and end the stream.
        let body = *start.body();
        let mut short = drone_state(&body);
        if let Some(proto::v1::race_request::Kind::State(s)) = &mut short.kind {
            s.position.pop();
        }
        let mut nan = drone_state(&body);
        if let Some(proto::v1::race_request::Kind::State(s)) = &mut nan.kind {
            s.velocity[1] = f64::NAN;
        }
        let cases = [
            (vec![drone_state(&body)], "before any RaceStart"),
            (vec![race_start(""), short], "DroneState.position has 2 numbers"),
            (vec![race_start(""), nan], "DroneState.velocity[1]"),
            (vec![race_start("name = \"broken\"\n")], "RaceStart.track_toml"),
        ];
        for (messages, expected) in cases {
            let status = client.race(tokio_stream::iter(messages)).await.unwrap().into_inner().message().await.unwrap_err();
            assert_eq!(status.code(), tonic::Code::InvalidArgument, "{expected}: {status:?}");
            assert!(status.message().contains(expected), "{expected}: {}", status.message());
        }
    });
}

/// The Python closed loop of `docs/python/race_closed_loop.py`: the `dronerace` package plays
/// the drone from eval's first start, `Pilot/Race` serves the shipped generalist, and the flight
/// laps Figure8 as `dronerace eval`'s deployment 0 does.
#[test]
fn a_python_closed_loop_through_pilot_race_laps_as_eval_flies() {
    let needs = [Need::Python { modules: &["dronerace", "grpc", "grpc_tools"], packages: "./python grpcio grpcio-tools" }];
    if !available("a_python_closed_loop_through_pilot_race_laps_as_eval_flies", &needs) {
        return;
    }
    let _serial = serial();
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let (policy_path, track_path) = (root.join("policies/generalist.bin"), root.join("tracks/figure8.toml"));
    let dir = tempfile::tempdir().unwrap();
    let addr = format!("127.0.0.1:{}", free_port());
    let server = Proc::start(dir.path(), "serve", &args(&["serve", "--policy", policy_path.to_str().unwrap(), "--listen", &addr]));
    let rt = tokio::runtime::Runtime::new().unwrap();
    let channel = tonic::transport::Endpoint::from_shared(format!("http://{addr}")).unwrap();
    wait_until(Duration::from_secs(30), "the pilot server answers", &[&server], || rt.block_on(channel.connect()).is_ok());
    let track = Arc::new(racetracks::read_track(&track_path).unwrap());
    let policy = Arc::new(Policy::from_blob(&learner::checkpoint::read_policy(&policy_path).unwrap()).unwrap());
    let config = sim::eval::EvalConfig::default();
    let reference = sim::eval::deploy(track, &mut PolicyController::new(policy), &config, 0);
    assert!(reference.success && reference.lap_times.len() >= 2, "{reference:?}");
    let script = root.join("docs/python/race_closed_loop.py");
    let out = std::process::Command::new("python3")
        .arg(&script)
        .args(["--addr", &addr, "--track", track_path.to_str().unwrap(), "--steps", &config.steps.to_string()])
        .output()
        .expect("python3 runs");
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let flown: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    let fastest = reference.lap_times.iter().copied().fold(f64::INFINITY, f64::min);
    assert_eq!(flown["outcome"], "time_limit", "{flown}");
    assert_eq!(flown["laps"].as_u64(), Some(reference.lap_times.len() as u64), "{flown}");
    assert_eq!(flown["served_laps"], flown["laps"], "the server counted the laps the simulator did: {flown}");
    assert_eq!(flown["fastest_lap"].as_f64(), Some(fastest), "{flown}");
    assert_eq!(flown["steps"].as_u64(), Some(u64::from(reference.steps)), "{flown}");
}

/// A track file of `gates` gates in a row, 3 m apart, in an arena that holds them.
fn track_of(gates: usize) -> String {
    let rows: String = (0..gates).map(|i| format!("[[gate]]\nposition = [{}.0, 0.0, 2.0]\nyaw_deg = 0.0\n", 3 * i)).collect();
    format!("{rows}[arena]\nmin = [-10.0, -10.0, 0.0]\nmax = [{}.0, 10.0, 6.0]\n", 3 * gates + 10)
}

/// The Race message that stalled `serve` (a 20,000-gate, 1 MB track: its racing line is
/// O(gates²) and was built on the only async worker, > 75 s, SIGTERM ignored) is refused at
/// once naming the bound; while the largest admitted tracks are being started on several
/// streams, the server keeps answering within a second; races beyond the bound are refused
/// rather than held; refusals quote a bounded part of what was sent.
#[test]
fn a_hostile_race_start_is_refused_and_the_server_keeps_answering() {
    let _serial = serial();
    let served = Served::start();
    let rt = tokio::runtime::Runtime::new().unwrap();
    let mut client = served.client(&rt);
    let refusal = |mut client: PilotClient<tonic::transport::Channel>, toml: String| async move {
        let mut stream = client.race(with_token(tokio_stream::iter([race_start(&toml)]))).await.unwrap().into_inner();
        stream.message().await.unwrap_err()
    };
    rt.block_on(async {
        let huge = refusal(client.clone(), track_of(20_000)).await;
        assert_eq!(huge.code(), tonic::Code::InvalidArgument);
        assert!(huge.message().contains("more than the 65536 a track file may have"), "{}", huge.message());
        let many = refusal(client.clone(), track_of(65)).await;
        assert!(many.message().contains("at most 64 gates, found 65"), "{}", many.message());
        // An error that would quote a 60 kB line quotes at most 1 kB of it.
        let echo = refusal(client.clone(), format!("name = \"{}", "x".repeat(60_000))).await;
        assert_eq!(echo.code(), tonic::Code::InvalidArgument);
        assert!(echo.message().len() <= transport::refusal::MAX_STATUS_MESSAGE, "{} bytes", echo.message().len());

        // Sixteen streams (each on a connection of its own: a connection takes 16 streams at
        // most) start the largest admitted track; the server answers meanwhile.
        let url = format!("http://{}", served.addr);
        let mut races = Vec::new();
        for _ in 0..16 {
            let (tx, rx) = tokio::sync::mpsc::channel(4);
            tx.send(race_start(&track_of(64))).await.unwrap();
            let mut own = PilotClient::connect(url.clone()).await.unwrap();
            let reply = own.race(with_token(tokio_stream::wrappers::ReceiverStream::new(rx))).await.unwrap().into_inner();
            races.push((tx, reply));
        }
        let asked = std::time::Instant::now();
        let answer = tokio::time::timeout(Duration::from_secs(1), client.describe(with_token(DescribeRequest {}))).await;
        assert!(matches!(answer, Ok(Ok(_))), "Describe while 16 races start: {answer:?} after {:?}", asked.elapsed());
        // Up to the bound of 32 races at once; the 33rd is refused, not queued.
        for _ in 16..32 {
            let (tx, rx) = tokio::sync::mpsc::channel(4);
            let mut own = PilotClient::connect(url.clone()).await.unwrap();
            races.push((tx, own.race(with_token(tokio_stream::wrappers::ReceiverStream::new(rx))).await.unwrap().into_inner()));
        }
        let (_tx, rx) = tokio::sync::mpsc::channel::<proto::v1::RaceRequest>(1);
        let full = client.race(with_token(tokio_stream::wrappers::ReceiverStream::new(rx))).await.unwrap_err();
        assert_eq!(full.code(), tonic::Code::ResourceExhausted, "{full:?}");
        // A race that ends gives its place back.
        drop(races.pop());
        let taken = wait_for_place(&mut client).await;
        assert!(taken, "no place after a race ended");
    });
}

/// Whether a new race is taken within a few seconds (an ended stream's place comes back once
/// the server sees it close).
async fn wait_for_place(client: &mut PilotClient<tonic::transport::Channel>) -> bool {
    for _ in 0..50 {
        let (tx, rx) = tokio::sync::mpsc::channel::<proto::v1::RaceRequest>(1);
        if client.race(with_token(tokio_stream::wrappers::ReceiverStream::new(rx))).await.is_ok() {
            drop(tx);
            return true;
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    false
}
