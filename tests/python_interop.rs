//! Policy files and checkpoints open in Python: `docs/python/open_policy.py` loads them with the
//! `safetensors` package, acts in numpy, and must agree with dronerace's own inference.
//! Needs `python3` with numpy, safetensors and onnxruntime (`tests/run.sh` installs them).

// Test code: a panic is how a failure is reported.
#![allow(clippy::unwrap_used, clippy::expect_used)]

mod support;

use policy::NetworkBlob;
use std::path::Path;
use std::process::Command;

use learner::checkpoint::Checkpoint;
use policy::{ActorCritic, Architecture, ObsNormalizer, Policy, WeightsBlob};
use rand::{Rng, SeedableRng};
use support::prerequisites::{Need, available};

fn python_check(policy: &Path, expected: &Path) -> String {
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("docs/python/open_policy.py");
    let out = Command::new("python3").arg(&script).arg(policy).arg("--check").arg(expected).output().expect("python3 runs");
    let text = format!("{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
    assert!(out.status.success(), "{} {}:\n{text}", script.display(), policy.display());
    text
}

#[test]
fn a_policy_and_a_checkpoint_act_the_same_in_numpy_as_in_dronerace() {
    let needs = [Need::Python { modules: &["numpy", "safetensors"], packages: "numpy safetensors" }];
    if !available("a_policy_and_a_checkpoint_act_the_same_in_numpy_as_in_dronerace", &needs) {
        return;
    }
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

/// Runs `docs/python/check_onnx.py` on a model, observations and expected actions.
fn onnx_check(model: &Path, observations: &Path, expected: &Path) -> (bool, String) {
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("docs/python/check_onnx.py");
    let out = Command::new("python3").arg(script).args([model, observations, expected]).output().expect("python3 runs");
    (out.status.success(), format!("{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr)))
}

#[test]
fn an_exported_onnx_actor_acts_as_dronerace_in_onnxruntime() {
    let needs = [Need::Python { modules: &["numpy", "onnxruntime"], packages: "numpy onnxruntime" }];
    if !available("an_exported_onnx_actor_acts_as_dronerace_in_onnxruntime", &needs) {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let arch = Architecture {
        hidden: vec![64, 32],
        negative_slope: 0.2,
        observation: sim::ObservationLayout::spec(sim::ObservationFrame::Heading),
        ..Architecture::cpu()
    };
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(8);
    let mut normalizer = ObsNormalizer::new(arch.observation_dim);
    let sample: Vec<f32> = (0..arch.observation_dim * 200).map(|_| rng.random_range(-3.0..3.0) * 2.0 + 1.0).collect();
    normalizer.update(&sample);
    // A policy head with gain 1 rather than 0.01, so actions spread over [-1, 1] and the clip
    // at ±1 is exercised too.
    let mut model = ActorCritic::new(&arch, -0.5, 5, &policy::Device::flex());
    let mut params = model.export();
    for p in params.iter_mut().take(2 * (arch.hidden.len() + 1)).skip(2 * arch.hidden.len()) {
        p.values.iter_mut().for_each(|v| *v *= 100.0);
    }
    model = ActorCritic::import(&arch, &params, &policy::Device::flex()).unwrap();
    let blob = WeightsBlob::from_model(21, &arch, &normalizer, &model);
    let blob_path = dir.path().join("policy.bin");
    std::fs::write(&blob_path, blob.to_bytes()).unwrap();
    // 1,000 observations, some beyond the normaliser's clip.
    let observations: Vec<f32> = (0..arch.observation_dim * 1000).map(|_| rng.random_range(-25.0..25.0)).collect();
    let (means, _) = Policy::from_blob(&blob).unwrap().means_and_values(&observations);
    let actions: Vec<f32> = means.iter().map(|a| a.clamp(-1.0, 1.0)).collect();
    assert!(actions.iter().filter(|a| a.abs() == 1.0).count() > 100, "the clip is exercised");
    assert!(actions.iter().filter(|a| a.abs() < 0.9).count() > 100, "so is the interior");
    let observations_path = dir.path().join("observations.json");
    let expected_path = dir.path().join("expected.json");
    let rows = |v: &[f32], w: usize| serde_json::to_string(&v.chunks(w).collect::<Vec<_>>()).unwrap();
    std::fs::write(&observations_path, rows(&observations, arch.observation_dim)).unwrap();
    std::fs::write(&expected_path, rows(&actions, arch.action_dim)).unwrap();

    let model_path = dir.path().join("policy.onnx");
    let o = Command::new(env!("CARGO_BIN_EXE_dronerace"))
        .args(["export", blob_path.to_str().unwrap(), "--format", "onnx", "--out", model_path.to_str().unwrap()])
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let (ok, report) = onnx_check(&model_path, &observations_path, &expected_path);
    assert!(ok && report.contains("1000 observations"), "{report}");

    // And the comparison can fail: another policy's actions do not pass.
    let other: Vec<f32> = actions.iter().map(|a| (a * 0.5).clamp(-1.0, 1.0)).collect();
    std::fs::write(&expected_path, rows(&other, arch.action_dim)).unwrap();
    let (ok, report) = onnx_check(&model_path, &observations_path, &expected_path);
    assert!(!ok, "{report}");
}

/// A policy file of format 2 (a 6 KB run of the build before format 3, `tests/data`) converts
/// with `docs/python/upgrade_policy.py`: it reads with its layout in one object and every tensor
/// as it was; a converted or altered file is refused.
#[test]
fn a_format_2_policy_file_upgrades_with_its_tensors_unchanged() {
    let needs = [Need::Python { modules: &["json"], packages: "" }];
    if !available("a_format_2_policy_file_upgrades_with_its_tensors_unchanged", &needs) {
        return;
    }
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let script = root.join("docs/python/upgrade_policy.py");
    let old = root.join("tests/data/policy-format2.bin");
    let dir = tempfile::tempdir().unwrap();
    let upgrade = |from: &Path, to: &Path| Command::new("python3").arg(&script).arg(from).arg(to).output().expect("python3 runs");
    let new = dir.path().join("new.bin");
    let out = upgrade(&old, &new);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    assert!(WeightsBlob::from_bytes(&std::fs::read(&old).unwrap()).is_err(), "this build reads format 3 only");
    let blob = WeightsBlob::from_bytes(&std::fs::read(&new).unwrap()).unwrap();
    let layout = sim::ObservationLayout { line_points: 2, ..sim::ObservationLayout::spec(sim::ObservationFrame::Heading) };
    assert_eq!((blob.architecture.observation, blob.architecture.observation_dim, blob.version), (layout, 46, 1));
    let tensors = |path: &Path| policyfile::safetensors::TensorFile::from_bytes(&std::fs::read(path).unwrap()).unwrap().tensors;
    assert_eq!(tensors(&old), tensors(&new), "every tensor as it was");
    let again = upgrade(&new, &dir.path().join("again.bin"));
    assert!(!again.status.success() && String::from_utf8_lossy(&again.stderr).contains("format 3, not 2"));
    let mut altered = std::fs::read(&old).unwrap();
    *altered.last_mut().unwrap() ^= 1;
    std::fs::write(dir.path().join("altered.bin"), &altered).unwrap();
    let refused = upgrade(&dir.path().join("altered.bin"), &dir.path().join("x.bin"));
    assert!(!refused.status.success() && String::from_utf8_lossy(&refused.stderr).contains("altered"));
}
