//! `dronerace token`: an actor's own bearer token, made from the run's token, for an actor
//! machine to hold instead of the run's. With it the actor can register, report and send
//! rollouts under its own name only (`transport::security::Caller`).

use std::path::PathBuf;

use anyhow::Context;
use clap::Args;

/// Arguments of `dronerace token`.
#[derive(Args)]
pub struct TokenArgs {
    /// The actor's name (its `dronerace actor --name`).
    #[arg(long)]
    actor: String,
    /// Run configuration whose `[network] token_file` holds the run's token.
    #[arg(long)]
    config: PathBuf,
}

/// Prints the token of `--actor`: put it in a file on that actor's machine and name the file
/// as its `[network] token_file`.
pub fn run(args: TokenArgs) -> anyhow::Result<()> {
    let security = super::client_security(Some(&args.config))?;
    let token = security.actor_token(&args.actor).with_context(|| format!("{}", args.config.display()))?;
    println!("{token}");
    Ok(())
}
