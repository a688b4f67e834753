//! `dronerace sim render`: what the vision agent sees. One camera frame from a given pose as
//! the exact 84×84 greyscale observation (PNG), or a whole flight as an animated GIF (camera
//! view beside a top view with the trajectory) and a PNG strip of chosen frames.

use std::path::{Path, PathBuf};
use std::sync::Arc;

use ::sim::camera::{IMAGE_PIXELS, IMAGE_SIDE, gate_colour, render};
use ::sim::nalgebra::{Quaternion, UnitQuaternion, Vector3};
use ::sim::{EnvConfig, RaceEnv, Track};
use anyhow::{Context, bail, ensure};
use clap::Args;

use super::eval::{ControllerKind, controller_factory};
use super::sim::parse_numbers;
use super::write_atomic;

/// Arguments of `dronerace sim render`.
#[derive(Args)]
pub struct RenderArgs {
    /// Track file.
    #[arg(long)]
    track: PathBuf,
    /// One frame from this pose, `x,y,z,qw,qx,qy,qz` (world position, body attitude), instead
    /// of a flight.
    #[arg(long, allow_hyphen_values = true)]
    pose: Option<String>,
    /// Target gate of the single frame.
    #[arg(long, default_value_t = 0)]
    target: usize,
    /// Who flies the flight [default: policy with --policy, else pilot].
    #[arg(long, value_enum)]
    controller: Option<ControllerKind>,
    /// Checkpoint or weights blob of the policy to fly.
    #[arg(long)]
    policy: Option<PathBuf>,
    /// Policy steps to fly at most; the flight also ends at a crash or after `--laps` laps.
    #[arg(long, default_value_t = 1000)]
    steps: u32,
    /// Laps after which the flight ends.
    #[arg(long, default_value_t = 1)]
    laps: u32,
    /// One GIF frame every this many policy steps (50 per second).
    #[arg(long, default_value_t = 2)]
    every: usize,
    /// Also a PNG strip of the camera frames at these policy steps, e.g. `0,40,80,120`.
    #[arg(long, value_delimiter = ',', requires = "strip")]
    strip_steps: Vec<usize>,
    /// Where the strip goes.
    #[arg(long)]
    strip: Option<PathBuf>,
    /// Output: `.png` for one frame, `.gif` for a flight.
    #[arg(long)]
    out: PathBuf,
}

/// Renders a frame or a flight.
pub fn run(args: RenderArgs) -> anyhow::Result<()> {
    let track = Arc::new(racetracks::read_track(&args.track)?);
    match &args.pose {
        Some(pose) => single_frame(&track, pose, args.target, &args.out),
        None => flight(&track, &args),
    }
}

/// Writes the observation at one pose as an 8-bit greyscale PNG.
fn single_frame(track: &Track, pose: &str, target: usize, out: &Path) -> anyhow::Result<()> {
    ensure!(target < track.gates.len(), "--target {target}: track {} has gates 0–{}", track.name, track.gates.len() - 1);
    let (position, rotation) = parse_pose(pose).with_context(|| format!("--pose {pose:?}"))?;
    let mut image = vec![0u8; IMAGE_PIXELS];
    render(track, target, &position, &rotation.to_rotation_matrix().into_inner(), &mut image);
    write_atomic(out, &png_bytes(&image, IMAGE_SIDE, IMAGE_SIDE)?)?;
    let seen = image.iter().filter(|&&p| p != 0).count();
    println!("wrote {} (84×84, {seen} pixels show a gate)", out.display());
    Ok(())
}

/// Parses `x,y,z,qw,qx,qy,qz`; the quaternion is normalised, but must not be zero.
fn parse_pose(text: &str) -> anyhow::Result<(Vector3<f64>, UnitQuaternion<f64>)> {
    let values = parse_numbers(text)?;
    let [x, y, z, qw, qx, qy, qz] = values[..] else {
        bail!("expected x,y,z,qw,qx,qy,qz (7 numbers), found {}", values.len());
    };
    let q = Quaternion::new(qw, qx, qy, qz);
    ensure!(q.norm() > 1e-9, "the attitude quaternion is zero");
    Ok((Vector3::new(x, y, z), UnitQuaternion::from_quaternion(q)))
}

/// Side of one panel of the GIF (the camera image scaled 3×).
const PANEL: usize = 3 * IMAGE_SIDE;

/// Palette of the GIF: camera greys first, then the top view's colours.
const PALETTE: [[u8; 3]; 8] = [
    [0, 0, 0],       // background
    [55, 55, 55],    // other gates
    [155, 155, 155], // next gate
    [255, 255, 255], // target gate
    [230, 60, 40],   // trajectory
    [60, 220, 90],   // drone
    [24, 28, 36],    // top-view floor
    [90, 90, 110],   // panel divider
];

/// Palette index of a camera grey level.
fn grey_index(level: u8) -> u8 {
    match level {
        0 => 0,
        l if l <= 55 => 1,
        l if l <= 155 => 2,
        _ => 3,
    }
}

/// Flies the track with the chosen controller from its start (nominal dynamics, no start
/// perturbation) and writes the GIF and, if asked, the strip.
fn flight(track: &Arc<Track>, args: &RenderArgs) -> anyhow::Result<()> {
    ensure!(args.every > 0, "--every must be at least 1");
    ensure!(args.strip.is_none() || !args.strip_steps.is_empty(), "--strip needs --strip-steps, e.g. 0,40,80");
    ensure!(args.out.extension().is_some_and(|e| e == "gif"), "--out {}: a flight is written as a .gif", args.out.display());
    let kind = ControllerKind::resolve(args.controller, args.policy.is_some())?;
    let (name, make) = controller_factory(kind, args.policy.as_deref())?;
    let mut controller = make();
    let config = EnvConfig { randomization: ::sim::RandomizationParams::none(), ..EnvConfig::evaluation() };
    let mut env = RaceEnv::new(track.clone(), config, 0, 0);
    controller.reset(&env);
    let mut camera = vec![0u8; IMAGE_PIXELS];
    let mut trajectory = vec![env.body().position];
    let mut gif_frames = Vec::new();
    let mut strip = Vec::new();
    let mut ending = "step limit";
    for step in 0..=args.steps as usize {
        env.render_camera(&mut camera);
        if args.strip_steps.contains(&step) {
            strip.push(camera.clone());
        }
        if step % args.every == 0 {
            gif_frames.push(compose(&camera, track, env.target_gate(), &trajectory));
        }
        if step == args.steps as usize {
            break;
        }
        let action = controller.act(&env);
        let outcome = env.step(&action);
        trajectory.push(env.body().position);
        let ended = if outcome.terminated { Some("crash") } else { (env.stats().laps >= args.laps).then_some("laps done") };
        if let Some(why) = ended {
            // The last frame shows where the flight ended, whatever --every says.
            ending = why;
            env.render_camera(&mut camera);
            gif_frames.push(compose(&camera, track, env.target_gate(), &trajectory));
            break;
        }
    }
    write_atomic(&args.out, &gif_bytes(&gif_frames, 2 * args.every as u16)?)?;
    println!(
        "{name} on {}: {} steps ({ending}), {} laps; wrote {} ({} frames)",
        track.name,
        trajectory.len() - 1,
        env.stats().laps,
        args.out.display(),
        gif_frames.len()
    );
    if let Some(path) = &args.strip {
        ensure!(!strip.is_empty(), "--strip-steps: the flight ended before any of {:?}", args.strip_steps);
        let width = strip.len() * (IMAGE_SIDE + 2) - 2;
        let mut pixels = vec![40u8; width * IMAGE_SIDE];
        for (k, frame) in strip.iter().enumerate() {
            for r in 0..IMAGE_SIDE {
                let at = r * width + k * (IMAGE_SIDE + 2);
                pixels[at..at + IMAGE_SIDE].copy_from_slice(&frame[r * IMAGE_SIDE..(r + 1) * IMAGE_SIDE]);
            }
        }
        write_atomic(path, &png_bytes(&pixels, width, IMAGE_SIDE)?)?;
        println!("wrote {} ({} frames)", path.display(), strip.len());
    }
    Ok(())
}

/// One GIF frame: the camera image scaled 3× beside a top view of the arena with the gates
/// (coloured as the camera colours them), the trajectory so far and the drone.
fn compose(camera: &[u8], track: &Track, target: usize, trajectory: &[Vector3<f64>]) -> Vec<u8> {
    let width = 2 * PANEL + 2;
    let mut frame = vec![6u8; width * PANEL];
    for r in 0..PANEL {
        for c in 0..PANEL {
            frame[r * width + c] = grey_index(camera[(r / 3) * IMAGE_SIDE + c / 3]);
        }
        frame[r * width + PANEL] = 7;
        frame[r * width + PANEL + 1] = 7;
    }
    // The top view frames the gates with a 3 m margin (the arena is mostly empty).
    let margin = Vector3::new(3.0, 3.0, 0.0);
    let lo = track.gates.iter().fold(track.gates[0].position, |m, g| m.inf(&g.position)) - margin;
    let hi = track.gates.iter().fold(track.gates[0].position, |m, g| m.sup(&g.position)) + margin;
    let scale = (PANEL - 1) as f64 / (hi.x - lo.x).max(hi.y - lo.y);
    // Top view: x to the right, y up.
    let mut plot = |p: &Vector3<f64>, colour: u8, radius: i64| {
        let c = ((p.x - lo.x) * scale).round() as i64;
        let r = (PANEL - 1) as i64 - ((p.y - lo.y) * scale).round() as i64;
        for dr in -radius..=radius {
            for dc in -radius..=radius {
                let (rr, cc) = (r + dr, c + dc);
                if (0..PANEL as i64).contains(&rr) && (0..PANEL as i64).contains(&cc) {
                    frame[rr as usize * width + PANEL + 2 + cc as usize] = colour;
                }
            }
        }
    };
    for (index, gate) in track.gates.iter().enumerate() {
        let colour = grey_index(gate_colour(index, target, track.gates.len()));
        for k in -20..=20 {
            let across = gate.to_world(&Vector3::new(0.0, f64::from(k) * 0.05, 0.0));
            plot(&across, colour, 1);
        }
    }
    for p in trajectory {
        plot(p, 4, 0);
    }
    if let Some(p) = trajectory.last() {
        plot(p, 5, 2);
    }
    frame
}

/// Encodes palette-indexed frames as a looping GIF with `delay` hundredths of a second each.
fn gif_bytes(frames: &[Vec<u8>], delay: u16) -> anyhow::Result<Vec<u8>> {
    let palette: Vec<u8> = PALETTE.iter().flatten().copied().collect();
    let (width, height) = ((2 * PANEL + 2) as u16, PANEL as u16);
    let mut bytes = Vec::new();
    {
        let mut encoder = gif::Encoder::new(&mut bytes, width, height, &palette)?;
        encoder.set_repeat(gif::Repeat::Infinite)?;
        for pixels in frames {
            let mut frame = gif::Frame::from_indexed_pixels(width, height, pixels.clone(), None);
            frame.delay = delay;
            encoder.write_frame(&frame)?;
        }
    }
    Ok(bytes)
}

/// Encodes an 8-bit greyscale image as PNG.
fn png_bytes(pixels: &[u8], width: usize, height: usize) -> anyhow::Result<Vec<u8>> {
    let mut bytes = Vec::new();
    {
        let mut encoder = png::Encoder::new(&mut bytes, width as u32, height as u32);
        encoder.set_color(png::ColorType::Grayscale);
        encoder.set_depth(png::BitDepth::Eight);
        encoder.write_header()?.write_image_data(pixels)?;
    }
    Ok(bytes)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn poses_parse_and_bad_ones_are_named() {
        let (p, q) = parse_pose("1,2,3,2,0,0,0").unwrap();
        assert_eq!(p, Vector3::new(1.0, 2.0, 3.0));
        assert!((q.w - 1.0).abs() < 1e-12, "normalised");
        assert!(parse_pose("1,2,3,1,0,0").unwrap_err().to_string().contains("7 numbers"));
        assert!(parse_pose("1,2,x,1,0,0,0").unwrap_err().to_string().contains("column 3"));
        assert!(parse_pose("1,2,3,0,0,0,0").unwrap_err().to_string().contains("zero"));
    }
}
