//! Generated tracks satisfy every constraint of SPEC §7 across thousands of seeds, for both
//! generators, and are valid track files.

// Test code: a panic is how a failure is reported.
#![allow(clippy::unwrap_used, clippy::expect_used, clippy::print_stdout, clippy::print_stderr)]

use racetracks::generator::{GeneratorKind, TrackGenParams, TrackGenerator};
use sim::nalgebra::Vector3;

const SEEDS: u64 = 2000;

fn check(kind: GeneratorKind) -> usize {
    let params = TrackGenParams::default();
    let generator = TrackGenerator { kind, params };
    let b = params.bounds;
    let pad = params.boundary_padding;
    let mut attempts = 0;
    for seed in 0..SEEDS {
        let g = generator.generate(seed, "t").unwrap_or_else(|e| panic!("{e}"));
        attempts += g.attempts;
        let t = &g.track;
        assert_eq!(t.gates.len(), params.gates);
        t.validate().unwrap();
        for (i, a) in t.gates.iter().enumerate() {
            assert!(a.position.x >= b.min.x + pad && a.position.x <= b.max.x - pad, "seed {seed} gate {i} x");
            assert!(a.position.y >= b.min.y + pad && a.position.y <= b.max.y - pad, "seed {seed} gate {i} y");
            assert!(a.position.z >= b.min.z + 1.0 && a.position.z <= b.max.z - 1.0, "seed {seed} gate {i} z");
            for c in &t.gates[i + 1..] {
                assert!((a.position - c.position).norm() >= params.min_gate_spacing, "seed {seed} spacing");
            }
        }
        let g0 = &t.gates[0];
        assert!((t.start.position - (g0.position - g0.normal() * 2.0)).norm() < 1e-12, "seed {seed} start");
        assert_eq!(t.start.yaw, g0.yaw);
        assert!(b.contains(&t.start.position), "seed {seed} start inside B");
        if kind == GeneratorKind::Informed {
            let points = &g.control_points;
            assert_eq!(points.len(), params.control_points);
            let mean = points.iter().sum::<Vector3<f64>>() / points.len() as f64;
            assert!((mean - b.centre()).norm() < 1e-9, "seed {seed}: control points re-centred");
            for (i, p) in points.iter().enumerate() {
                for q in &points[i + 1..] {
                    assert!((p.xy() - q.xy()).norm() >= params.min_control_spacing - 1e-9, "seed {seed} control spacing");
                }
            }
        }
    }
    attempts
}

#[test]
fn informed_tracks_meet_every_constraint() {
    let attempts = check(GeneratorKind::Informed);
    assert!(attempts >= SEEDS as usize);
}

#[test]
fn uniform_tracks_meet_every_constraint() {
    check(GeneratorKind::Uniform);
}
