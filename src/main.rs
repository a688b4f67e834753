//! The `dronerace` command: parses arguments and dispatches to the library crates.

// The command line talks to its user on stdout and stderr; the libraries log through `tracing`.
#![allow(clippy::print_stdout, clippy::print_stderr)]

mod commands;
mod signal;

use clap::{Parser, Subcommand};

/// Train drone-racing policies that fly racetracks they have never seen.
#[derive(Parser)]
#[command(name = "dronerace", version, about)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Draw, generate and fit tracks; make the held-out test set; time generation and switching.
    #[command(subcommand)]
    Tracks(commands::tracks::TracksCommand),
    /// Evaluate a controller on a set of tracks (S_pw, success, lap times).
    Eval(commands::eval::EvalArgs),
    /// Write a checkpoint's policy (or the weight average of several) as a stand-alone weights
    /// blob, or as ONNX for other runtimes.
    Export(commands::eval::ExportArgs),
    /// Serve a trained policy over gRPC (dronerace.v1.Pilot) for a flight stack.
    Serve(commands::serve::ServeArgs),
    /// Simulator tools: replay action files, render the camera, measure stepping speed.
    #[command(subcommand)]
    Sim(commands::sim::SimCommand),
    /// Run an experiment file (variants × seeds, resumable) and write its report.
    #[command(subcommand)]
    Experiment(commands::experiment::ExperimentCommand),
    /// Train a policy with PPO: task controller, learner and actors as processes on this machine.
    Train(commands::train::TrainArgs),
    /// Distil a vision policy from a state-based teacher (DAgger): the student flies on camera
    /// images, the teacher labels every state it visits.
    Distill(commands::distill::DistillArgs),
    /// Serve the task controller (tracks and switching of every environment) over gRPC.
    Taskctl(commands::processes::TaskctlArgs),
    /// Run the learner process (PPO; takes rollouts, publishes weights).
    Learner(commands::processes::LearnerArgs),
    /// Show the task controller's state: every environment's track, window, ρ, q, switches.
    Tasks(commands::tasks::TasksArgs),
    /// Show how a running training is doing, from its learner: iteration, env steps, actors.
    Status(commands::status::StatusArgs),
    /// Run an actor process (environments, inference, rollouts).
    Actor(commands::processes::ActorArgs),
    /// Print an actor's own bearer token, made from the run's, for that actor's machine.
    Token(commands::token::TokenArgs),
    /// Measure speed: the PPO step, the transports, the simulator, track generation.
    #[command(subcommand)]
    Bench(commands::bench::BenchCommand),
    /// Kill -9 random processes of a training run for minutes, then audit what was lost.
    Chaos(runtime::chaos::ChaosOptions),
    /// Draw runs' learning curves (training return, validation S_pw and success against env
    /// steps, the runs overlaid) from their metrics.csv.
    Plot(commands::curves::PlotArgs),
}

fn main() -> std::process::ExitCode {
    runtime::keep_freed_memory();
    tracing_subscriber::fmt()
        .with_env_filter(tracing_subscriber::EnvFilter::try_from_default_env().unwrap_or_else(|_| "info".into()))
        .with_writer(std::io::stderr)
        // Colour codes only for a person at a terminal: logs in files stay greppable.
        .with_ansi(std::io::IsTerminal::is_terminal(&std::io::stderr()))
        .init();
    let result = match Cli::parse().command {
        Command::Tracks(c) => commands::tracks::run(c),
        Command::Eval(a) => commands::eval::run(a),
        Command::Sim(c) => commands::sim::run(c),
        Command::Train(a) => commands::train::run(a),
        Command::Experiment(c) => commands::experiment::run(c),
        Command::Distill(a) => commands::distill::run(a),
        Command::Taskctl(a) => commands::processes::taskctl(a),
        Command::Learner(a) => commands::processes::learner(a),
        Command::Actor(a) => commands::processes::actor(a),
        Command::Token(a) => commands::token::run(a),
        Command::Tasks(a) => commands::tasks::run(a),
        Command::Status(a) => commands::status::run(a),
        Command::Chaos(a) => commands::chaos::run(a),
        Command::Serve(a) => commands::serve::serve(a),
        Command::Export(a) => commands::eval::export(a),
        Command::Plot(a) => commands::curves::run(a),
        Command::Bench(c) => commands::bench::run(c),
    };
    match result {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {}", error_message(&e));
            let fatal = e.chain().any(|c| {
                c.downcast_ref::<runtime::TrainError>().is_some_and(runtime::TrainError::is_fatal)
                    || c.downcast_ref::<runtime::services::ServiceError>().is_some_and(runtime::services::ServiceError::is_fatal)
            });
            if fatal { std::process::ExitCode::from(runtime::supervisor::EXIT_FATAL) } else { std::process::ExitCode::FAILURE }
        }
    }
}

/// The error and its causes joined by ": ", leaving out a cause whose text the message already
/// ends with (our error types name their cause in their own text and also expose it as the
/// source, which `{:#}` would print twice).
fn error_message(e: &anyhow::Error) -> String {
    let mut message = String::new();
    for cause in e.chain() {
        let text = cause.to_string();
        if message.ends_with(&text) {
            continue;
        }
        if !message.is_empty() {
            message.push_str(": ");
        }
        message.push_str(&text);
    }
    message
}
