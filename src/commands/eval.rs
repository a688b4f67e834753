//! `dronerace eval`: the evaluation harness of SPEC §9 for any controller.

use std::path::{Path, PathBuf};

use ::sim::ReferencePilot;
use ::sim::eval::{EvalConfig, evaluate};
use anyhow::Context;
use clap::{Args, ValueEnum};
use policy::ControllerFactory;

use super::{load_tracks, write_atomic};

/// Which controller flies.
#[derive(Clone, Copy, Debug, ValueEnum)]
pub enum ControllerKind {
    /// The non-learned reference pilot.
    Pilot,
    /// A trained policy's mean action (needs --policy).
    Policy,
}

/// Arguments of `dronerace eval`.
#[derive(Args)]
pub struct EvalArgs {
    /// Controller to evaluate.
    #[arg(long, value_enum, default_value = "pilot")]
    controller: ControllerKind,
    /// Track files or directories; the built-in library when omitted.
    #[arg(long, num_args = 1..)]
    tracks: Vec<PathBuf>,
    /// Deployments per track.
    #[arg(long, default_value_t = 25)]
    runs: usize,
    /// Steps per deployment.
    #[arg(long, default_value_t = 1000)]
    steps: u32,
    /// Seed of the start perturbations.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Checkpoint or weights blob of the policy (with `--controller policy`); several
    /// state-based ones fly as an ensemble, the mean of their actions.
    #[arg(long, num_args = 1..)]
    policy: Vec<PathBuf>,
    /// TOML file of the reference pilot's tuning (`sim::PilotParams`; every field optional),
    /// to fly a retuned pilot (with `--controller pilot`).
    #[arg(long)]
    pilot_tuning: Option<PathBuf>,
    /// Directory for `eval.json` and `eval.md`.
    #[arg(long, default_value = "runs/eval")]
    out: PathBuf,
}

/// The reference pilot, or the mean action of the policy at `policy` (a checkpoint or blob;
/// a vision policy renders its camera every step), with a name for reports.
pub fn controller_factory(kind: ControllerKind, policy: Option<&Path>) -> anyhow::Result<(String, ControllerFactory)> {
    Ok(match kind {
        ControllerKind::Pilot => ("pilot".into(), Box::new(|| Box::new(ReferencePilot::default()))),
        ControllerKind::Policy => {
            let path = policy.context("--controller policy needs --policy CHECKPOINT")?;
            let blob = learner::checkpoint::read_policy(path)?;
            let name = format!("policy v{} ({}, {})", blob.version, path.display(), blob.architecture.agent);
            (name, policy::controller_factory(&blob)?)
        }
    })
}

/// The policies of several checkpoints or weights blobs, an error naming the file that fails.
fn read_policies(paths: &[PathBuf]) -> anyhow::Result<Vec<policy::WeightsBlob>> {
    paths.iter().map(|path| learner::checkpoint::read_policy(path).with_context(|| format!("reading {}", path.display()))).collect()
}

/// The mean action of several state-based policies, with a name for reports.
fn ensemble_factory(paths: &[PathBuf]) -> anyhow::Result<(String, ControllerFactory)> {
    let blobs = read_policies(paths)?;
    let ensemble = policy::EnsembleController::from_blobs(&blobs).context("an ensemble takes state-based policies")?;
    let names: Vec<String> = paths.iter().map(|p| p.display().to_string()).collect();
    Ok((format!("ensemble of {} policies ({})", paths.len(), names.join(", ")), ensemble.factory()))
}

/// Runs the evaluation, prints the table and writes JSON and Markdown.
pub fn run(args: EvalArgs) -> anyhow::Result<()> {
    anyhow::ensure!(args.runs > 0, "--runs must be at least 1");
    anyhow::ensure!(args.steps > 0, "--steps must be at least 1");
    let tracks = load_tracks(&args.tracks)?;
    let config = EvalConfig { runs: args.runs, steps: args.steps, seed: args.seed, ..EvalConfig::default() };
    let (name, make) = match (&args.pilot_tuning, args.controller) {
        (None, ControllerKind::Policy) if args.policy.len() > 1 => ensemble_factory(&args.policy)?,
        (None, kind) => controller_factory(kind, args.policy.first().map(PathBuf::as_path))?,
        (Some(path), ControllerKind::Pilot) => {
            let text = std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
            let params = runtime::overrides::parse_over(&::sim::PilotParams::default(), &text)
                .map_err(|e| anyhow::anyhow!("{}: {e}", path.display()))?;
            let make: ControllerFactory = Box::new(move || Box::new(ReferencePilot::new(params)));
            (format!("pilot ({})", path.display()), make)
        }
        (Some(_), ControllerKind::Policy) => anyhow::bail!("--pilot-tuning retunes the pilot; it does not apply to --controller policy"),
    };
    let started = std::time::Instant::now();
    let report = evaluate(&name, &tracks, make.as_ref(), &config);
    let markdown = report.to_markdown();
    println!("{markdown}");
    tracing::info!(deployments = tracks.len() * args.runs, seconds = started.elapsed().as_secs_f64(), "evaluation finished");
    write_atomic(&args.out.join("eval.json"), serde_json::to_string_pretty(&report)?.as_bytes())?;
    write_atomic(&args.out.join("eval.md"), markdown.as_bytes())?;
    println!("wrote {} and {}", args.out.join("eval.json").display(), args.out.join("eval.md").display());
    Ok(())
}

/// Arguments of `dronerace export-policy`.
#[derive(Args)]
pub struct ExportArgs {
    /// Checkpoint (or weights blob) to take the policy from; several (of one run) export the
    /// mean of their weights, under the newest one's normaliser (stochastic weight averaging).
    #[arg(required = true)]
    checkpoints: Vec<PathBuf>,
    /// Weights blob to write: architecture, normaliser, version and weights only.
    #[arg(long)]
    out: PathBuf,
}

/// Writes the policy of a checkpoint — or the weight average of several — as a stand-alone
/// weights blob (what `eval --policy`, `train --init-from` and actors read), without
/// optimiser, environments or curriculum.
pub fn export(args: ExportArgs) -> anyhow::Result<()> {
    let blobs = read_policies(&args.checkpoints)?;
    let blob = match blobs.as_slice() {
        [one] => one.clone(),
        many => policy::averaging::average(many).context("averaging the policies")?,
    };
    let bytes = blob.to_bytes();
    write_atomic(&args.out, &bytes)?;
    let of = if blobs.len() > 1 { format!("mean of {} policies, newest ", blobs.len()) } else { String::new() };
    println!("wrote {} ({of}policy v{}, {} bytes)", args.out.display(), blob.version, bytes.len());
    Ok(())
}

/// Formats `dronerace export` writes.
#[derive(Clone, Copy, Debug, ValueEnum)]
pub enum ExportFormat {
    /// The deterministic actor with its normaliser folded in, as an ONNX model (opset 13).
    Onnx,
}

/// Arguments of `dronerace export`.
#[derive(Args)]
pub struct ExportModelArgs {
    /// Checkpoint or weights blob of the policy.
    #[arg(long)]
    policy: PathBuf,
    /// Format of the file to write.
    #[arg(long, value_enum, default_value = "onnx")]
    format: ExportFormat,
    /// File to write.
    #[arg(long)]
    out: PathBuf,
}

/// Writes a policy in a format other programs run (ONNX Runtime, TensorRT, …).
pub fn export_model(args: ExportModelArgs) -> anyhow::Result<()> {
    let blob = learner::checkpoint::read_policy(&args.policy)?;
    let bytes = match args.format {
        ExportFormat::Onnx => policy::onnx::actor_model(&blob)?,
    };
    write_atomic(&args.out, &bytes)?;
    println!(
        "wrote {} (policy v{}: {} raw observations in the {} frame -> {} actions in [-1, 1], {} bytes)",
        args.out.display(),
        blob.version,
        blob.architecture.observation_dim,
        blob.architecture.observation_frame.name(),
        blob.architecture.action_dim,
        bytes.len()
    );
    Ok(())
}
