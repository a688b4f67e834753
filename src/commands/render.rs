//! `dronerace sim render`: what the vision agent sees (`figures::flight`). One camera frame
//! from a given pose as the exact 84×84 greyscale observation (PNG), or a whole flight as an
//! animated GIF (camera view beside a top view with the trajectory) and a PNG strip of chosen
//! frames.

use std::path::{Path, PathBuf};
use std::sync::Arc;

use ::sim::Track;
use anyhow::{Context, ensure};
use clap::Args;
use figures::flight::{FlightPlan, camera_png, fly};

use super::eval::{ControllerKind, controller_factory};
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
    let (position, rotation) = ::sim::poses_text::parse_pose_quaternion(pose).with_context(|| format!("--pose {pose:?}"))?;
    let (png, seen) = camera_png(track, target, &position, &rotation.to_rotation_matrix().into_inner())?;
    write_atomic(out, &png)?;
    println!("wrote {} (84×84, {seen} pixels show a gate)", out.display());
    Ok(())
}

/// Flies the track with the chosen controller and writes the GIF and, if asked, the strip.
fn flight(track: &Arc<Track>, args: &RenderArgs) -> anyhow::Result<()> {
    ensure!(args.strip.is_none() || !args.strip_steps.is_empty(), "--strip needs --strip-steps, e.g. 0,40,80");
    ensure!(args.out.extension().is_some_and(|e| e == "gif"), "--out {}: a flight is written as a .gif", args.out.display());
    let kind = ControllerKind::resolve(args.controller, args.policy.is_some())?;
    let (name, make) = controller_factory(kind, args.policy.as_deref())?;
    let plan = FlightPlan { steps: args.steps, laps: args.laps, every: args.every, strip_steps: &args.strip_steps };
    let pictures = fly(track, make().as_mut(), &plan)?;
    write_atomic(&args.out, &pictures.gif)?;
    println!(
        "{name} on {}: {} steps ({}), {} laps; wrote {} ({} frames)",
        track.name,
        pictures.steps,
        pictures.ending,
        pictures.laps,
        args.out.display(),
        pictures.frames
    );
    if let Some(path) = &args.strip {
        let strip = pictures.strip.with_context(|| format!("--strip-steps: the flight ended before any of {:?}", args.strip_steps))?;
        write_atomic(path, &strip)?;
        println!("wrote {} ({} frames)", path.display(), pictures.strip_frames);
    }
    Ok(())
}
