//! `dronerace serve`: a trained policy as the gRPC service `dronerace.v1.Pilot`, for a flight
//! stack or a companion computer. One observation in raw units → the policy's deterministic
//! action (its own normaliser applied, clipped to [-1, 1] as evaluation does), unary or over a
//! stream for a control loop; health, reflection, TLS and the token as on every other server
//! (`transport::pilot_grpc`).

use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::Arc;

use anyhow::Context;
use clap::Args;
use policy::Policy;
use serving::PolicyPilot;

use crate::signal::stop_flag;

/// Arguments of `dronerace serve`.
#[derive(Args)]
pub struct ServeArgs {
    /// Checkpoint or weights blob of the policy to serve.
    #[arg(long)]
    policy: PathBuf,
    /// Address to serve gRPC on.
    #[arg(long, default_value = "127.0.0.1:50060")]
    listen: SocketAddr,
    /// Run configuration whose `[network]` section sets TLS and the token (none: plaintext,
    /// no token).
    #[arg(long)]
    config: Option<PathBuf>,
    /// Also serve gRPC health alone, in plaintext, here: for probes that cannot speak TLS.
    #[arg(long)]
    health_listen: Option<SocketAddr>,
    /// Track file a `Race` stream flies when its `RaceStart` names none.
    #[arg(long)]
    track: Option<PathBuf>,
}

/// Serves the policy until SIGINT/SIGTERM.
pub fn serve(args: ServeArgs) -> anyhow::Result<()> {
    let security = super::client_security(args.config.as_deref())?;
    security.check_listen(&args.listen)?;
    let blob = learner::checkpoint::read_policy(&args.policy)?;
    let mut pilot = PolicyPilot::new(Arc::new(Policy::from_blob(&blob)?));
    if let Some(path) = &args.track {
        pilot = pilot.with_track(Arc::new(racetracks::read_track(path)?));
    }
    let stop = stop_flag()?;
    let rt = runtime::services::async_runtime(1)?;
    let listener = rt.block_on(tokio::net::TcpListener::bind(args.listen)).with_context(|| format!("serve: binding {}", args.listen))?;
    runtime::services::spawn_health(&rt, args.health_listen, &["dronerace.v1.Pilot"], stop.clone())?;
    eprintln!("serve: policy v{} from {} on {}", blob.version, args.policy.display(), args.listen);
    rt.block_on(transport::pilot_grpc::serve(listener, &security, pilot, runtime::services::until(stop)))
        .map_err(|e| anyhow::anyhow!("serve on {}: {e}", args.listen))
}
