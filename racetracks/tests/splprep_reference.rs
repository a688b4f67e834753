//! The closed smoothing spline equals `scipy.interpolate.splprep(P_closed.T, s=s, per=1, k=3)`
//! on every case of the reference vectors (`tests/data/splprep_periodic.json`, generated with
//! scipy 1.17.1; a copy of the project's shared reference file).

// Test code: a panic is how a failure is reported.
#![allow(clippy::unwrap_used, clippy::expect_used, clippy::print_stdout, clippy::print_stderr)]

use racetracks::spline::fit_closed_curve;
use serde_json::Value;
use sim::nalgebra::Vector3;

fn cases() -> Vec<Value> {
    let text = include_str!("data/splprep_periodic.json");
    let reference: Value = serde_json::from_str(text).unwrap();
    reference["cases"].as_array().unwrap().clone()
}

fn floats(v: &Value) -> Vec<f64> {
    v.as_array().unwrap().iter().map(|x| x.as_f64().unwrap()).collect()
}

fn points(v: &Value) -> Vec<Vector3<f64>> {
    v.as_array().unwrap().iter().map(|p| Vector3::from_vec(floats(p))).collect()
}

fn assert_close(what: &str, case: usize, got: &[f64], want: &[f64], tolerance: f64) {
    assert_eq!(got.len(), want.len(), "case {case}: {what} length");
    for (i, (g, w)) in got.iter().zip(want).enumerate() {
        assert!((g - w).abs() <= tolerance, "case {case}: {what}[{i}] = {g}, scipy {w} (Δ {:e})", (g - w).abs());
    }
}

#[test]
fn knots_coefficients_and_points_match_scipy() {
    let cases = cases();
    assert_eq!(cases.len(), 14);
    for (n, case) in cases.iter().enumerate() {
        let s = case["s"].as_f64().unwrap();
        let fit = fit_closed_curve(&points(&case["control_points"]), s).unwrap();
        assert_close("u", n, &fit.u, &floats(&case["u"]), 1e-12);
        assert_close("knots", n, &fit.curve.knots, &floats(&case["knots"]), 1e-6);
        for (d, want) in case["coefficients"].as_array().unwrap().iter().enumerate() {
            assert_close("coefficients", n, &fit.curve.coefficients[d], &floats(want), 1e-6);
        }
        let params = floats(&case["eval_params"]);
        for (u, want) in params.iter().zip(points(&case["eval_points"])) {
            let got = fit.curve.point(*u);
            assert!((got - want).amax() <= 1e-6, "case {n}: point at {u}: {got:?} vs {want:?}");
        }
    }
}

#[test]
fn arc_length_and_equal_arc_gates_match_the_reference() {
    for (n, case) in cases().iter().enumerate() {
        let fit = fit_closed_curve(&points(&case["control_points"]), case["s"].as_f64().unwrap()).unwrap();
        let want_length = case["arc_length"].as_f64().unwrap();
        let length = fit.curve.arc_length(fit.curve.start(), fit.curve.end());
        // The reference integrated with a dense trapezoid rule; ours is piecewise Gauss–Legendre.
        assert!((length - want_length).abs() < 1e-6, "case {n}: arc length {length} vs {want_length}");
        let gates = racetracks::generator::place_gates(&fit.curve, 6, [1.0, 5.0]);
        for (i, (gate, want)) in gates.iter().zip(case["gates"].as_array().unwrap()).enumerate() {
            let position = Vector3::from_vec(floats(&want["position"]));
            assert!((gate.position - position).norm() < 1e-3, "case {n} gate {i}: {:?} vs {position:?}", gate.position);
            let yaw = want["yaw_rad"].as_f64().unwrap();
            let dyaw = (gate.yaw - yaw + std::f64::consts::PI).rem_euclid(std::f64::consts::TAU) - std::f64::consts::PI;
            assert!(dyaw.abs() < 1e-3, "case {n} gate {i}: yaw {} vs {yaw}", gate.yaw);
        }
    }
}
