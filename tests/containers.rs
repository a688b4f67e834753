//! The compose stack for real, in CI's short version: `deploy/compose-test.sh` with an image
//! around the binary these tests built (`--target prebuilt`, so nothing compiles inside a
//! container): task controller, learner and two actors over gRPC with TLS and a token train
//! three iterations, a client container reads Learner/Status and ListTasks, the learner
//! container is stopped and started and resumes from its volume, and teardown leaves nothing.
//! The whole version (image compiled from source) is `deploy/compose-test.sh` without an
//! argument. Needs root, podman, runc, debootstrap and podman-compose (`tests/run.sh` installs them).

// Test code: a panic is how a failure is reported.
#![allow(clippy::unwrap_used, clippy::expect_used)]

mod support;

use std::path::Path;
use std::process::Command;

use support::prerequisites::{Need, available};

#[test]
fn compose_stack_trains_resumes_from_its_volume_and_tears_down() {
    let needs = [
        Need::Root,
        Need::Program { name: "podman", install: "apt-get install podman" },
        Need::Program { name: "runc", install: "apt-get install runc" },
        Need::Program { name: "debootstrap", install: "apt-get install debootstrap" },
        Need::Program { name: "podman-compose", install: "pip install podman-compose==1.5.0" },
    ];
    if !available("compose_stack_trains_resumes_from_its_volume_and_tears_down", &needs) {
        return;
    }
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("deploy/compose-test.sh");
    let out = Command::new("bash").arg(script).arg(env!("CARGO_BIN_EXE_dronerace")).output().expect("bash runs deploy/compose-test.sh");
    let text = format!("{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
    assert!(out.status.success(), "{text}");
    for line in [
        "ListTasks: 96 environments on actor-0 and actor-1",
        "resumed from its volume",
        "no containers, volumes or networks left",
        "compose-test: passed",
    ] {
        assert!(text.contains(line), "missing {line:?} in:\n{text}");
    }
}
