//! Pictures of what the vision agent sees: one camera frame as the exact 84×84 greyscale
//! observation (PNG), and a whole flight as an animated GIF (camera view beside a top view with
//! the trajectory) with a PNG strip of chosen frames.

use std::sync::Arc;

use sim::camera::{IMAGE_PIXELS, IMAGE_SIDE, gate_colour};
use sim::nalgebra::Vector3;
use sim::{Controller, EnvConfig, RaceEnv, Track};

use crate::FigureError;

/// An encoder's error as a [`FigureError`].
fn encoding(e: impl std::fmt::Display) -> FigureError {
    FigureError::Draw(format!("encoding: {e}"))
}

/// What to fly and which frames to keep.
pub struct FlightPlan<'a> {
    /// Policy steps to fly at most; the flight also ends at a crash or after `laps` laps.
    pub steps: u32,
    /// Laps after which the flight ends.
    pub laps: u32,
    /// One GIF frame every this many policy steps (at least 1).
    pub every: usize,
    /// Policy steps whose camera frames go into the strip.
    pub strip_steps: &'a [usize],
}

/// A flight drawn.
pub struct FlightPictures {
    /// The animated GIF.
    pub gif: Vec<u8>,
    /// GIF frames.
    pub frames: usize,
    /// The strip of the chosen camera frames as a PNG (none if no chosen step was flown).
    pub strip: Option<Vec<u8>>,
    /// Frames in the strip.
    pub strip_frames: usize,
    /// Policy steps flown.
    pub steps: usize,
    /// Laps flown.
    pub laps: u32,
    /// Why it ended: `crash`, `laps done` or `step limit`.
    pub ending: &'static str,
}

/// The camera observation at one pose as an 8-bit greyscale PNG, and how many pixels show a gate.
pub fn camera_png(
    track: &Track,
    target: usize,
    position: &Vector3<f64>,
    rotation: &sim::nalgebra::Matrix3<f64>,
) -> Result<(Vec<u8>, usize), FigureError> {
    let mut image = vec![0u8; IMAGE_PIXELS];
    sim::camera::render(track, target, position, rotation, &mut image);
    let seen = image.iter().filter(|&&p| p != 0).count();
    Ok((png_bytes(&image, IMAGE_SIDE, IMAGE_SIDE)?, seen))
}

/// Flies `track` with `controller` from its start (nominal dynamics, no start perturbation)
/// and draws the flight.
pub fn fly(track: &Arc<Track>, controller: &mut dyn Controller, plan: &FlightPlan<'_>) -> Result<FlightPictures, FigureError> {
    if plan.every == 0 {
        return Err(FigureError::Nothing("--every must be at least 1"));
    }
    let config = EnvConfig { randomization: sim::RandomizationParams::none(), ..EnvConfig::evaluation() };
    let mut env = RaceEnv::new(track.clone(), config, 0, 0);
    controller.reset(&env);
    let mut camera = vec![0u8; IMAGE_PIXELS];
    let mut trajectory = vec![env.body().position];
    let mut gif_frames = Vec::new();
    let mut strip = Vec::new();
    let mut ending = "step limit";
    for step in 0..=plan.steps as usize {
        env.render_camera(&mut camera);
        if plan.strip_steps.contains(&step) {
            strip.push(camera.clone());
        }
        if step % plan.every == 0 {
            gif_frames.push(compose(&camera, track, env.target_gate(), &trajectory));
        }
        if step == plan.steps as usize {
            break;
        }
        let action = controller.act(&env);
        let outcome = env.step(&action);
        trajectory.push(env.body().position);
        let ended = if outcome.terminated { Some("crash") } else { (env.stats().laps >= plan.laps).then_some("laps done") };
        if let Some(why) = ended {
            // The last frame shows where the flight ended, whatever `every` says.
            ending = why;
            env.render_camera(&mut camera);
            gif_frames.push(compose(&camera, track, env.target_gate(), &trajectory));
            break;
        }
    }
    let strip_png = if strip.is_empty() {
        None
    } else {
        let width = strip.len() * (IMAGE_SIDE + 2) - 2;
        let mut pixels = vec![40u8; width * IMAGE_SIDE];
        for (k, frame) in strip.iter().enumerate() {
            for r in 0..IMAGE_SIDE {
                let at = r * width + k * (IMAGE_SIDE + 2);
                pixels[at..at + IMAGE_SIDE].copy_from_slice(&frame[r * IMAGE_SIDE..(r + 1) * IMAGE_SIDE]);
            }
        }
        Some(png_bytes(&pixels, width, IMAGE_SIDE)?)
    };
    Ok(FlightPictures {
        gif: gif_bytes(&gif_frames, 2 * plan.every as u16)?,
        frames: gif_frames.len(),
        strip: strip_png,
        strip_frames: strip.len(),
        steps: trajectory.len() - 1,
        laps: env.stats().laps,
        ending,
    })
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
pub fn gif_bytes(frames: &[Vec<u8>], delay: u16) -> Result<Vec<u8>, FigureError> {
    let palette: Vec<u8> = PALETTE.iter().flatten().copied().collect();
    let (width, height) = ((2 * PANEL + 2) as u16, PANEL as u16);
    let mut bytes = Vec::new();
    {
        let mut encoder = gif::Encoder::new(&mut bytes, width, height, &palette).map_err(encoding)?;
        encoder.set_repeat(gif::Repeat::Infinite).map_err(encoding)?;
        for pixels in frames {
            let mut frame = gif::Frame::from_indexed_pixels(width, height, pixels.clone(), None);
            frame.delay = delay;
            encoder.write_frame(&frame).map_err(encoding)?;
        }
    }
    Ok(bytes)
}

/// Encodes an 8-bit greyscale image as PNG.
pub fn png_bytes(pixels: &[u8], width: usize, height: usize) -> Result<Vec<u8>, FigureError> {
    let mut bytes = Vec::new();
    {
        let mut encoder = png::Encoder::new(&mut bytes, width as u32, height as u32);
        encoder.set_color(png::ColorType::Grayscale);
        encoder.set_depth(png::BitDepth::Eight);
        encoder.write_header().map_err(encoding)?.write_image_data(pixels).map_err(encoding)?;
    }
    Ok(bytes)
}
