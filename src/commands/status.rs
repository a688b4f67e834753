//! `dronerace status`: how a running training is doing, as its learner reports it
//! (`dronerace.v1.Learner/Status`): iteration, env steps, throughput, connected actors.

use std::path::PathBuf;
use std::time::Duration;

use clap::Args;

/// Arguments of `dronerace status`.
#[derive(Args)]
pub struct StatusArgs {
    /// Learner address (`http://` or `https://`).
    #[arg(long, default_value = "http://127.0.0.1:50052")]
    learner: String,
    /// Run config whose `[network]` section holds the token and CA.
    #[arg(long)]
    config: Option<PathBuf>,
}

/// Prints the learner's status.
pub fn run(args: StatusArgs) -> anyhow::Result<()> {
    let security = super::client_security(args.config.as_deref())?;
    let status = transport::grpc_link::learner_status(&args.learner, &security, Duration::from_secs(10))?;
    println!("iteration {}", status.iteration);
    println!("env steps {}", status.env_steps);
    println!("env-steps/s {:.0}", status.sps);
    println!("connected actors {}", status.connected_actors.join(" "));
    println!("policy lag {}", status.policy_lag);
    println!("refused chunks {}", status.refused_chunks);
    println!("learner epoch {}", status.learner_epoch);
    Ok(())
}
