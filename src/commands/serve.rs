//! `dronerace serve`: a trained policy as the gRPC service `dronerace.v1.Pilot`, for a flight
//! stack or a companion computer. One observation in raw units → the policy's deterministic
//! action (its own normaliser applied, clipped to [-1, 1] as evaluation does), unary or over a
//! stream for a control loop; health, reflection, TLS and the token as on every other server.

#![allow(clippy::print_stderr, reason = "the server's own terminal output: what it serves and where")]

use std::net::SocketAddr;
use std::path::PathBuf;
use std::pin::Pin;
use std::sync::Arc;

use crate::signal::stop_flag;
use anyhow::Context;
use clap::Args;
use policy::Policy;
use proto::v1::pilot_server::{Pilot as PilotRpc, PilotServer};
use proto::v1::race_request::Kind;
use proto::v1::{ActRequest, ActResponse, DescribeRequest, PilotDescription, RaceCommand, RaceRequest};
use runtime::pilot::{DroneState, Pilot, PilotError, PolicyPilot};
use sim::Racer;
use tokio_stream::Stream;
use tonic::{Request, Response, Status, Streaming};

use super::processes::{async_runtime, read_config, until};

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
    let config = read_config(&args.config)?;
    let security = proto::Security::load(&config.network)?;
    security.check_listen(&args.listen)?;
    let blob = learner::checkpoint::read_policy(&args.policy)?;
    let mut pilot = PolicyPilot::new(Arc::new(Policy::from_blob(&blob)?));
    if let Some(path) = &args.track {
        pilot = pilot.with_track(Arc::new(racetracks::read_track(path)?));
    }
    let service = PilotGrpc { version: pilot.describe().policy_version, pilot: Arc::new(pilot) };
    let stop = stop_flag()?;
    let rt = async_runtime(1)?;
    let listener = rt.block_on(tokio::net::TcpListener::bind(args.listen)).with_context(|| format!("serve: binding {}", args.listen))?;
    super::processes::spawn_health(&rt, args.health_listen, &["dronerace.v1.Pilot"], stop.clone())?;
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

/// The gRPC face of a [`Pilot`].
struct PilotGrpc<P> {
    pilot: Arc<P>,
    /// The served policy's version, sent with every action.
    version: u64,
}

/// The one place pilot errors become status codes: the pilot's own failures are INTERNAL, a
/// refused request INVALID_ARGUMENT with the pilot's message (naming the field).
fn status(e: PilotError) -> Status {
    if e.is_internal() { Status::internal(e.to_string()) } else { Status::invalid_argument(e.to_string()) }
}

type ActionStream = Pin<Box<dyn Stream<Item = Result<ActResponse, Status>> + Send>>;
type CommandStream = Pin<Box<dyn Stream<Item = Result<RaceCommand, Status>> + Send>>;

impl<P: Pilot + 'static> PilotGrpc<P> {
    /// The answer to one observation.
    fn act(&self, observation: &[f32]) -> Result<ActResponse, Status> {
        let action = self.pilot.act(observation).map_err(status)?;
        Ok(ActResponse { action, policy_version: self.version })
    }
}

#[tonic::async_trait]
impl<P: Pilot + 'static> PilotRpc for PilotGrpc<P> {
    async fn describe(&self, _: Request<DescribeRequest>) -> Result<Response<PilotDescription>, Status> {
        let d = self.pilot.describe();
        Ok(Response::new(PilotDescription {
            observation_dim: d.observation_dim as u32,
            action_dim: d.action_dim as u32,
            observation_frame: d.observation_frame,
            policy_version: d.policy_version,
            observation_layout: d.observation_layout,
        }))
    }

    async fn act(&self, request: Request<ActRequest>) -> Result<Response<ActResponse>, Status> {
        self.act(&request.into_inner().observation).map(Response::new)
    }

    type FlyStream = ActionStream;

    /// Answers each observation in order; a refused one ends the stream with its status.
    async fn fly(&self, request: Request<Streaming<ActRequest>>) -> Result<Response<Self::FlyStream>, Status> {
        let service = Self { pilot: self.pilot.clone(), version: self.version };
        Ok(Response::new(answer_each(request.into_inner(), move |request: ActRequest| Some(service.act(&request.observation)))))
    }

    type RaceStream = CommandStream;

    /// A `RaceStart`, then a command per `DroneState`; a refused message ends the stream with
    /// its status (INVALID_ARGUMENT naming the field).
    async fn race(&self, request: Request<Streaming<RaceRequest>>) -> Result<Response<Self::RaceStream>, Status> {
        let pilot = self.pilot.clone();
        let mut racer: Option<Racer> = None;
        Ok(Response::new(answer_each(request.into_inner(), move |request: RaceRequest| match request.kind {
            Some(Kind::Start(start)) => match pilot.start_race(&start.track_toml) {
                Ok(r) => {
                    racer = Some(r);
                    None
                }
                Err(e) => Some(Err(status(e))),
            },
            Some(Kind::State(s)) => Some(match racer.as_mut() {
                Some(r) => {
                    let state = DroneState {
                        position: &s.position,
                        velocity: &s.velocity,
                        orientation: &s.orientation,
                        angular_velocity: &s.angular_velocity,
                    };
                    pilot.race_step(r, state).map_err(status).map(|c| RaceCommand {
                        action: c.action,
                        target_gate: c.target_gate as u32,
                        laps: c.laps,
                    })
                }
                None => Err(Status::invalid_argument("a DroneState before any RaceStart: start the race with its track first")),
            }),
            None => Some(Err(Status::invalid_argument("RaceRequest holds neither a RaceStart nor a DroneState"))),
        })))
    }
}

/// Answers a stream's messages in order with `answer` (`None`: this message needs no answer);
/// the first refusal ends the stream with its status.
fn answer_each<In, Out>(
    mut inbound: Streaming<In>,
    mut answer: impl FnMut(In) -> Option<Result<Out, Status>> + Send + 'static,
) -> Pin<Box<dyn Stream<Item = Result<Out, Status>> + Send>>
where
    In: Send + 'static,
    Out: Send + 'static,
{
    let (tx, rx) = tokio::sync::mpsc::channel(16);
    tokio::spawn(async move {
        loop {
            let reply = match inbound.message().await {
                Ok(Some(message)) => match answer(message) {
                    Some(reply) => reply,
                    None => continue,
                },
                Ok(None) => break,
                Err(status) => Err(status),
            };
            let failed = reply.is_err();
            if tx.send(reply).await.is_err() || failed {
                break;
            }
        }
    });
    Box::pin(tokio_stream::wrappers::ReceiverStream::new(rx))
}
