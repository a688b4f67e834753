//! `dronerace tracks …`: draw, fit, generate and benchmark tracks.

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::Context;
use clap::{Subcommand, ValueEnum};
use racetracks::{GeneratorKind, TrackGenParams, TrackGenerator};

use super::{load_tracks, read_text};
use figures::plot::Layout;

/// Track subcommands.
#[derive(Subcommand)]
pub enum TracksCommand {
    /// Draw tracks into one PNG: top and side views, or a compact gallery of top views.
    Show {
        /// Track files or directories; the built-in library when omitted.
        files: Vec<PathBuf>,
        /// PNG to write.
        #[arg(long)]
        out: PathBuf,
        /// Only the top view, in smaller cells: for many tracks at once.
        #[arg(long)]
        gallery: bool,
    },
    /// Print how close the reference pilot's racing line — which state policies read — comes to
    /// any gate frame, per track: policies fly few tracks where it comes within ~0.2 m.
    Clearance {
        /// Track files or directories; the built-in library when omitted.
        files: Vec<PathBuf>,
    },
    /// Fit a closed smoothing spline (scipy splprep per=1, k=3) and print it as JSON.
    Fit {
        /// CSV with one control point `x,y,z` per row, no header; the closing point is added.
        #[arg(long)]
        points: PathBuf,
        /// Smoothing factor s.
        #[arg(long, default_value_t = 4.0)]
        smoothing: f64,
    },
    /// Generate track files from consecutive seeds.
    Generate {
        /// Seed of the first track; track i uses seed + i.
        #[arg(long)]
        seed: u64,
        /// Number of tracks.
        #[arg(long, default_value_t = 16)]
        count: usize,
        /// Directory to write into.
        #[arg(long)]
        out: PathBuf,
        /// Generator.
        #[arg(long, value_enum, default_value = "informed")]
        generator: Generator,
        /// Gates per track (SPEC §7's N_g).
        #[arg(long, default_value_t = 6)]
        gates: usize,
        /// Draw each track's gate count uniformly from `--gates` up to this.
        #[arg(long)]
        gates_max: Option<usize>,
    },
    /// Write the evaluation test set: the library topped up with generated tracks to 40.
    Testset {
        /// Seed of the generated part; keep it out of training.
        #[arg(long, default_value_t = racetracks::track_sets::TEST_SEED)]
        seed: u64,
        /// Directory to write into.
        #[arg(long)]
        out: PathBuf,
    },
    /// Write an out-of-distribution family (SPEC §13): `many-gates` (8–12 gates), `steep` (a 14 m
    /// tall arena), `tight` (a 14 × 14 m floor) or `races` (hand-made layouts, `tracks/ood/`).
    Ood {
        /// The family.
        #[arg(long)]
        family: racetracks::ood::Family,
        /// Tracks of a generated family (from seed 9,500,000, held out from training).
        #[arg(long, default_value_t = 40)]
        count: usize,
        /// Directory to write into.
        #[arg(long)]
        out: PathBuf,
    },
    /// Make a track file from a CSV of gate poses, one gate a row in racing order:
    /// `x,y,z,yaw_deg` (a header row and `#` comments are skipped).
    Import {
        /// The CSV.
        csv: PathBuf,
        /// The track's name [default: the CSV's file name without extension].
        #[arg(long)]
        name: Option<String>,
        /// Track file to write.
        #[arg(long)]
        out: PathBuf,
    },
}

/// Arguments of `dronerace bench tracks`.
#[derive(clap::Args)]
pub struct TracksBenchArgs {
    /// Tracks to generate.
    #[arg(long, default_value_t = 1000)]
    count: usize,
    /// Environments reporting per iteration.
    #[arg(long, default_value_t = 96)]
    envs: usize,
    /// Switching window l.
    #[arg(long, default_value_t = 600)]
    window: usize,
}

/// Generator choice on the command line.
#[derive(Clone, Copy, Debug, ValueEnum)]
pub enum Generator {
    /// Informed spline generator.
    Informed,
    /// Uniform baseline.
    Uniform,
}

impl From<Generator> for GeneratorKind {
    fn from(g: Generator) -> Self {
        match g {
            Generator::Informed => GeneratorKind::Informed,
            Generator::Uniform => GeneratorKind::Uniform,
        }
    }
}

/// A racing line closer than this to a frame (m) marks a track policies seldom fly
/// (docs/notebook/generalist.md: 11–43 % success there against 86–91 % elsewhere).
const NEAR_FRAME: f64 = 0.2;

/// Runs a track subcommand.
pub fn run(command: TracksCommand) -> anyhow::Result<()> {
    match command {
        TracksCommand::Show { files, out, gallery } => {
            let tracks = load_tracks(&files)?;
            let layout = if gallery { Layout::Gallery } else { Layout::TopAndSide };
            figures::plot::draw_tracks(&tracks, &out, layout)?;
            println!("wrote {} ({} tracks)", out.display(), tracks.len());
            Ok(())
        }
        TracksCommand::Clearance { files } => {
            let tracks = load_tracks(&files)?;
            let mut near = 0;
            for track in &tracks {
                let c = ::sim::RacingLine::new(track).frame_clearance(&track.gates);
                near += usize::from(c.distance < NEAR_FRAME);
                println!("{:<24} {:.3} m from gate {}'s frame, flying to gate {}", track.name, c.distance, c.gate, c.target);
            }
            println!("{near} of {} tracks have a racing line within {NEAR_FRAME} m of a frame", tracks.len());
            Ok(())
        }
        TracksCommand::Fit { points, smoothing } => fit(&points, smoothing),
        TracksCommand::Generate { seed, count, out, generator, gates, gates_max } => {
            let params = TrackGenParams { gates, gates_max, ..TrackGenParams::default() };
            let generator = TrackGenerator { kind: generator.into(), params };
            let started = Instant::now();
            let attempts = generator.write_tracks(seed, count, &out)?;
            println!(
                "wrote {count} tracks to {} in {:.2} s; acceptance {:.1} % ({count} of {attempts} candidates)",
                out.display(),
                started.elapsed().as_secs_f64(),
                100.0 * count as f64 / attempts as f64
            );
            Ok(())
        }
        TracksCommand::Testset { seed, out } => {
            let n = write_numbered(&racetracks::test_set(seed)?, &out)?;
            println!("wrote {n} tracks (library, then generated from seed {seed}) to {}", out.display());
            Ok(())
        }
        TracksCommand::Ood { family, count, out } => {
            let n = write_numbered(&racetracks::ood::family_tracks(family, count)?, &out)?;
            println!("wrote {n} tracks of the {} family to {}", family.name(), out.display());
            Ok(())
        }
        TracksCommand::Import { csv, name, out } => {
            let text = read_text(&csv).with_context(|| format!("reading {}", csv.display()))?;
            let name = name.unwrap_or_else(|| csv.file_stem().map_or_else(|| "imported".into(), |s| s.to_string_lossy().into_owned()));
            let track = racetracks::track_from_csv(&name, &text, &csv)?;
            racetracks::write_track(&track, &out)?;
            println!(
                "wrote {} ({}: {} gates, arena {:?} to {:?} m)",
                out.display(),
                track.name,
                track.gates.len(),
                track.arena.min.as_slice(),
                track.arena.max.as_slice()
            );
            Ok(())
        }
    }
}

/// Writes `tracks` into `out` as `NN-<name>.toml`, numbered so the directory lists in order.
fn write_numbered(tracks: &[::sim::Track], out: &Path) -> anyhow::Result<usize> {
    std::fs::create_dir_all(out).with_context(|| format!("creating {}", out.display()))?;
    for (i, track) in tracks.iter().enumerate() {
        racetracks::write_track(track, &out.join(format!("{i:02}-{}.toml", track.name.to_lowercase())))?;
    }
    Ok(tracks.len())
}

/// `tracks fit`: reads `x,y,z` rows and prints scipy's tck layout as JSON.
fn fit(points: &Path, smoothing: f64) -> anyhow::Result<()> {
    let text = read_text(points).with_context(|| format!("reading {}", points.display()))?;
    let at = || points.display().to_string();
    let control =
        racetracks::spline::control_points_from_csv(&text).map_err(|e| anyhow::anyhow!("{}:{}: {e}", points.display(), e.line))?;
    let fit = racetracks::spline::fit_closed_curve(&control, smoothing).with_context(at)?;
    let json = serde_json::json!({ "u": fit.u, "knots": fit.curve.knots, "coefficients": fit.curve.coefficients });
    println!("{}", serde_json::to_string_pretty(&json)?);
    Ok(())
}

/// Generation rate and acceptance for both generators; task-controller update cost.
pub fn bench(args: TracksBenchArgs) -> anyhow::Result<()> {
    let TracksBenchArgs { count, envs, window } = args;
    for timing in taskctl::bench::time_generators(count)? {
        println!("{timing}");
    }
    let u = taskctl::bench::time_updates(envs, window)?;
    println!(
        "task controller: {:.3} ms per update of {envs} environments with full windows of {window} \
         ({} switches in {} iterations, new tracks generated included)",
        u.seconds * 1e3,
        u.switches,
        u.iterations
    );
    Ok(())
}
