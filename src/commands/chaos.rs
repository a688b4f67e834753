//! `dronerace chaos`: kill -9 random processes of a training run for minutes, then audit what
//! was lost (`runtime::chaos`, which defines the flags). Writes `<out>/chaos.json` and prints it.

/// Runs the chaos experiment, prints its report and fails if the audit does.
pub fn run(options: runtime::chaos::ChaosOptions) -> anyhow::Result<()> {
    let report = runtime::chaos::run(&options)?;
    println!("{}", serde_json::to_string_pretty(&report)?);
    Ok(report.verdict()?)
}
