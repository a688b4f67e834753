//! The reference pilot completes a lap without crashing on at least 7 library tracks: proof
//! that the library is flyable and that pass and lap logic work end to end.

// Test code: a panic is how a failure is reported.
#![allow(clippy::unwrap_used, clippy::expect_used, clippy::print_stdout, clippy::print_stderr)]

use std::sync::Arc;

use sim::eval::{EvalConfig, evaluate};
use sim::{Controller, ReferencePilot};

#[test]
fn reference_pilot_laps_at_least_seven_library_tracks_in_every_deployment() {
    let tracks: Vec<_> = racetracks::library().unwrap().into_iter().map(Arc::new).collect();
    let config = EvalConfig { runs: 5, ..EvalConfig::default() };
    let make = || Box::new(ReferencePilot::default()) as Box<dyn Controller>;
    let report = evaluate("pilot", &tracks, &make, &config);
    let flyable: Vec<&str> = report.tracks.iter().filter(|t| t.success_rate == 1.0).map(|t| t.track.as_str()).collect();
    assert!(flyable.len() >= 7, "only {flyable:?} flyable:\n{}", report.to_markdown());
    for t in &report.tracks {
        for d in t.deployments.iter().filter(|d| d.success) {
            // A lap passes every gate once more after the first pass of gate 0.
            assert!(d.gates_passed as usize > tracks.iter().find(|x| x.name == t.track).unwrap().gates.len());
            assert!(d.fastest_lap().iter().chain(&d.lap_times).all(|l| *l > 1.0));
        }
    }
}
