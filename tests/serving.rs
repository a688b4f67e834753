//! `dronerace serve`: a policy served over gRPC acts exactly as `dronerace eval`'s controller on
//! the same observations (unary and streamed, from Rust and from the Python client in
//! `docs/python/pilot_client.py`), refuses wrong sizes and non-finite values, and enforces the
//! token. The Python client's test needs `python3` with grpcio and grpcio-tools (`tests/run.sh`
//! installs them); the Rust checks need nothing beyond the build.

// Test code: a panic is how a failure is reported.
#![allow(clippy::unwrap_used, clippy::expect_used)]

mod support;

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
    let arch = Architecture { hidden: vec![32, 32], observation_frame: sim::ObservationFrame::Heading, ..Architecture::cpu() };
    let model = ActorCritic::new(&arch, -0.5, 9, &policy::Device::flex());
    let track = Arc::new(racetracks::library_track("Figure8").unwrap().unwrap());
    let mut env = RaceEnv::new(track, EnvConfig::evaluation(), 0, 0);
    let mut pilot = ReferencePilot::default();
    pilot.reset(&env);
    let mut observations = Vec::new();
    for _ in 0..60 {
        observations.push(env.observation_in(arch.observation_layout()).to_vec());
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
