//! `dronerace distill`: a student learns from a teacher by DAgger (the `distill` crate): a
//! vision student from a state-based policy, or a state-based student from the pilot.

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};

use anyhow::Context;
use clap::Args;
use distill::{DistillConfig, Distiller, progress_line};
use policy::WeightsBlob;
use runtime::progress::ProgressLog;

/// Arguments of `dronerace distill`.
#[derive(Args)]
pub struct DistillArgs {
    /// The teacher: a state-based checkpoint or weights blob, or `pilot` for the reference
    /// pilot (overrides the config).
    #[arg(long)]
    teacher: Option<PathBuf>,
    /// The student: `vision` (default) or `state` (overrides the config; without a config, the
    /// student's defaults).
    #[arg(long, value_parser = super::train::parse_agent)]
    student: Option<policy::Agent>,
    /// TOML configuration (every field optional; see distill::DistillConfig).
    #[arg(long)]
    config: Option<PathBuf>,
    /// Run directory.
    #[arg(long, default_value = "runs/vision-student")]
    out: PathBuf,
    /// Continue the distillation in this directory from its newest checkpoint.
    #[arg(long, conflicts_with_all = ["teacher", "student", "config", "seed"])]
    resume: Option<PathBuf>,
    /// Rounds of the whole run (overrides the config; with --resume, extends or shortens the
    /// run being resumed).
    #[arg(long = "total-rounds", id = "rounds_total")]
    total_rounds: Option<u64>,
    /// Seed (overrides the config).
    #[arg(long)]
    seed: Option<u64>,
    /// Stop after this many rounds of this sitting (a checkpoint is written on the way out).
    #[arg(long)]
    rounds: Option<u64>,
    /// Also write the final student as a weights blob here (e.g. policies/vision-student.bin).
    #[arg(long)]
    save: Option<PathBuf>,
}

/// Runs the distillation and reports where the student is.
pub fn run(args: DistillArgs) -> anyhow::Result<()> {
    let stop = crate::signal::stop_flag()?;
    let (dir, config) = match &args.resume {
        Some(dir) => {
            if let Some(rounds) = args.total_rounds {
                let path = dir.join("config.toml");
                let mut config = DistillConfig::read(&path)?;
                config.rounds = rounds;
                config.write(&path)?;
            }
            (dir.clone(), None)
        }
        None => {
            let mut config = match &args.config {
                Some(path) => DistillConfig::read(path)?,
                None => DistillConfig::defaults_for(args.student.unwrap_or(policy::Agent::Vision)),
            };
            if let Some(student) = args.student {
                config.student = student;
            }
            if let Some(teacher) = &args.teacher {
                config.teacher = teacher.clone();
            }
            if let Some(rounds) = args.total_rounds {
                config.rounds = rounds;
            }
            if let Some(seed) = args.seed {
                config.seed = seed;
            }
            (args.out.clone(), Some(config))
        }
    };
    let student = distil(&dir, config, args.rounds, &stop)?;
    if let Some(path) = &args.save {
        super::write_atomic(path, &student.to_bytes()).with_context(|| format!("saving the student to {}", path.display()))?;
        println!("student (version {}) written to {}", student.version, path.display());
    }
    println!("best student by validation S_pw: {}", dir.join("checkpoints/best.bin").display());
    Ok(())
}

/// Distils until every round is done, `rounds` more are done, or `stop` is raised; then
/// checkpoints and returns the student. A new run starts from `config` in `dir`; without one
/// the run there continues.
fn distil(dir: &Path, config: Option<DistillConfig>, rounds: Option<u64>, stop: &AtomicBool) -> anyhow::Result<WeightsBlob> {
    let mut distiller = match config {
        Some(config) => {
            std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
            Distiller::start(config, dir)?
        }
        None => Distiller::resume(dir)?,
    };
    let mut log = ProgressLog::open(dir)?;
    let first = distiller.round();
    eprintln!("distilling in {} (from round {first})", dir.display());
    while !distiller.finished() && !stop.load(Ordering::SeqCst) && rounds.is_none_or(|n| distiller.round() - first < n) {
        let s = distiller.round_step()?;
        log.report(&progress_line(&s, distiller.config().rounds))?;
    }
    let path = distiller.checkpoint()?;
    eprintln!("checkpoint written to {} ({:.0} s of distillation so far)", path.display(), distiller.wall_seconds());
    Ok(distiller.student())
}
