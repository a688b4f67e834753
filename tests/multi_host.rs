//! A multi-host run on one machine: the task controller and the learner in one network
//! namespace, an actor in each of two others, joined by veth pairs; everything over gRPC with
//! TLS and a bearer token. Needs root and iproute2 (CI runs as root).

// Test code: a panic is how a failure is reported.
#![allow(clippy::unwrap_used, clippy::expect_used, clippy::print_stdout, clippy::print_stderr)]

mod support;

use std::process::Command;
use std::time::Duration;

use support::prerequisites::{Need, available};
use support::*;

/// Network namespaces `<prefix>-hub`, `<prefix>-a`, `<prefix>-b`; removed when dropped.
struct Namespaces {
    prefix: String,
}

fn ip(args: &[&str]) {
    let out = Command::new("ip").args(args).output().expect("running ip (iproute2)");
    assert!(out.status.success(), "ip {}: {}", args.join(" "), String::from_utf8_lossy(&out.stderr));
}

impl Namespaces {
    /// hub ⟷ a over 10.77.1.0/24, hub ⟷ b over 10.77.2.0/24.
    fn create() -> Self {
        let prefix = format!("dr{}", std::process::id() % 100_000);
        let ns = Self { prefix: prefix.clone() };
        let hub = format!("{prefix}-hub");
        ip(&["netns", "add", &hub]);
        ip(&["-n", &hub, "link", "set", "lo", "up"]);
        for (side, net) in [("a", 1), ("b", 2)] {
            let name = format!("{prefix}-{side}");
            let (h, s) = (format!("{prefix}h{side}"), format!("{prefix}s{side}"));
            ip(&["netns", "add", &name]);
            ip(&["-n", &name, "link", "set", "lo", "up"]);
            ip(&["link", "add", &h, "netns", &hub, "type", "veth", "peer", "name", &s, "netns", &name]);
            ip(&["-n", &hub, "addr", "add", &format!("10.77.{net}.1/24"), "dev", &h]);
            ip(&["-n", &name, "addr", "add", &format!("10.77.{net}.2/24"), "dev", &s]);
            ip(&["-n", &hub, "link", "set", &h, "up"]);
            ip(&["-n", &name, "link", "set", &s, "up"]);
        }
        ns
    }

    fn name(&self, which: &str) -> String {
        format!("{}-{which}", self.prefix)
    }
}

impl Drop for Namespaces {
    fn drop(&mut self) {
        for which in ["a", "b", "hub"] {
            let _ = Command::new("ip").args(["netns", "del", &self.name(which)]).status();
        }
    }
}

#[test]
fn actors_in_two_namespaces_train_with_a_learner_in_a_third_over_tls() {
    let needs = [
        Need::Root,
        Need::Program { name: "ip", install: "apt-get install iproute2" },
        Need::Program { name: "openssl", install: "apt-get install openssl" },
    ];
    if !available("actors_in_two_namespaces_train_with_a_learner_in_a_third_over_tls", &needs) {
        return;
    }
    let _serial = serial();
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    support::certificates::make(dir, "IP:10.77.1.1,IP:10.77.2.1,IP:127.0.0.1");
    std::fs::write(dir.join("token"), "multi-host-token\n").unwrap();
    let p = |f: &str| dir.join(f).display().to_string();
    let network = format!(
        "\n[network]\ntoken_file = {:?}\ntls_cert = {:?}\ntls_key = {:?}\ntls_ca = {:?}\n",
        p("token"),
        p("server.pem"),
        p("server.key"),
        p("ca.pem")
    );
    let config = write_config(dir, &network).display().to_string();
    let ns = Namespaces::create();
    let hub = ns.name("hub");
    let in_hub = ["ip", "netns", "exec", hub.as_str()];
    let snapshot = p("taskctl.snapshot");
    let out = p("run");
    let taskctl = Proc::start_wrapped(
        dir,
        "taskctl",
        &in_hub,
        &args(&["taskctl", "--config", &config, "--listen", "0.0.0.0:7051", "--snapshot", &snapshot]),
    );
    let learner = Proc::start_wrapped(
        dir,
        "learner",
        &in_hub,
        &args(&[
            "learner",
            "--config",
            &config,
            "--out",
            &out,
            "--listen",
            "0.0.0.0:7052",
            "--transport",
            "grpc",
            "--actors",
            "2",
            "--iterations",
            "3",
            "--taskctl",
            "https://127.0.0.1:7051",
        ]),
    );
    let mut actors = Vec::new();
    for (side, net) in [("a", 1), ("b", 2)] {
        let namespace = ns.name(side);
        let wrapper = ["ip", "netns", "exec", namespace.as_str()];
        actors.push(Proc::start_wrapped(
            dir,
            &format!("actor-{side}"),
            &wrapper,
            &args(&[
                "actor",
                "--config",
                &config,
                "--name",
                &format!("actor-{side}"),
                "--envs",
                "4",
                "--transport",
                "grpc",
                "--taskctl",
                &format!("https://10.77.{net}.1:7051"),
                "--learner",
                &format!("https://10.77.{net}.1:7052"),
            ]),
        ));
    }
    let mut learner = learner;
    let all = |l: &Proc| -> Vec<String> {
        [&taskctl, l, &actors[0], &actors[1]].iter().map(|p| format!("--- {} ---\n{}", p.name, p.output())).collect()
    };
    let status = learner.wait_exit(Duration::from_secs(180));
    assert!(status.success(), "{}", all(&learner).join("\n"));
    let rows = metrics_rows(&dir.join("run"));
    assert_eq!(rows.len(), 3, "{}", all(&learner).join("\n"));
    // Both remote actors contributed to every update: 2 × 4 environments × 32 steps.
    assert_eq!(rows.last().unwrap().1, 3 * 256, "{}", all(&learner).join("\n"));
    // The actors registered their ranges with the task controller across the namespaces.
    let registered = [&actors[0], &actors[1]].iter().map(|a| a.output()).collect::<String>();
    assert!(registered.contains("environments 0..4") && registered.contains("environments 4..8"), "{registered}");
}
