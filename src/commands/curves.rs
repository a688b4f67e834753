//! `dronerace plot`: learning curves of single runs from their metrics.csv.

/// Arguments of `dronerace plot`.
#[derive(clap::Args)]
pub struct PlotArgs {
    /// Run directories (each with its metrics.csv).
    #[arg(required = true, num_args = 1..)]
    runs: Vec<std::path::PathBuf>,
    /// PNG to write.
    #[arg(long, default_value = "curves.png")]
    out: std::path::PathBuf,
}

/// Reads every run's curves, then draws them.
pub fn run(args: PlotArgs) -> anyhow::Result<()> {
    let runs = args.runs.iter().map(|r| figures::plot::RunCurves::read(r)).collect::<Result<Vec<_>, _>>()?;
    figures::plot::draw_run_curves(&runs, &args.out)?;
    println!("wrote {}", args.out.display());
    Ok(())
}
