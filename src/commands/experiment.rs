//! `dronerace experiment`: run an experiment file (variants × seeds, resumable) and report it.

use std::path::PathBuf;
use std::sync::atomic::Ordering;

use anyhow::Context;
use clap::Subcommand;
use runtime::experiment::{Experiment, markdown_report, run_experiment, sequential_track_curves, summarise};

use super::write_atomic;
use crate::signal::stop_flag;

/// Experiment subcommands.
#[derive(Subcommand)]
pub enum ExperimentCommand {
    /// Train every variant × seed of FILE under --out (done runs are skipped, interrupted ones
    /// resumed, runs another runner holds left to it), test each finished run, then write the
    /// report.
    Run {
        /// Experiment file (TOML: description, seeds, [base], [[variant]] name + set).
        file: PathBuf,
        /// Directory of the experiment's runs.
        #[arg(long)]
        out: PathBuf,
        /// Run only this variant (repeat for several; default all). The report still covers
        /// every run under --out.
        #[arg(long = "variant")]
        variants: Vec<String>,
        /// Run only this seed of the file's (repeat for several; default all).
        #[arg(long = "seed")]
        seeds: Vec<u64>,
    },
    /// Write report.md and curves.png for the runs of FILE under --out.
    Report {
        /// Experiment file.
        file: PathBuf,
        /// Directory of the experiment's runs (as given to `experiment run`).
        #[arg(long)]
        out: PathBuf,
    },
}

/// Runs an experiment subcommand.
pub fn run(command: ExperimentCommand) -> anyhow::Result<()> {
    match command {
        ExperimentCommand::Run { file, out, variants, seeds } => {
            let experiment = Experiment::read(&file)?;
            let mut selection = experiment.clone();
            selection.select(&variants, &seeds)?;
            std::fs::create_dir_all(&out).with_context(|| format!("creating {}", out.display()))?;
            // The file travels with its results, so a report can be remade from the directory.
            write_atomic(&out.join("experiment.toml"), std::fs::read(&file)?.as_slice())?;
            let stop = stop_flag()?;
            let log = run_experiment(&selection, &out, &stop, &mut |dir, summary| {
                let run = dir.strip_prefix(&out).unwrap_or(dir).display().to_string();
                eprintln!("{run}: {}", runtime::progress::progress_line(summary, f64::NAN));
            })?;
            eprintln!(
                "experiment: {} runs finished now, {} were done already, {} resumed, {} held by other runners{}",
                log.finished.len(),
                log.skipped.len(),
                log.resumed.len(),
                log.busy.len(),
                if log.interrupted || stop.load(Ordering::SeqCst) { "; interrupted: run it again to continue" } else { "" }
            );
            report(&experiment, &out)
        }
        ExperimentCommand::Report { file, out } => report(&Experiment::read(&file)?, &out),
    }
}

fn report(experiment: &Experiment, dir: &std::path::Path) -> anyhow::Result<()> {
    let summaries = summarise(experiment, dir)?;
    write_atomic(&dir.join("report.md"), markdown_report(experiment, &summaries).as_bytes())?;
    figures::plot::draw_validation_curves(&summaries, &dir.join("curves.png"))?;
    println!("wrote {} and {}", dir.join("report.md").display(), dir.join("curves.png").display());
    if experiment.sequential {
        for &seed in &experiment.seeds {
            let (curves, boundaries) = sequential_track_curves(experiment, dir, seed)?;
            if curves.is_empty() {
                continue;
            }
            let path = dir.join(format!("tracks-seed-{seed}.png"));
            let stages: Vec<&str> = experiment.variants.iter().map(|v| v.name.as_str()).collect();
            figures::plot::draw_track_curves(
                &curves,
                &boundaries,
                &format!("validation success per track; stages {}", stages.join(" > ")),
                &path,
            )?;
            println!("wrote {}", path.display());
        }
    }
    Ok(())
}
