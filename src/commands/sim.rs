//! `dronerace sim …`: replay action files exactly; render the camera; measure stepping speed.

use std::path::{Path, PathBuf};
use std::sync::Arc;

use ::sim::nalgebra::Vector3;
use ::sim::{EnvConfig, Pose, VecEnv};
use anyhow::{Context, bail};
use clap::Subcommand;
use rand::{Rng, SeedableRng};

use super::{load_tracks, parse_numbers, read_text, write_atomic};

/// Simulator subcommands.
#[derive(Subcommand)]
pub enum SimCommand {
    /// Replay normalised actions from rest at the start pose and write the state per step.
    Replay {
        /// Track file.
        #[arg(long)]
        track: PathBuf,
        /// CSV with one action row `a0,a1,a2,a3` per policy step (an optional header is skipped).
        #[arg(long)]
        actions: PathBuf,
        /// CSV to write (columns: see `::sim::replay::CSV_HEADER`).
        #[arg(long)]
        out: PathBuf,
        /// Start pose `x,y,z,yaw_deg` instead of the track's.
        #[arg(long, allow_hyphen_values = true)]
        start: Option<String>,
    },
    /// Render what the vision agent sees: one frame from a pose (PNG), or a flight (GIF).
    Render(super::render::RenderArgs),
    /// Measure environment steps per second (an earlier spelling of `bench sim`).
    #[command(hide = true)]
    Bench(SimBenchArgs),
}

/// Arguments of `dronerace bench sim`.
#[derive(clap::Args)]
pub struct SimBenchArgs {
    /// Parallel environments.
    #[arg(long, default_value_t = 96)]
    envs: usize,
    /// Worker threads (default: all cores).
    #[arg(long)]
    threads: Option<usize>,
    /// Vectorised steps to time.
    #[arg(long, default_value_t = 3000)]
    steps: usize,
    /// `random`: uniform random actions with training randomisation (many early crashes);
    /// `hover`: the hover command without randomisation, so every step runs all substeps and
    /// episodes end only by truncation (the worst case per step).
    #[arg(long, value_enum, default_value = "random")]
    actions: BenchActions,
    /// `state`: the state-based agent's environments (its 52-number observation); `vision`:
    /// the vision agent's, with the 84×84 camera image of every environment after every step
    /// (SPEC §5).
    #[arg(long, value_enum, default_value = "state")]
    obs: BenchObs,
}

/// What `sim bench` observes.
#[derive(Clone, Copy, Debug, PartialEq, clap::ValueEnum)]
pub enum BenchObs {
    /// State observations.
    State,
    /// State observations and camera images.
    Vision,
}

/// Action source of `sim bench`.
#[derive(Clone, Copy, Debug, PartialEq, clap::ValueEnum)]
pub enum BenchActions {
    /// Uniform in [-1, 1]⁴.
    Random,
    /// The hover command.
    Hover,
    /// The reference pilot racing each track: the images a racing policy sees.
    Pilot,
}

/// Runs a simulator subcommand.
pub fn run(command: SimCommand) -> anyhow::Result<()> {
    match command {
        SimCommand::Replay { track, actions, out, start } => {
            let track = Arc::new(racetracks::read_track(&track)?);
            let start = start.as_deref().map(parse_start).transpose()?;
            let actions = read_actions(&actions)?;
            let rows = ::sim::replay::replay(track, start, &actions);
            let mut csv = Vec::new();
            ::sim::replay::write_csv(&rows, &mut csv)?;
            write_atomic(&out, &csv)?;
            let ended = if rows.last().is_some_and(|r| r.terminated) { " (stopped at a crash)" } else { "" };
            println!("wrote {} rows to {}{ended}", rows.len(), out.display());
            Ok(())
        }
        SimCommand::Render(args) => super::render::run(args),
        SimCommand::Bench(args) => bench(args),
    }
}

/// Parses `x,y,z,yaw_deg`.
fn parse_start(text: &str) -> anyhow::Result<Pose> {
    let values = parse_numbers(text).with_context(|| format!("--start {text:?}"))?;
    let [x, y, z, yaw_deg] = values[..] else {
        bail!("--start {text:?}: expected x,y,z,yaw_deg (4 numbers), found {}", values.len());
    };
    Ok(Pose { position: Vector3::new(x, y, z), yaw: yaw_deg.to_radians() })
}

/// Reads one 4-number action per line; blank lines and `#` comments are skipped, and so is a
/// first line with no numbers in it (a header).
fn read_actions(path: &Path) -> anyhow::Result<Vec<[f64; 4]>> {
    let text = read_text(path).with_context(|| format!("reading {}", path.display()))?;
    let mut actions = Vec::new();
    for (i, line) in text.lines().enumerate() {
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let is_header = actions.is_empty() && line.split(',').all(|f| f.trim().parse::<f64>().is_err());
        if is_header {
            continue;
        }
        let values = parse_numbers(line).with_context(|| format!("{}:{}", path.display(), i + 1))?;
        let [a0, a1, a2, a3] = values[..] else {
            bail!("{}:{}: expected 4 action values, found {}", path.display(), i + 1, values.len());
        };
        actions.push([a0, a1, a2, a3]);
    }
    anyhow::ensure!(!actions.is_empty(), "{}: no action rows", path.display());
    Ok(actions)
}

/// Steps `envs` environments (library tracks, round robin) and reports the rate.
pub fn bench(args: SimBenchArgs) -> anyhow::Result<()> {
    let SimBenchArgs { envs, threads, steps, actions: kind, obs } = args;
    anyhow::ensure!(envs > 0 && steps > 0, "--envs and --steps must be at least 1");
    let threads = threads.unwrap_or_else(rayon::current_num_threads);
    let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build()?;
    let library = load_tracks(&[])?;
    let tracks = (0..envs).map(|i| library[i % library.len()].clone()).collect();
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(0);
    let hover = ::sim::quadrotor::Command::hover().to_action(&::sim::QuadrotorParams::default()).map(|a| a as f32);
    let actions: Vec<Vec<f32>> = match kind {
        BenchActions::Random => (0..64).map(|_| (0..envs * 4).map(|_| rng.random_range(-1.0..1.0)).collect()).collect(),
        BenchActions::Hover | BenchActions::Pilot => vec![hover.repeat(envs)],
    };
    let mut pilots: Vec<::sim::ReferencePilot> = (0..envs).map(|_| ::sim::ReferencePilot::default()).collect();
    let (seconds, episodes, mut coded) = pool.install(|| {
        // The environments the agent trains in: what a training run steps.
        let agent = match obs {
            BenchObs::State => EnvConfig::state_agent(),
            BenchObs::Vision => EnvConfig::vision_agent(),
        };
        let config = match kind {
            BenchActions::Random | BenchActions::Pilot => agent,
            BenchActions::Hover => EnvConfig { randomization: ::sim::RandomizationParams::none(), ..agent },
        };
        let mut env = VecEnv::new(tracks, config, 0);
        if obs == BenchObs::Vision {
            env = env.with_images();
        }
        let (mut episodes, mut seconds, mut coded) = (0, 0.0, Vec::new());
        let mut pilot_actions = vec![0.0f32; envs * 4];
        for k in 0..steps {
            let mut step_actions = &actions[k % actions.len()];
            if kind == BenchActions::Pilot {
                // The pilot's own time is not the simulator's: it stays outside the timing.
                for (i, (pilot, row)) in pilots.iter_mut().zip(pilot_actions.chunks_mut(4)).enumerate() {
                    if env.envs()[i].stats().length == 0 {
                        ::sim::Controller::reset(pilot, &env.envs()[i]);
                    }
                    row.copy_from_slice(&::sim::Controller::act(pilot, &env.envs()[i]));
                }
                step_actions = &pilot_actions;
            }
            let started = std::time::Instant::now();
            env.step(step_actions);
            seconds += started.elapsed().as_secs_f64();
            episodes += env.finished.len();
            // What the images cost on the wire, run-length coded as rollout chunks carry them.
            if !env.images.is_empty() && k % 10 == 0 {
                for image in env.images.chunks(::sim::camera::IMAGE_PIXELS) {
                    let mut code = Vec::new();
                    policy::run_length::encode(image, &mut code);
                    coded.push(code.len());
                }
            }
        }
        (seconds, episodes, coded)
    });
    let rate = (envs * steps) as f64 / seconds;
    println!(
        "{kind:?} actions, {obs:?} observations, {envs} envs x {steps} steps on {threads} thread(s): {rate:.0} env-steps/s ({:.0} per thread), \
         {episodes} episodes ended, {seconds:.2} s",
        rate / threads as f64
    );
    if !coded.is_empty() {
        coded.sort_unstable();
        let mean = coded.iter().sum::<usize>() as f64 / coded.len() as f64;
        println!(
            "images run-length coded (as rollout chunks carry them): mean {mean:.0} bytes, median {}, p99 {} of {} ({} images sampled)",
            coded[coded.len() / 2],
            coded[coded.len() * 99 / 100],
            ::sim::camera::IMAGE_PIXELS,
            coded.len()
        );
    }
    Ok(())
}
