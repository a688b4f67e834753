//! `dronerace tasks`: what the task controller of a running training holds — each
//! environment's track, window, ρ, q and switches, or the switch history.

use std::path::PathBuf;

use clap::Args;
use taskctl::{TaskInfo, TaskService};
use transport::task_client::TaskClient;

/// Arguments of `dronerace tasks`.
#[derive(Args)]
pub struct TasksArgs {
    /// Task controller address (`http://` or `https://`).
    #[arg(long, default_value = "http://127.0.0.1:50051")]
    taskctl: String,
    /// Run config whose `[network]` section holds the token and CA.
    #[arg(long)]
    config: Option<PathBuf>,
    /// Only this environment.
    #[arg(long, conflicts_with = "history")]
    env: Option<usize>,
    /// The switch history instead of the tasks.
    #[arg(long)]
    history: bool,
}

fn opt(x: Option<f64>) -> String {
    x.map_or("–".into(), |v| format!("{v:.3}"))
}

fn row(t: &TaskInfo) -> String {
    let actor = t.actor.as_deref().unwrap_or("–");
    format!("{:>4}  {:<12} {:<32} {:>6} {:>8} {:>8} {:>8}", t.env, actor, t.track.name, t.window_length, opt(t.rho), opt(t.q), t.switches)
}

/// Prints the tasks (or one, or the history).
pub fn run(args: TasksArgs) -> anyhow::Result<()> {
    let security = super::client_security(args.config.as_deref())?;
    // The blocking client drives calls through a Handle, which needs a runtime with its own worker.
    let rt = tokio::runtime::Builder::new_multi_thread().worker_threads(1).enable_all().build()?;
    let client = TaskClient::new(rt.handle().clone(), &args.taskctl, &security)?;
    if args.history {
        println!("{:>8} {:>4}  {:<32} {:<32} {:>8} {:>8}", "rollout", "env", "old track", "new track", "rho", "q");
        for e in client.switch_history(0)? {
            println!("{:>8} {:>4}  {:<32} {:<32} {:>8.3} {:>8.3}", e.iteration, e.env, e.old_track, e.new_track, e.rho, e.q);
        }
        return Ok(());
    }
    println!("{:>4}  {:<12} {:<32} {:>6} {:>8} {:>8} {:>8}", "env", "actor", "track", "window", "rho", "q", "switches");
    match args.env {
        Some(env) => println!("{}", row(&client.task(env)?)),
        None => client.tasks()?.iter().for_each(|t| println!("{}", row(t))),
    }
    Ok(())
}
