//! `dronerace serve`: a trained policy as the gRPC service `dronerace.v1.Pilot`, for a flight
//! stack or a companion computer. One observation in raw units → the policy's deterministic
//! action (its own normaliser applied, clipped to [-1, 1] as evaluation does), unary or over a
//! stream for a control loop; health, reflection, TLS and the token as on every other server.

#![allow(clippy::print_stderr, reason = "the server's own terminal output: what it serves and where")]

use std::net::SocketAddr;
use std::path::PathBuf;
use std::pin::Pin;
use std::sync::Arc;

use anyhow::Context;
use clap::Args;
use policy::Policy;
use proto::v1::pilot_server::{Pilot, PilotServer};
use proto::v1::{ActRequest, ActResponse, DescribeRequest, PilotDescription};
use tokio_stream::Stream;
use tonic::{Request, Response, Status, Streaming};

use crate::services::{async_runtime, read_config, stop_flag, until};

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
}

/// Serves the policy until SIGINT/SIGTERM.
pub fn serve(args: ServeArgs) -> anyhow::Result<()> {
    let config = read_config(&args.config)?;
    let security = proto::Security::load(&config.network)?;
    security.check_listen(&args.listen)?;
    let blob = learner::checkpoint::read_policy(&args.policy)?;
    let service = PilotService::new(Arc::new(Policy::from_blob(&blob)?));
    let stop = stop_flag()?;
    let rt = async_runtime(1)?;
    let listener = rt.block_on(tokio::net::TcpListener::bind(args.listen)).with_context(|| format!("serve: binding {}", args.listen))?;
    eprintln!("serve: policy v{} from {} on {}", blob.version, args.policy.display(), args.listen);
    rt.block_on(async {
        proto::with_discovery(security.server()?, &["dronerace.v1.Pilot"])
            .await
            .add_service(tonic::service::interceptor::InterceptedService::new(PilotServer::new(service), security.token_check()))
            .serve_with_incoming_shutdown(proto::security::incoming(listener), until(stop))
            .await
            .map_err(anyhow::Error::from)
    })
    .with_context(|| format!("serve on {}", args.listen))
}

/// The Pilot service over one policy.
#[derive(Clone)]
pub struct PilotService {
    policy: Arc<Policy>,
}

impl PilotService {
    /// Serves `policy`.
    pub fn new(policy: Arc<Policy>) -> Self {
        Self { policy }
    }

    /// The action for one raw observation, or why it is refused.
    fn act(&self, observation: &[f32]) -> Result<ActResponse, Status> {
        let expected = self.policy.observation_dim();
        if observation.len() != expected {
            return Err(Status::invalid_argument(format!("observation has {} values; this policy reads {expected}", observation.len())));
        }
        if let Some(i) = observation.iter().position(|x| !x.is_finite()) {
            return Err(Status::invalid_argument(format!("observation[{i}] is {}, not a finite number", observation[i])));
        }
        Ok(ActResponse { action: self.policy.deterministic_actions(observation), policy_version: self.policy.version() })
    }
}

type ActionStream = Pin<Box<dyn Stream<Item = Result<ActResponse, Status>> + Send>>;

#[tonic::async_trait]
impl Pilot for PilotService {
    async fn describe(&self, _: Request<DescribeRequest>) -> Result<Response<PilotDescription>, Status> {
        Ok(Response::new(PilotDescription {
            observation_dim: self.policy.observation_dim() as u32,
            action_dim: self.policy.action_dim() as u32,
            observation_frame: self.policy.observation_layout().frame.name().into(),
            policy_version: self.policy.version(),
            observation_layout: self.policy.observation_layout().describe(),
        }))
    }

    async fn act(&self, request: Request<ActRequest>) -> Result<Response<ActResponse>, Status> {
        self.act(&request.into_inner().observation).map(Response::new)
    }

    type FlyStream = ActionStream;

    /// Answers each observation in order; a refused one ends the stream with its status.
    async fn fly(&self, request: Request<Streaming<ActRequest>>) -> Result<Response<Self::FlyStream>, Status> {
        let mut inbound = request.into_inner();
        let service = self.clone();
        let (tx, rx) = tokio::sync::mpsc::channel(16);
        tokio::spawn(async move {
            loop {
                let reply = match inbound.message().await {
                    Ok(Some(request)) => service.act(&request.observation),
                    Ok(None) => break,
                    Err(status) => Err(status),
                };
                let failed = reply.is_err();
                if tx.send(reply).await.is_err() || failed {
                    break;
                }
            }
        });
        Ok(Response::new(Box::pin(tokio_stream::wrappers::ReceiverStream::new(rx))))
    }
}
