//! `dronerace plot`: learning curves of single runs from their metrics.csv, or the robustness
//! figure from its table (`docs/bench/robustness.sh`).

/// Arguments of `dronerace plot`.
#[derive(clap::Args)]
pub struct PlotArgs {
    /// Run directories (each with its metrics.csv).
    #[arg(required_unless_present = "robustness", num_args = 1..)]
    runs: Vec<std::path::PathBuf>,
    /// Draw success against disturbance level from this table instead
    /// (`disturbance,level,controller,success` rows).
    #[arg(long, conflicts_with = "runs")]
    robustness: Option<std::path::PathBuf>,
    /// PNG to write.
    #[arg(long, default_value = "curves.png")]
    out: std::path::PathBuf,
}

/// Reads every run's curves (or the robustness table), then draws them.
pub fn run(args: PlotArgs) -> anyhow::Result<()> {
    if let Some(table) = &args.robustness {
        figures::robustness::draw_robustness(&figures::robustness::read_rows(table)?, &args.out)?;
    } else {
        let runs = args.runs.iter().map(|r| figures::plot::RunCurves::read(r)).collect::<Result<Vec<_>, _>>()?;
        figures::plot::draw_run_curves(&runs, &args.out)?;
    }
    println!("wrote {}", args.out.display());
    Ok(())
}
