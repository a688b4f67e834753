//! `dronerace eval`: the evaluation harness of SPEC §9 for any controller.

use std::path::{Path, PathBuf};

use ::sim::ReferencePilot;
use ::sim::eval::{EvalConfig, Trajectory, evaluate_recording};
use anyhow::Context;
use clap::{Args, ValueEnum};
use learner::export::{ExportFormat, Exported};
use policy::ControllerFactory;

use super::{load_tracks, read_text, write_atomic};

/// Which controller flies.
#[derive(Clone, Copy, Debug, ValueEnum)]
pub enum ControllerKind {
    /// The non-learned reference pilot.
    Pilot,
    /// A trained policy's mean action (needs --policy).
    Policy,
}

impl ControllerKind {
    /// The controller a command flies: `--controller` if given, else the policy when `--policy`
    /// names one and the reference pilot otherwise; `--controller pilot` with `--policy` is an
    /// error rather than a pilot flight the user did not ask for.
    pub fn resolve(chosen: Option<Self>, policy_given: bool) -> anyhow::Result<Self> {
        match (chosen, policy_given) {
            (Some(Self::Pilot), true) => {
                anyhow::bail!("--policy names a policy, but --controller pilot flies the reference pilot: drop one of them")
            }
            (Some(kind), _) => Ok(kind),
            (None, true) => Ok(Self::Policy),
            (None, false) => Ok(Self::Pilot),
        }
    }
}

/// The disturbances a flight meets (SPEC §13), for `eval` and `sim replay`.
#[derive(Args)]
pub struct DisturbanceArgs {
    /// Fly in a mean wind of this speed (m/s), direction drawn per deployment, with gusts of
    /// 0.2 × its speed (SPEC §13).
    #[arg(long)]
    wind: Option<f64>,
    /// Other disturbances (SPEC §13) as TOML key-values, e.g. `noise = 2, latency_ms = 20` or
    /// `thrust_loss = 0.1, thrust_loss_motor = 0`.
    #[arg(long)]
    disturbance: Option<String>,
}

impl DisturbanceArgs {
    /// The disturbances the flags name, checked.
    pub fn parse(&self) -> anyhow::Result<::sim::Disturbances> {
        let text = self.disturbance.as_deref().unwrap_or_default();
        let mut d: ::sim::Disturbances = toml::from_str(&text.replace(',', "\n")).with_context(|| format!("--disturbance {text:?}"))?;
        d.wind_speed = self.wind.unwrap_or(d.wind_speed);
        d.check().context("--wind, --disturbance")?;
        Ok(d)
    }
}

/// Arguments of `dronerace eval`.
#[derive(Args)]
pub struct EvalArgs {
    /// Controller to evaluate [default: policy with --policy, else pilot].
    #[arg(long, value_enum)]
    controller: Option<ControllerKind>,
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
    /// Checkpoint or weights blob of the policy to fly.
    #[arg(long)]
    policy: Option<PathBuf>,
    /// TOML file of the reference pilot's tuning (`sim::PilotParams`; every field optional),
    /// to fly a retuned pilot (with `--controller pilot`).
    #[arg(long)]
    pilot_tuning: Option<PathBuf>,
    /// Directory for `eval.json` and `eval.md`.
    #[arg(long, default_value = "runs/eval")]
    out: PathBuf,
    #[command(flatten)]
    disturbance: DisturbanceArgs,
    /// Also write every deployment's states, one CSV a deployment (`<t>-<track>-<run>.csv`:
    /// time, position, velocity, attitude, body rates, action, target gate, laps), into this
    /// directory.
    #[arg(long)]
    trajectories: Option<PathBuf>,
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

/// Runs the evaluation, prints the table and writes JSON and Markdown.
pub fn run(args: EvalArgs) -> anyhow::Result<()> {
    anyhow::ensure!(args.runs > 0, "--runs must be at least 1");
    anyhow::ensure!(args.steps > 0, "--steps must be at least 1");
    let tracks = load_tracks(&args.tracks)?;
    let mut config = EvalConfig { runs: args.runs, steps: args.steps, seed: args.seed, ..EvalConfig::default() };
    config.env.disturbance = args.disturbance.parse()?;
    let kind = ControllerKind::resolve(args.controller, args.policy.is_some())?;
    let (name, make) = match (&args.pilot_tuning, kind) {
        (None, kind) => controller_factory(kind, args.policy.as_deref())?,
        (Some(path), ControllerKind::Pilot) => {
            let text = read_text(path).with_context(|| format!("reading {}", path.display()))?;
            let params = runtime::overrides::parse_over(&::sim::PilotParams::default(), &text)
                .map_err(|e| anyhow::anyhow!("{}: {e}", path.display()))?;
            let make: ControllerFactory = Box::new(move || Box::new(ReferencePilot::new(params)));
            (format!("pilot ({})", path.display()), make)
        }
        (Some(_), ControllerKind::Policy) => anyhow::bail!("--pilot-tuning retunes the pilot; it does not apply to --controller policy"),
    };
    let started = std::time::Instant::now();
    let (report, trajectories) = evaluate_recording(&name, &tracks, make.as_ref(), &config, args.trajectories.is_some());
    if let Some(dir) = &args.trajectories {
        for (i, trajectory) in trajectories.iter().enumerate() {
            let (track, run) = (i / args.runs, i % args.runs);
            write_atomic(&dir.join(Trajectory::file_name(track, &tracks[track].name, run)), trajectory.to_csv().as_bytes())?;
        }
        println!("wrote {} trajectories into {}", trajectories.len(), dir.display());
    }
    let markdown = report.to_markdown();
    println!("{markdown}");
    tracing::info!(deployments = tracks.len() * args.runs, seconds = started.elapsed().as_secs_f64(), "evaluation finished");
    write_atomic(&args.out.join("eval.json"), serde_json::to_string_pretty(&report)?.as_bytes())?;
    write_atomic(&args.out.join("eval.md"), markdown.as_bytes())?;
    println!("wrote {} and {}", args.out.join("eval.json").display(), args.out.join("eval.md").display());
    Ok(())
}

/// Arguments of `dronerace export`.
#[derive(Args)]
pub struct ExportArgs {
    /// Checkpoint or weights blob to take the policy from; with `--average`, several of one run.
    policies: Vec<PathBuf>,
    /// Export the mean of the given policies' weights, under the newest one's normaliser
    /// (stochastic weight averaging).
    #[arg(long)]
    average: bool,
    /// `safetensors` (a weights blob, what `eval --policy`, `serve`, `train --init-from` and
    /// actors read) or `onnx` (the deterministic actor with its normaliser folded in, opset 13)
    /// [default: onnx for a `.onnx` file, else safetensors].
    #[arg(long)]
    format: Option<ExportFormat>,
    /// File to write.
    #[arg(long)]
    out: PathBuf,
}

/// Writes a checkpoint's policy, or the weight average of several, as a weights blob or ONNX.
pub fn export(args: ExportArgs) -> anyhow::Result<()> {
    let n = args.policies.len();
    anyhow::ensure!(n <= 1 || args.average, "export: {n} policies given; pass --average to export the mean of their weights");
    let onnx_file = args.out.extension().is_some_and(|e| e.eq_ignore_ascii_case("onnx"));
    let format = args.format.unwrap_or(if onnx_file { ExportFormat::Onnx } else { ExportFormat::Safetensors });
    let Exported { blob, bytes } = learner::export::export(&args.policies, format)?;
    write_atomic(&args.out, &bytes)?;
    let of = if n > 1 { format!("mean of {n} policies, newest ") } else { String::new() };
    let what = match format {
        ExportFormat::Safetensors => String::new(),
        ExportFormat::Onnx => format!(
            ": {} raw observations in the {} frame -> {} actions in [-1, 1]",
            blob.architecture.observation_dim,
            blob.architecture.observation.frame.name(),
            blob.architecture.action_dim
        ),
    };
    println!("wrote {} ({of}policy v{}{what}, {} bytes)", args.out.display(), blob.version, bytes.len());
    Ok(())
}
