//! Policy files and checkpoints open in Python: `docs/python/open_policy.py` loads them with the
//! `safetensors` package, acts in numpy, and must agree with dronerace's own inference.
//! Needs `python3` with numpy and safetensors (`.ci/run` installs them).

// Test code: a panic is how a failure is reported.
#![allow(clippy::unwrap_used, clippy::expect_used)]

use std::path::Path;
use std::process::Command;

use learner::checkpoint::Checkpoint;
use policy::{ActorCritic, Architecture, ObsNormalizer, Policy, WeightsBlob};
use rand::{Rng, SeedableRng};

fn python_check(policy: &Path, expected: &Path) -> String {
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("docs/python/open_policy.py");
    let out = Command::new("python3")
        .arg(&script)
        .arg(policy)
        .arg("--check")
        .arg(expected)
        .output()
        .expect("python3 runs (install it, with `pip install numpy safetensors`, or run .ci/run)");
    let text = format!("{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
    assert!(out.status.success(), "{} {}:\n{text}", script.display(), policy.display());
    text
}

#[test]
fn a_policy_and_a_checkpoint_act_the_same_in_numpy_as_in_dronerace() {
    let dir = tempfile::tempdir().unwrap();
    let arch = Architecture { hidden: vec![16, 8], negative_slope: 0.2, ..Architecture::cpu() };
    let model = ActorCritic::new(&arch, -0.5, 3, &policy::Device::flex());
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(4);
    let mut normalizer = ObsNormalizer::new(arch.observation_dim);
    let sample: Vec<f32> = (0..arch.observation_dim * 50).map(|_| rng.random_range(-3.0..3.0)).collect();
    normalizer.update(&sample);
    let blob = WeightsBlob::from_model(12, &arch, &normalizer, &model);
    // Observations beyond the normaliser's clip too, so clipping is checked.
    let observations: Vec<f32> = (0..arch.observation_dim * 5).map(|_| rng.random_range(-20.0..20.0)).collect();
    let (means, values) = Policy::from_blob(&blob).unwrap().means_and_values(&observations);
    let expected = serde_json::json!({
        "observations": observations.chunks(arch.observation_dim).collect::<Vec<_>>(),
        "means": means.chunks(arch.action_dim).collect::<Vec<_>>(),
        "values": values,
    });
    let expected_path = dir.path().join("expected.json");
    std::fs::write(&expected_path, expected.to_string()).unwrap();

    let policy_path = dir.path().join("policy.bin");
    std::fs::write(&policy_path, blob.to_bytes()).unwrap();
    let report = python_check(&policy_path, &expected_path);
    assert!(report.contains("policy version 12") && report.contains("actor.2.weight"), "{report}");

    let mut checkpoint = Checkpoint::default();
    checkpoint.put("weights", blob.to_bytes());
    checkpoint.put("optimizer", vec![0xfe; 100]);
    checkpoint.put("learner", br#"{"version":12}"#.to_vec());
    let checkpoint_path = dir.path().join("ckpt.bin");
    checkpoint.write(&checkpoint_path).unwrap();
    python_check(&checkpoint_path, &expected_path);

    // And the check can fail: a policy with other weights does not pass.
    let other = WeightsBlob::from_model(12, &arch, &normalizer, &ActorCritic::new(&arch, -0.5, 4, &policy::Device::flex()));
    std::fs::write(&policy_path, other.to_bytes()).unwrap();
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("docs/python/open_policy.py");
    let status = Command::new("python3").arg(script).arg(&policy_path).arg("--check").arg(&expected_path).output().unwrap().status;
    assert!(!status.success(), "different weights must not match");
}
