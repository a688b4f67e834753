//! One binary for every x86-64 CPU: the matrix kernels under every product of the gradient step
//! (the dense layers, burn's products, the vision CNN's convolutions) are chosen at run time —
//! AVX-512 where the CPU has it, AVX2/FMA otherwise — and both give the same step. The AVX2 path
//! is forced by running this test again under qemu's user-mode emulator as a CPU without
//! AVX-512 (Haswell); the two gradients must agree to float tolerance.

// Test code: a panic is how a failure is reported.
#![allow(clippy::unwrap_used, clippy::expect_used)]

mod support;

use std::process::Command;

use support::prerequisites::{Need, available};

/// Set in the emulated run: where it writes its gradients.
const CHILD_OUTPUT: &str = "DRONERACE_KERNELS_OUTPUT";

/// What one run computes: whether its CPU has AVX-512, and the gradients of one PPO minibatch
/// step of the cpu profile's MLP (512 samples) and of the vision agent (16 samples).
fn step() -> serde_json::Value {
    let device = policy::Device::flex().autodiff();
    let profile = learner::Profile::cpu().default_learner();
    serde_json::json!({
        "avx512f": std::arch::is_x86_feature_detected!("avx512f"),
        "state": learner::bench::gradient(&profile, 512, false, &device),
        "vision": learner::bench::gradient(&profile, 16, true, &device),
    })
}

/// The largest difference between `a` and `b` relative to the largest magnitude in `a`.
fn relative_difference(a: &[f32], b: &[f32]) -> f32 {
    assert_eq!(a.len(), b.len());
    let scale = a.iter().fold(0.0f32, |m, x| m.max(x.abs()));
    assert!(scale > 0.0, "a zero gradient tells nothing");
    a.iter().zip(b).map(|(x, y)| (x - y).abs()).fold(0.0, f32::max) / scale
}

#[test]
fn the_avx2_fallback_gives_the_same_gradient_step_as_the_cpus_own_kernels() {
    if let Some(path) = std::env::var_os(CHILD_OUTPUT) {
        std::fs::write(path, step().to_string()).unwrap();
        return;
    }
    let needs = [Need::Program { name: "qemu-x86_64", install: "apt-get install qemu-user" }];
    if !available("the_avx2_fallback_gives_the_same_gradient_step_as_the_cpus_own_kernels", &needs) {
        return;
    }
    let native = step();
    let dir = tempfile::tempdir().unwrap();
    let output = dir.path().join("emulated.json");
    let run = Command::new("qemu-x86_64")
        .args(["-cpu", "Haswell"])
        .arg(std::env::current_exe().unwrap())
        .args(["--exact", "the_avx2_fallback_gives_the_same_gradient_step_as_the_cpus_own_kernels", "--test-threads", "1"])
        .env(CHILD_OUTPUT, &output)
        .output()
        .unwrap();
    assert!(run.status.success(), "{}{}", String::from_utf8_lossy(&run.stdout), String::from_utf8_lossy(&run.stderr));
    let emulated: serde_json::Value = serde_json::from_slice(&std::fs::read(&output).unwrap()).unwrap();
    assert_eq!(emulated["avx512f"], false, "the emulated CPU must lack AVX-512, so it runs the fallback");
    for agent in ["state", "vision"] {
        let a: Vec<f32> = serde_json::from_value(native[agent].clone()).unwrap();
        let b: Vec<f32> = serde_json::from_value(emulated[agent].clone()).unwrap();
        // Different kernels sum in different orders: equal to float rounding, not bit for bit.
        let difference = relative_difference(&a, &b);
        assert!(difference < 1e-5, "{agent}: the two kernels' gradients differ by {difference:e} of the largest");
    }
}
