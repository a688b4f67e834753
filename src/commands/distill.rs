//! `dronerace distill`: a student learns from a teacher by DAgger (the `distill` crate): a
//! vision student from a state-based policy, or a state-based student from the pilot.

use std::path::PathBuf;

use anyhow::Context;
use clap::Args;
use distill::{DistillConfig, DistillFlags, Distiller};

/// Arguments of `dronerace distill`.
#[derive(Args)]
pub struct DistillArgs {
    /// The teacher: a state-based checkpoint or weights blob, or `pilot` for the reference
    /// pilot (overrides the config).
    #[arg(long)]
    teacher: Option<PathBuf>,
    /// The student: `vision` (default) or `state` (overrides the config; without a config, the
    /// student's defaults).
    #[arg(long)]
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
    let mut distiller = match &args.resume {
        Some(dir) => Distiller::resume_for(dir, args.total_rounds)?,
        None => {
            let flags = DistillFlags { student: args.student, teacher: args.teacher.clone(), rounds: args.total_rounds, seed: args.seed };
            std::fs::create_dir_all(&args.out).with_context(|| format!("creating {}", args.out.display()))?;
            Distiller::start(DistillConfig::with_flags(args.config.as_deref(), &flags)?, &args.out)?
        }
    };
    let dir = args.resume.clone().unwrap_or_else(|| args.out.clone());
    let path = distiller.run(&dir, args.rounds, &stop)?;
    eprintln!("checkpoint written to {} ({:.0} s of distillation so far)", path.display(), distiller.wall_seconds());
    let student = distiller.student();
    if let Some(path) = &args.save {
        super::write_atomic(path, &student.to_bytes()).with_context(|| format!("saving the student to {}", path.display()))?;
        println!("student (version {}) written to {}", student.version, path.display());
    }
    println!("best student by validation S_pw: {}", dir.join("checkpoints/best.bin").display());
    Ok(())
}
