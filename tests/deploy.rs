//! The Kubernetes manifests validate against the Kubernetes schemas and keep the deployment
//! rules (non-root, resources, native gRPC probes on the plaintext health port, volumes,
//! Secret, actors spread), checked by `deploy/check-k8s.py`; the check fails on a manifest that
//! breaks them (needs `python3` with kubernetes-validate, which `tests/run.sh` installs). And
//! the manifests' probes, asked as the kubelet asks them, pass against servers that speak only
//! TLS (needs `openssl`).

// Test code: a panic is how a failure is reported.
#![allow(clippy::unwrap_used, clippy::expect_used)]

mod support;

use std::path::Path;
use std::process::{Command, Output};
use std::time::Duration;

use support::prerequisites::{Need, available};
use support::{Proc, args, free_port, wait_until, write_config};
use tonic_health::pb::HealthCheckRequest;
use tonic_health::pb::health_check_response::ServingStatus;
use tonic_health::pb::health_client::HealthClient;

fn check(files: &[&Path]) -> Output {
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("deploy/check-k8s.py");
    Command::new("python3").arg(script).args(files).output().expect("python3 runs")
}

#[test]
fn kubernetes_manifests_validate_and_a_broken_one_does_not() {
    let needs = [Need::Python { modules: &["kubernetes_validate", "yaml"], packages: "kubernetes-validate" }];
    if !available("kubernetes_manifests_validate_and_a_broken_one_does_not", &needs) {
        return;
    }
    let manifest = Path::new(env!("CARGO_MANIFEST_DIR")).join("deploy/k8s/dronerace.yaml");
    let o = check(&[&manifest]);
    let text = format!("{}{}", String::from_utf8_lossy(&o.stdout), String::from_utf8_lossy(&o.stderr));
    assert!(o.status.success() && text.contains("0 failures"), "{text}");
    // The same manifest without the liveness probe of the learner and with an unknown field.
    let original = std::fs::read_to_string(&manifest).unwrap();
    let broken = original
        .replace(
            "livenessProbe: { grpc: { port: 8081, service: dronerace.v1.Learner }, initialDelaySeconds: 60, periodSeconds: 15, failureThreshold: 4 }",
            "",
        )
        .replace("readinessProbe: { grpc: { port: 8081, service: dronerace.v1.TaskController }", "readinessProbe: { grpc: { port: 50051, service: dronerace.v1.TaskController }")
        .replace("podManagementPolicy: Parallel", "podManagementPolicy: Parallel\n  replica: 3");
    assert_ne!(broken, original);
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("broken.yaml");
    std::fs::write(&path, broken).unwrap();
    let o = check(&[&path]);
    let text = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success(), "{text}");
    assert!(text.contains("learner: serves gRPC but has no native gRPC livenessProbe"), "{text}");
    assert!(text.contains("StatefulSet/actor") && text.contains("replica"), "{text}");
    assert!(text.contains("taskctl: readinessProbe asks port 50051"), "a probe on the TLS port is refused: {text}");
}

/// `(port, service)` of every native gRPC probe in the manifest, and the ports given to
/// `--health-listen`.
fn probes_and_health_ports(manifest: &str) -> (Vec<(u16, String)>, Vec<u16>) {
    let mut probes = Vec::new();
    for line in manifest.lines().filter(|l| l.contains("Probe: { grpc: {")) {
        let after = |key: &str| line.split(key).nth(1).map(|rest| rest.split([',', ' ', '}']).next().unwrap_or("").to_string());
        let port = after("port: ").expect("every probe names its port").parse().unwrap();
        probes.push((port, after("service: ").unwrap_or_default()));
    }
    let health = manifest
        .split("--health-listen, \"")
        .skip(1)
        .map(|rest| rest.split('"').next().unwrap().rsplit(':').next().unwrap().parse().unwrap())
        .collect();
    (probes, health)
}

/// The kubelet's native gRPC probe: `grpc.health.v1.Health/Check` for `service`, in plaintext.
fn probe(rt: &tokio::runtime::Runtime, port: u16, service: &str) -> Result<ServingStatus, String> {
    rt.block_on(async {
        let ask = async {
            let endpoint = tonic::transport::Endpoint::from_shared(format!("http://127.0.0.1:{port}")).map_err(|e| e.to_string())?;
            let mut client = HealthClient::new(endpoint.connect().await.map_err(|e| e.to_string())?);
            let answer = client.check(HealthCheckRequest { service: service.into() }).await.map_err(|s| s.to_string())?;
            Ok::<_, String>(answer.into_inner().status())
        };
        tokio::time::timeout(Duration::from_secs(3), ask).await.map_err(|_| "no answer within 3 s".to_string())?
    })
}

#[test]
fn the_manifests_probes_pass_against_servers_that_speak_only_tls() {
    let needs = [Need::Program { name: "openssl", install: "apt-get install openssl" }];
    if !available("the_manifests_probes_pass_against_servers_that_speak_only_tls", &needs) {
        return;
    }
    let _serial = support::serial();
    let manifest = std::fs::read_to_string(Path::new(env!("CARGO_MANIFEST_DIR")).join("deploy/k8s/dronerace.yaml")).unwrap();
    let (probes, health_ports) = probes_and_health_ports(&manifest);
    assert_eq!(probes.len(), 4, "readiness and liveness of the task controller and the learner: {probes:?}");
    for (port, _) in &probes {
        assert!(health_ports.contains(port), "probe on port {port}, which is not a --health-listen port {health_ports:?}");
    }
    // The two servers as the manifests run them (TLS and a token), on local ports.
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    support::certificates::make(d, "IP:127.0.0.1");
    std::fs::write(d.join("token"), "probe-test-token\n").unwrap();
    let network = format!(
        "[network]\ntoken_file = \"{0}/token\"\ntls_cert = \"{0}/server.pem\"\ntls_key = \"{0}/server.key\"\ntls_ca = \"{0}/ca.pem\"\n",
        d.display()
    );
    let config = write_config(d, &network).display().to_string();
    let (tasks_port, tasks_health, learner_port, learner_health) = (free_port(), free_port(), free_port(), free_port());
    let at = |port: u16| format!("127.0.0.1:{port}");
    let snapshot = d.join("taskctl.snapshot").display().to_string();
    let run = d.join("run").display().to_string();
    let taskctl = Proc::start(
        d,
        "taskctl",
        &args(&[
            "taskctl",
            "--config",
            &config,
            "--listen",
            &at(tasks_port),
            "--snapshot",
            &snapshot,
            "--health-listen",
            &at(tasks_health),
        ]),
    );
    let learner = Proc::start(
        d,
        "learner",
        &args(&[
            "learner",
            "--config",
            &config,
            "--out",
            &run,
            "--listen",
            &at(learner_port),
            "--transport",
            "grpc",
            "--health-listen",
            &at(learner_health),
        ]),
    );
    let rt = tokio::runtime::Builder::new_current_thread().enable_all().build().unwrap();
    let local =
        |service: &str| if service.ends_with("TaskController") { (tasks_port, tasks_health) } else { (learner_port, learner_health) };
    for (_, service) in &probes {
        let (tls_port, health_port) = local(service);
        wait_until(Duration::from_secs(90), &format!("{service} SERVING on its health port"), &[&taskctl, &learner], || {
            probe(&rt, health_port, service) == Ok(ServingStatus::Serving)
        });
        // What the manifests probed before: the TLS port, which a plaintext probe cannot reach.
        assert!(probe(&rt, tls_port, service).is_err(), "{service}: a plaintext probe must not pass on the TLS port");
    }
    assert_eq!(probe(&rt, tasks_health, "dronerace.v1.Learner").ok(), None, "each health port knows its own service only");
}
