//! `dronerace distill`: a student learns from a teacher by DAgger (`runtime::distill`): a
//! vision student from a state-based policy, or a state-based student from the pilot.

use std::path::PathBuf;

use anyhow::Context;
use clap::Args;
use runtime::distill::DistillConfig;

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
    /// TOML configuration (every field optional; see runtime::distill::DistillConfig).
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
    let stop = runtime::signal::stop_flag()?;
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
    let student = runtime::distill::run(&dir, config, args.rounds, &stop)?.student;
    if let Some(path) = &args.save {
        super::write_atomic(path, &student.to_bytes()).with_context(|| format!("saving the student to {}", path.display()))?;
        println!("student (version {}) written to {}", student.version, path.display());
    }
    println!("best student by validation S_pw: {}", dir.join("checkpoints/best.bin").display());
    Ok(())
}
