//! `dronerace sim …`: replay action files exactly; render the camera; measure stepping speed.

use std::path::PathBuf;
use std::sync::Arc;

use actor::bench::{BenchActions, BenchObs, SimBench, SimBenchReport};
use anyhow::Context;
use clap::Subcommand;

use super::{load_tracks, read_text, write_atomic};

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
        #[command(flatten)]
        disturbance: super::eval::DisturbanceArgs,
    },
    /// Render what the vision agent sees: one frame from a pose (PNG), or a flight (GIF).
    Render(super::render::RenderArgs),
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
    /// episodes end only by truncation (the worst case per step); `pilot`: the reference pilot
    /// racing each track.
    #[arg(long, default_value = "random")]
    actions: BenchActions,
    /// `state`: the state-based agent's environments (its 52-number observation); `vision`:
    /// the vision agent's, with the 84×84 camera image of every environment after every step
    /// (SPEC §5).
    #[arg(long, default_value = "state")]
    obs: BenchObs,
}

/// Runs a simulator subcommand.
pub fn run(command: SimCommand) -> anyhow::Result<()> {
    match command {
        SimCommand::Replay { track, actions, out, start, disturbance } => {
            let track = Arc::new(racetracks::read_track(&track)?);
            let start =
                start.as_deref().map(|t| ::sim::poses_text::parse_pose_yaw(t).with_context(|| format!("--start {t:?}"))).transpose()?;
            let text = read_text(&actions).with_context(|| format!("reading {}", actions.display()))?;
            let actions = ::sim::replay::parse_actions(&text).map_err(|e| match &e {
                ::sim::replay::ActionsError::BadRow { line, .. } => anyhow::anyhow!("{}:{line}: {e}", actions.display()),
                ::sim::replay::ActionsError::Empty => anyhow::anyhow!("{}: {e}", actions.display()),
            })?;
            let rows = ::sim::replay::replay(track, start, &actions, disturbance.parse()?);
            let mut csv = Vec::new();
            ::sim::replay::write_csv(&rows, &mut csv)?;
            write_atomic(&out, &csv)?;
            let ended = if rows.last().is_some_and(|r| r.terminated) { " (stopped at a crash)" } else { "" };
            println!("wrote {} rows to {}{ended}", rows.len(), out.display());
            Ok(())
        }
        SimCommand::Render(args) => super::render::run(args),
    }
}

/// Steps the library's tracks (round robin) and prints the rate.
pub fn bench(args: SimBenchArgs) -> anyhow::Result<()> {
    let SimBenchArgs { envs, threads, steps, actions, obs } = args;
    let threads = threads.unwrap_or_else(rayon::current_num_threads);
    let report = SimBench { envs, threads, steps, actions, obs }.measure(&load_tracks(&[])?)?;
    let SimBenchReport { rate, seconds, episodes, coded_image_bytes: coded } = report;
    println!(
        "{actions:?} actions, {obs:?} observations, {envs} envs x {steps} steps on {threads} thread(s): {rate:.0} env-steps/s ({:.0} per thread), \
         {episodes} episodes ended, {seconds:.2} s",
        rate / threads as f64
    );
    if !coded.is_empty() {
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
