//! `dronerace chaos`: kill -9 random processes of a training run for minutes, then audit what
//! was lost (`runtime::chaos`). Writes `<out>/chaos.json` and prints it.

use std::path::PathBuf;

use clap::Args;

use super::TransportArg;

/// Arguments of `dronerace chaos`.
#[derive(Args)]
pub struct ChaosArgs {
    /// Run configuration (TOML; default: the built-in defaults, i.e. the main job).
    #[arg(long)]
    config: Option<PathBuf>,
    /// Run directory (must not hold checkpoints yet); the audit goes to `<out>/chaos.json`.
    #[arg(long)]
    out: PathBuf,
    /// Seconds between two kills.
    #[arg(long, default_value_t = 20.0)]
    every: f64,
    /// Minutes of fault injection.
    #[arg(long, default_value_t = 30.0)]
    minutes: f64,
    /// Actor processes.
    #[arg(long, default_value_t = 2)]
    actors: usize,
    /// How rollouts travel.
    #[arg(long, value_enum, default_value_t = TransportArg::Shm)]
    transport: TransportArg,
    /// Seed of the choice of victims.
    #[arg(long, default_value_t = 0)]
    seed: u64,
}

/// Runs the chaos experiment, prints its report and fails if the audit does.
pub fn run(args: ChaosArgs) -> anyhow::Result<()> {
    let options = runtime::chaos::ChaosOptions {
        config: args.config,
        out: args.out,
        every: args.every,
        minutes: args.minutes,
        actors: args.actors,
        transport: args.transport.into(),
        seed: args.seed,
    };
    let report = runtime::chaos::run(&options)?;
    println!("{}", serde_json::to_string_pretty(&report)?);
    Ok(report.verdict()?)
}
