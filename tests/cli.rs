//! The `dronerace` command end to end: drawings, evaluation outputs, exact replays, and clear
//! errors for bad input files.

// Test code: a panic is how a failure is reported.
#![allow(clippy::unwrap_used, clippy::expect_used, clippy::print_stdout, clippy::print_stderr)]

use std::path::Path;
use std::process::{Command, Output};

fn dronerace(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_dronerace")).args(args).output().expect("run dronerace")
}

fn stderr(o: &Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

fn library_file(name: &str) -> String {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tracks").join(name).display().to_string()
}

/// Width and height from a PNG's IHDR chunk.
fn png_size(path: &Path) -> (u32, u32) {
    let bytes = std::fs::read(path).unwrap();
    assert_eq!(&bytes[..8], b"\x89PNG\r\n\x1a\n", "not a PNG");
    let be = |i: usize| u32::from_be_bytes(bytes[i..i + 4].try_into().unwrap());
    (be(16), be(20))
}

#[test]
fn tracks_show_draws_one_cell_per_track() {
    let dir = tempfile::tempdir().unwrap();
    let one = dir.path().join("one.png");
    let o = dronerace(&["tracks", "show", &library_file("figure8.toml"), "--out", one.to_str().unwrap()]);
    assert!(o.status.success(), "{}", stderr(&o));
    let (w1, h1) = png_size(&one);
    let four = dir.path().join("sub/four.png");
    let files = ["figure8.toml", "bigs.toml", "kidney.toml", "twist.toml"].map(library_file);
    let mut args = vec!["tracks", "show"];
    args.extend(files.iter().map(String::as_str));
    args.extend(["--out", four.to_str().unwrap()]);
    let o = dronerace(&args);
    assert!(o.status.success(), "{}", stderr(&o));
    assert_eq!(png_size(&four), (2 * w1, 2 * h1), "a 2 × 2 grid of cells");
}

/// The racing line's clearance to the frames: the planner keeps its 0.45 m from every frame on
/// each of the test set's tracks (three of which a single Hermite segment a leg cannot clear) and
/// in the library, and the command says so.
#[test]
fn tracks_clearance_reports_every_racing_line_clear_of_the_frames() {
    let dir = tempfile::tempdir().unwrap();
    let ts = dir.path().join("ts");
    assert!(dronerace(&["tracks", "testset", "--out", ts.to_str().unwrap()]).status.success());
    let o = dronerace(&["tracks", "clearance", ts.to_str().unwrap()]);
    assert!(o.status.success(), "{}", stderr(&o));
    let text = String::from_utf8_lossy(&o.stdout).into_owned();
    let distances: Vec<f64> =
        text.lines().filter(|l| l.contains(" m from gate")).map(|l| l.split_whitespace().nth(1).unwrap().parse().unwrap()).collect();
    assert_eq!(distances.len(), 40, "{text}");
    assert!(distances.iter().all(|&d| d >= 0.449), "{text}");
    assert!(text.ends_with("0 of 40 tracks have a racing line within 0.2 m of a frame\n"), "{text}");
    let library = dronerace(&["tracks", "clearance"]);
    assert!(String::from_utf8_lossy(&library.stdout).ends_with("0 of 9 tracks have a racing line within 0.2 m of a frame\n"));
}

#[test]
fn eval_prints_and_writes_json_and_markdown() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("eval");
    let o = dronerace(&[
        "eval",
        "--controller",
        "pilot",
        "--tracks",
        &library_file("kidney.toml"),
        "--runs",
        "3",
        "--steps",
        "600",
        "--out",
        out.to_str().unwrap(),
        "--trajectories",
        out.join("trajectories").to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let printed = String::from_utf8_lossy(&o.stdout);
    assert!(printed.contains("| Kidney |"), "{printed}");
    let report: serde_json::Value = serde_json::from_slice(&std::fs::read(out.join("eval.json")).unwrap()).unwrap();
    assert_eq!(report["tracks"][0]["deployments"].as_array().unwrap().len(), 3);
    // The trajectories: one CSV a deployment, a row a step and one for the state after the last.
    for (k, deployment) in report["tracks"][0]["deployments"].as_array().unwrap().iter().enumerate() {
        let csv = std::fs::read_to_string(out.join(format!("trajectories/00-Kidney-{k:03}.csv"))).unwrap();
        let mut lines = csv.lines();
        assert!(lines.next().unwrap().starts_with("t,x,y,z,vx,vy,vz,qw,qx,qy,qz,p,q,r,a0"));
        let rows: Vec<&str> = lines.collect();
        assert_eq!(rows.len() as u64, deployment["steps"].as_u64().unwrap() + 1, "deployment {k}");
        let laps = rows.last().unwrap().rsplit(',').next().unwrap();
        assert_eq!(laps.parse::<usize>().unwrap(), deployment["lap_times"].as_array().unwrap().len(), "deployment {k}");
    }
    assert_eq!(report["config"]["steps"], 600);
    assert!(report["s_pw"].as_f64().unwrap() > 0.0);
    assert!(std::fs::read_to_string(out.join("eval.md")).unwrap().contains("S_pw"));
}

#[test]
fn eval_flies_the_disturbance_asked_for_names_it_and_refuses_a_bad_one_by_name() {
    let dir = tempfile::tempdir().unwrap();
    let eval = |extra: &[&str]| {
        let out = dir.path().join("eval");
        let mut args = vec!["eval", "--controller", "pilot", "--runs", "2", "--steps", "300", "--out", out.to_str().unwrap()];
        args.extend(["--tracks", "tracks/kidney.toml"]);
        args.extend(extra);
        let o = Command::new(env!("CARGO_BIN_EXE_dronerace")).current_dir(env!("CARGO_MANIFEST_DIR")).args(&args).output().unwrap();
        let report = std::fs::read(out.join("eval.json")).ok().map(|b| serde_json::from_slice::<serde_json::Value>(&b).unwrap());
        (o, report)
    };
    let (o, report) = eval(&["--wind", "3", "--disturbance", "latency_ms = 10, thrust_loss = 0.05"]);
    assert!(o.status.success(), "{}", stderr(&o));
    let printed = String::from_utf8_lossy(&o.stdout);
    assert!(printed.contains("flown in wind 3 m/s") && printed.contains("latency +10 ms") && printed.contains("thrust −5 %"), "{printed}");
    assert_eq!(report.unwrap()["config"]["env"]["disturbance"]["wind_speed"], 3.0);
    let (o, _) = eval(&["--disturbance", "wind = 3"]);
    assert!(!o.status.success() && stderr(&o).contains("--disturbance") && stderr(&o).contains("wind"), "{}", stderr(&o));
    let (o, _) = eval(&["--disturbance", "thrust_loss = 1.5"]);
    assert!(!o.status.success() && stderr(&o).contains("thrust_loss"), "{}", stderr(&o));
}

#[test]
fn a_policy_given_is_the_policy_flown_and_asking_for_the_pilot_with_it_is_an_error() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("eval");
    let generalist = Path::new(env!("CARGO_MANIFEST_DIR")).join("policies/generalist.bin").display().to_string();
    let figure8 = library_file("figure8.toml");
    let common = ["--tracks", figure8.as_str(), "--runs", "1", "--steps", "50", "--out", out.to_str().unwrap()];
    let o = dronerace(&[&["eval", "--policy", &generalist][..], &common].concat());
    assert!(o.status.success(), "{}", stderr(&o));
    let report: serde_json::Value = serde_json::from_slice(&std::fs::read(out.join("eval.json")).unwrap()).unwrap();
    assert!(report["controller"].as_str().unwrap().starts_with("policy v"), "--policy alone flies the policy: {}", report["controller"]);
    let o = dronerace(&[&["eval", "--controller", "pilot", "--policy", &generalist][..], &common].concat());
    assert!(!o.status.success() && stderr(&o).contains("--controller pilot"), "{}", stderr(&o));
    let gif = dir.path().join("f.gif");
    let o = dronerace(&[
        "sim",
        "render",
        "--track",
        &figure8,
        "--controller",
        "pilot",
        "--policy",
        &generalist,
        "--out",
        gif.to_str().unwrap(),
    ]);
    assert!(!o.status.success() && stderr(&o).contains("--controller pilot"), "sim render too: {}", stderr(&o));
    // One export verb: several policies are averaged only when asked to be.
    let o = dronerace(&["export", &generalist, &generalist, "--out", dir.path().join("two.bin").to_str().unwrap()]);
    assert!(!o.status.success() && stderr(&o).contains("--average"), "{}", stderr(&o));
    let o = dronerace(&["export", "--average", &generalist, &generalist, "--out", dir.path().join("two.bin").to_str().unwrap()]);
    assert!(o.status.success(), "{}", stderr(&o));
    let o = dronerace(&["export", &generalist, "--out", dir.path().join("g.onnx").to_str().unwrap()]);
    assert!(
        o.status.success() && String::from_utf8_lossy(&o.stdout).contains("actions in [-1, 1]"),
        "a .onnx file is ONNX: {}",
        stderr(&o)
    );
}

#[test]
fn a_retuned_pilot_flies_as_its_tuning_file_says_and_a_bad_file_is_refused_by_name() {
    let dir = tempfile::tempdir().unwrap();
    let mean_lap = |tuning: Option<&str>| {
        let out = dir.path().join("eval");
        let mut args = vec!["eval", "--controller", "pilot", "--runs", "2", "--steps", "1000", "--out", out.to_str().unwrap()];
        let kidney = library_file("kidney.toml");
        args.extend(["--tracks", &kidney]);
        let path = dir.path().join("tuning.toml");
        if let Some(text) = tuning {
            std::fs::write(&path, text).unwrap();
            args.extend(["--pilot-tuning", path.to_str().unwrap()]);
        }
        let o = dronerace(&args);
        assert!(o.status.success(), "{}", stderr(&o));
        let report: serde_json::Value = serde_json::from_slice(&std::fs::read(out.join("eval.json")).unwrap()).unwrap();
        report["mean_lap"].as_f64().unwrap()
    };
    // A pilot capped at 5 m/s laps slower than the default one (9 m/s).
    let (default, slow) = (mean_lap(None), mean_lap(Some("max_speed = 5.0")));
    assert!(slow > 1.2 * default, "{slow} s against {default} s");
    let bad = dir.path().join("bad.toml");
    std::fs::write(&bad, "max_sped = 5.0").unwrap();
    let o = dronerace(&["eval", "--pilot-tuning", bad.to_str().unwrap(), "--tracks", &library_file("kidney.toml"), "--runs", "1"]);
    assert!(!o.status.success() && stderr(&o).contains("bad.toml") && stderr(&o).contains("max_sped"), "{}", stderr(&o));
}

#[test]
fn replay_writes_one_row_per_step_and_stops_at_a_crash() {
    let dir = tempfile::tempdir().unwrap();
    let actions = dir.path().join("actions.csv");
    // Header, a comment, 30 hover-ish rows, then no thrust until the ground.
    let mut text = String::from("thrust,roll,pitch,yaw\n# hover first\n");
    let hover = 2.0 * 9.8066 / (4.0 * 8.5 / 0.752) - 1.0;
    for _ in 0..30 {
        text.push_str(&format!("{hover},0,0,0\n"));
    }
    for _ in 0..200 {
        text.push_str("-1,0,0,0\n");
    }
    std::fs::write(&actions, text).unwrap();
    let out = dir.path().join("replay.csv");
    let o = dronerace(&[
        "sim",
        "replay",
        "--track",
        &library_file("figure8.toml"),
        "--actions",
        actions.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--start",
        "0,0,2,-90",
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let csv = std::fs::read_to_string(&out).unwrap();
    let rows: Vec<Vec<&str>> = csv.lines().skip(1).map(|l| l.split(',').collect()).collect();
    assert!(csv.starts_with("t,px,py,pz,qw,qx,qy,qz,vx,vy,vz,wx,wy,wz,m1,m2,m3,m4,reward,terminated,target_gate,laps,event\n"));
    assert!(rows.len() > 30 && rows.len() < 230, "stops at the crash: {} rows", rows.len());
    let last = rows.last().unwrap();
    assert_eq!((last[19], last[22]), ("1", "crash"));
    // Starts at the given pose: after one hover step still at (0, 0, 2).
    let first: Vec<f64> = rows[0][..4].iter().map(|x| x.parse().unwrap()).collect();
    assert!((first[0] - 0.02).abs() < 1e-12 && first[1].abs() < 1e-6 && first[2].abs() < 1e-6 && (first[3] - 2.0).abs() < 1e-6);
}

#[test]
fn bad_inputs_are_refused_naming_the_file_and_the_field_or_line() {
    let dir = tempfile::tempdir().unwrap();
    let track = dir.path().join("broken.toml");
    std::fs::write(
        &track,
        "name = \"b\"\n[[gate]]\nposition = [0.0, 0.0, 2.0]\nyaw_deg = 0.0\n[[gate]]\nposition = [30.0, 0.0, 2.0]\nyaw_deg = 0.0\n",
    )
    .unwrap();
    let o = dronerace(&["tracks", "show", track.to_str().unwrap(), "--out", dir.path().join("x.png").to_str().unwrap()]);
    assert!(!o.status.success());
    let e = stderr(&o);
    assert!(e.contains("broken.toml") && e.contains("gate[1].position") && e.contains("outside the arena"), "{e}");

    let actions = dir.path().join("bad_actions.csv");
    std::fs::write(&actions, "0,0,0,0\n0,0,0\n").unwrap();
    let o = dronerace(&[
        "sim",
        "replay",
        "--track",
        &library_file("figure8.toml"),
        "--actions",
        actions.to_str().unwrap(),
        "--out",
        dir.path().join("r.csv").to_str().unwrap(),
    ]);
    assert!(!o.status.success());
    let e = stderr(&o);
    assert!(e.contains("bad_actions.csv:2") && e.contains("expected 4"), "{e}");

    std::fs::write(&actions, "0,0,0,0\n0,zero,0,0\n").unwrap();
    let o = dronerace(&[
        "sim",
        "replay",
        "--track",
        &library_file("figure8.toml"),
        "--actions",
        actions.to_str().unwrap(),
        "--out",
        dir.path().join("r.csv").to_str().unwrap(),
        "--start",
        "1,2,3",
    ]);
    assert!(!o.status.success());
    assert!(stderr(&o).contains("--start"), "{}", stderr(&o));

    // A cause is said once, though our error types both name it and expose it as the source.
    let missing = dir.path().join("missing.bin");
    let o = dronerace(&["eval", "--policy", missing.to_str().unwrap()]);
    let e = stderr(&o);
    assert!(!o.status.success() && e.contains("missing.bin") && e.matches("No such file").count() == 1, "{e}");

    // What aborted the process (exit 134) or would read until memory ran out: a trillion
    // gates, and a "policy" that is a device.
    let o = dronerace(&["tracks", "generate", "--seed", "0", "--gates", "1000000000000", "--out", dir.path().join("g").to_str().unwrap()]);
    assert_eq!(o.status.code(), Some(1), "{}", stderr(&o));
    assert!(stderr(&o).contains("gates = 1000000000000: a track has 2 to 64 gates"), "{}", stderr(&o));
    let o = dronerace(&["eval", "--policy", "/dev/zero"]);
    assert_eq!(o.status.code(), Some(1), "{}", stderr(&o));
    assert!(stderr(&o).contains("/dev/zero") && stderr(&o).contains("not a regular file"), "{}", stderr(&o));
}

#[test]
fn tracks_fit_prints_scipys_layout_and_values() {
    let reference: serde_json::Value = serde_json::from_str(include_str!("../racetracks/tests/data/splprep_periodic.json")).unwrap();
    let case = &reference["cases"][2];
    let dir = tempfile::tempdir().unwrap();
    let csv = dir.path().join("points.csv");
    let rows: Vec<String> = case["control_points"]
        .as_array()
        .unwrap()
        .iter()
        .map(|p| p.as_array().unwrap().iter().map(|x| format!("{}", x.as_f64().unwrap())).collect::<Vec<_>>().join(","))
        .collect();
    std::fs::write(&csv, rows.join("\n") + "\n").unwrap();
    let s = case["s"].as_f64().unwrap().to_string();
    let o = dronerace(&["tracks", "fit", "--points", csv.to_str().unwrap(), "--smoothing", &s]);
    assert!(o.status.success(), "{}", stderr(&o));
    let got: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    let keys: Vec<&String> = got.as_object().unwrap().keys().collect();
    assert_eq!(keys, ["coefficients", "knots", "u"]);
    let close = |a: &serde_json::Value, b: &serde_json::Value| {
        let (a, b) = (a.as_array().unwrap(), b.as_array().unwrap());
        a.len() == b.len() && a.iter().zip(b).all(|(x, y)| (x.as_f64().unwrap() - y.as_f64().unwrap()).abs() < 1e-6)
    };
    assert!(close(&got["u"], &case["u"]));
    assert!(close(&got["knots"], &case["knots"]));
    for d in 0..3 {
        assert!(close(&got["coefficients"][d], &case["coefficients"][d]));
    }
    std::fs::write(&csv, "1,2,3\n4,5\n").unwrap();
    let o = dronerace(&["tracks", "fit", "--points", csv.to_str().unwrap()]);
    assert!(!o.status.success() && stderr(&o).contains("points.csv:2"), "{}", stderr(&o));
}

#[test]
fn generate_is_reproducible_and_testset_has_forty_valid_tracks() {
    let dir = tempfile::tempdir().unwrap();
    let (a, b) = (dir.path().join("a"), dir.path().join("b"));
    for out in [&a, &b] {
        let o = dronerace(&["tracks", "generate", "--seed", "77", "--count", "5", "--out", out.to_str().unwrap()]);
        assert!(o.status.success(), "{}", stderr(&o));
    }
    let names = |d: &Path| {
        let mut v: Vec<_> = std::fs::read_dir(d).unwrap().map(|e| e.unwrap().file_name()).collect();
        v.sort();
        v
    };
    assert_eq!(names(&a).len(), 5);
    for name in names(&a) {
        assert_eq!(std::fs::read(a.join(&name)).unwrap(), std::fs::read(b.join(&name)).unwrap());
        racetracks::read_track(&a.join(&name)).unwrap();
    }
    let o = dronerace(&[
        "tracks",
        "generate",
        "--seed",
        "77",
        "--count",
        "3",
        "--generator",
        "uniform",
        "--out",
        dir.path().join("u").to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert_eq!(names(&dir.path().join("u")).len(), 3);

    let set = dir.path().join("testset");
    let o = dronerace(&["tracks", "testset", "--seed", "5", "--out", set.to_str().unwrap()]);
    assert!(o.status.success(), "{}", stderr(&o));
    let tracks = racetracks::read_track_dir(&set).unwrap();
    assert_eq!(tracks.len(), 40);
    let library = racetracks::library().unwrap();
    for (t, l) in tracks.iter().zip(&library) {
        assert_eq!(t.name, l.name, "the library comes first, in library order");
    }

    let png = dir.path().join("gallery.png");
    let o = dronerace(&["tracks", "show", a.to_str().unwrap(), "--gallery", "--out", png.to_str().unwrap()]);
    assert!(o.status.success(), "{}", stderr(&o));
    let (w, h) = png_size(&png);
    assert!(w > h, "5 tracks: a 3 × 2 grid of gallery cells ({w} × {h})");
}

/// Pixels of an 8-bit greyscale PNG.
fn grey_png(path: &Path) -> (u32, u32, Vec<u8>) {
    let decoder = png::Decoder::new(std::io::BufReader::new(std::fs::File::open(path).unwrap()));
    let mut reader = decoder.read_info().unwrap();
    let mut pixels = vec![0; reader.output_buffer_size()];
    let info = reader.next_frame(&mut pixels).unwrap();
    assert_eq!((info.color_type, info.bit_depth), (png::ColorType::Grayscale, png::BitDepth::Eight));
    pixels.truncate(info.buffer_size());
    (info.width, info.height, pixels)
}

#[test]
fn sim_render_writes_the_exact_observation_and_an_animated_flight() {
    let dir = tempfile::tempdir().unwrap();
    let track_file = library_file("figure8.toml");
    // One frame: the PNG holds exactly what the renderer gives the policy at that pose.
    let frame = dir.path().join("frame.png");
    let pose = "0.5,-1.0,2.5,0.9659,0,0,0.2588"; // 30° yaw
    let o = dronerace(&["sim", "render", "--track", &track_file, "--pose", pose, "--target", "2", "--out", frame.to_str().unwrap()]);
    assert!(o.status.success(), "{}", stderr(&o));
    let (w, h, pixels) = grey_png(&frame);
    assert_eq!((w, h), (84, 84));
    let track = racetracks::read_track(Path::new(&track_file)).unwrap();
    let q = sim::nalgebra::UnitQuaternion::from_quaternion(sim::nalgebra::Quaternion::new(0.9659, 0.0, 0.0, 0.2588));
    let mut expected = vec![0u8; sim::camera::IMAGE_PIXELS];
    sim::camera::render(&track, 2, &sim::nalgebra::Vector3::new(0.5, -1.0, 2.5), &q.to_rotation_matrix().into_inner(), &mut expected);
    assert_eq!(pixels, expected);
    assert!(pixels.contains(&255) || pixels.contains(&155) || pixels.contains(&55), "the pose sees a gate");
    // A flight: a looping GIF of many frames and a strip of the chosen steps.
    let gif_path = dir.path().join("flight.gif");
    let strip = dir.path().join("strip.png");
    let o = dronerace(&[
        "sim",
        "render",
        "--track",
        &track_file,
        "--controller",
        "pilot",
        "--out",
        gif_path.to_str().unwrap(),
        "--strip",
        strip.to_str().unwrap(),
        "--strip-steps",
        "0,20,40",
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(String::from_utf8_lossy(&o.stdout).contains("laps done"), "the pilot flies a lap: {}", String::from_utf8_lossy(&o.stdout));
    let mut decoder = gif::DecodeOptions::new().read_info(std::fs::File::open(&gif_path).unwrap()).unwrap();
    let mut frames = 0;
    while decoder.read_next_frame().unwrap().is_some() {
        frames += 1;
    }
    assert!(frames > 50, "{frames} frames");
    assert_eq!(grey_png(&strip).0, 3 * 86 - 2, "three frames side by side");
    // Bad input names the field.
    let o = dronerace(&["sim", "render", "--track", &track_file, "--pose", "1,2,3", "--out", frame.to_str().unwrap()]);
    assert!(!o.status.success() && stderr(&o).contains("7 numbers"), "{}", stderr(&o));
    let o = dronerace(&["sim", "render", "--track", &track_file, "--pose", pose, "--target", "9", "--out", frame.to_str().unwrap()]);
    assert!(!o.status.success() && stderr(&o).contains("--target 9"), "{}", stderr(&o));
}

#[test]
fn eval_flies_a_vision_policy_with_the_camera() {
    let dir = tempfile::tempdir().unwrap();
    let arch = policy::Architecture { hidden: vec![16, 16], ..policy::Architecture::cpu() };
    let net = policy::VisionActorCritic::new(&arch, -0.5, 2, &policy::Device::flex());
    let blob =
        <policy::WeightsBlob as policy::NetworkBlob>::from_vision_model(3, &arch, &policy::ObsNormalizer::new(arch.observation_dim), &net);
    let path = dir.path().join("vision.bin");
    std::fs::write(&path, blob.to_bytes()).unwrap();
    let out = dir.path().join("eval");
    let o = dronerace(&[
        "eval",
        "--controller",
        "policy",
        "--policy",
        path.to_str().unwrap(),
        "--tracks",
        &library_file("figure8.toml"),
        "--runs",
        "2",
        "--steps",
        "40",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let report: serde_json::Value = serde_json::from_slice(&std::fs::read(out.join("eval.json")).unwrap()).unwrap();
    assert!(report["controller"].as_str().unwrap().contains("vision-based"), "{}", report["controller"]);
    assert_eq!(report["tracks"][0]["deployments"].as_array().unwrap().len(), 2);
    // A vision policy cannot be served or exported as a state-based one: refused by name.
    let o = dronerace(&["export", path.to_str().unwrap(), "--out", dir.path().join("v.onnx").to_str().unwrap()]);
    assert!(!o.status.success() && stderr(&o).contains("vision-based"), "{}", stderr(&o));
}

#[test]
fn plot_draws_the_learning_curves_of_runs_overlaid_and_names_a_missing_file() {
    let dir = tempfile::tempdir().unwrap();
    let header = "iteration,env_steps,wall_seconds,charts/episodic_return,eval/S_pw,eval/success";
    for (run, shift) in [("a", 0.0), ("b", 0.5)] {
        std::fs::create_dir(dir.path().join(run)).unwrap();
        let rows: Vec<String> = (1..=20)
            .map(|i| {
                let validation = if i % 5 == 0 { format!("{},{}", 0.01 * i as f64 + shift * 0.01, 0.04 * i as f64) } else { ",".into() };
                format!("{i},{},{},{},{validation}", i * 24000, i as f64, -5.0 + i as f64 + shift)
            })
            .collect();
        std::fs::write(dir.path().join(run).join("metrics.csv"), format!("{header}\n{}\n", rows.join("\n"))).unwrap();
    }
    let out = dir.path().join("curves.png");
    let (a, b) = (dir.path().join("a"), dir.path().join("b"));
    let o = dronerace(&["plot", a.to_str().unwrap(), b.to_str().unwrap(), "--out", out.to_str().unwrap()]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert_eq!(png_size(&out), (960, 1080), "three panels");
    let o = dronerace(&["plot", dir.path().join("missing").to_str().unwrap(), "--out", out.to_str().unwrap()]);
    assert!(!o.status.success() && stderr(&o).contains("missing/metrics.csv"), "{}", stderr(&o));
}

/// A run directory another live trainer holds is refused by name, before anything is written.
#[test]
fn train_refuses_a_run_directory_another_trainer_holds() {
    let dir = tempfile::tempdir().unwrap();
    let host = std::fs::read_to_string("/proc/sys/kernel/hostname").unwrap_or_default();
    // This test process is alive: its claim is not stale.
    std::fs::write(dir.path().join(runtime::run_lock::LOCK_FILE), format!("{} {}", host.trim(), std::process::id())).unwrap();
    let out = dir.path().to_str().unwrap();
    let o = dronerace(&["train", "--in-process", "--out", out, "--iterations", "1"]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && err.contains("is held by"), "{err}");
    assert!(!dir.path().join("config.toml").exists() && !dir.path().join("checkpoints").exists(), "nothing written");
}
