//! The Kubernetes manifests validate against the Kubernetes schemas and keep the deployment
//! rules (non-root, resources, native gRPC probes, volumes, Secret, actors spread), checked by
//! `deploy/check-k8s.py`; and the check fails on a manifest that breaks them. Needs `python3`
//! with kubernetes-validate (`tests/run.sh` installs it).

// Test code: a panic is how a failure is reported.
#![allow(clippy::unwrap_used, clippy::expect_used)]

mod support;

use std::path::Path;
use std::process::{Command, Output};

use support::prerequisites::{Need, available};

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
        .replace("livenessProbe: { grpc: { port: 50052 }, initialDelaySeconds: 60, periodSeconds: 15, failureThreshold: 4 }", "")
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
}
