//! The gRPC face of a [`serving::Pilot`] (`dronerace.v1.Pilot`): the one place its errors
//! become status codes, the bounds on races a server flies at once, and the server itself with
//! health, reflection, TLS and the token as on every other dronerace server.

use std::pin::Pin;
use std::sync::Arc;

use serving::{DroneState, Pilot, PilotError};
use sim::Racer;
use tokio_stream::Stream;
use tonic::{Request, Response, Status, Streaming};

use proto::v1::pilot_server::{Pilot as PilotRpc, PilotServer};
use proto::v1::race_request::Kind;
use proto::v1::{ActRequest, ActResponse, DescribeRequest, PilotDescription, RaceCommand, RaceRequest};

/// Serves `pilot` as `dronerace.v1.Pilot` on `listener` until `shutdown`.
pub async fn serve<P: Pilot + 'static>(
    listener: tokio::net::TcpListener,
    security: &crate::Security,
    pilot: P,
    shutdown: impl std::future::Future<Output = ()>,
) -> Result<(), Box<dyn std::error::Error + Send + Sync>> {
    crate::with_discovery(security.server()?, &["dronerace.v1.Pilot"], security.token_check())
        .await
        .add_service(tonic::service::interceptor::InterceptedService::new(PilotServer::new(PilotGrpc::new(pilot)), security.token_check()))
        .serve_with_incoming_shutdown(crate::listener::incoming(listener), shutdown)
        .await?;
    Ok(())
}

/// Races flown at once: each holds its racing line and stream buffers (~6 MiB), so the bound
/// keeps a server's memory bounded whatever its clients open.
const MAX_RACES: usize = 32;
/// Races whose track is being read and its racing line built at once, on the blocking pool:
/// the async worker meanwhile answers health and every other stream.
const MAX_STARTING: usize = 2;

/// The gRPC face of a [`Pilot`].
struct PilotGrpc<P> {
    pilot: Arc<P>,
    /// The served policy's version, sent with every action.
    version: u64,
    /// Places for races ([`MAX_RACES`]).
    races: Arc<tokio::sync::Semaphore>,
    /// Places for race starts ([`MAX_STARTING`]).
    starting: Arc<tokio::sync::Semaphore>,
}

impl<P: Pilot> PilotGrpc<P> {
    fn new(pilot: P) -> Self {
        Self {
            version: pilot.describe().policy_version,
            pilot: Arc::new(pilot),
            races: Arc::new(tokio::sync::Semaphore::new(MAX_RACES)),
            starting: Arc::new(tokio::sync::Semaphore::new(MAX_STARTING)),
        }
    }
}

/// The one place pilot errors become status codes: the pilot's own failures are INTERNAL, a
/// refused request INVALID_ARGUMENT with the pilot's message (naming the field, and quoting at
/// most a bounded part of what was sent).
fn status(e: PilotError) -> Status {
    let code = if e.is_internal() { tonic::Code::Internal } else { tonic::Code::InvalidArgument };
    crate::refusal::status(code, e.to_string())
}

/// A race on `track_toml`, read and its racing line built on the blocking pool, at most
/// [`MAX_STARTING`] at a time.
async fn start_race<P: Pilot + 'static>(pilot: Arc<P>, starting: Arc<tokio::sync::Semaphore>, track_toml: String) -> Result<Racer, Status> {
    let _place = starting.acquire_owned().await.map_err(|_| Status::unavailable("the server is stopping"))?;
    match tokio::task::spawn_blocking(move || pilot.start_race(&track_toml)).await {
        Ok(started) => started.map_err(status),
        Err(e) => Err(Status::internal(format!("starting the race failed: {e}"))),
    }
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
        let service = Self { pilot: self.pilot.clone(), version: self.version, races: self.races.clone(), starting: self.starting.clone() };
        let answers = answer_each(request.into_inner(), (), move |(), request: ActRequest| {
            let answer = service.act(&request.observation);
            async move { ((), Some(answer)) }
        });
        Ok(Response::new(answers))
    }

    type RaceStream = CommandStream;

    /// A `RaceStart`, then a command per `DroneState`; a refused message ends the stream with
    /// its status (INVALID_ARGUMENT naming the field). At most [`MAX_RACES`] at once.
    async fn race(&self, request: Request<Streaming<RaceRequest>>) -> Result<Response<Self::RaceStream>, Status> {
        let place = self.races.clone().try_acquire_owned().map_err(|_| {
            Status::resource_exhausted(format!("this server flies at most {MAX_RACES} races at once: try again when one has ended"))
        })?;
        let (pilot, starting) = (self.pilot.clone(), self.starting.clone());
        let answers = answer_each(request.into_inner(), None, move |racer: Option<Racer>, request: RaceRequest| {
            // The stream holds its place among the races until it ends.
            let _place = &place;
            let (pilot, starting) = (pilot.clone(), starting.clone());
            async move {
                match request.kind {
                    Some(Kind::Start(start)) => match start_race(pilot, starting, start.track_toml).await {
                        Ok(started) => (Some(started), None),
                        Err(refused) => (racer, Some(Err(refused))),
                    },
                    Some(Kind::State(s)) => {
                        let Some(mut r) = racer else {
                            let refused =
                                Status::invalid_argument("a DroneState before any RaceStart: start the race with its track first");
                            return (None, Some(Err(refused)));
                        };
                        let state = DroneState {
                            position: &s.position,
                            velocity: &s.velocity,
                            orientation: &s.orientation,
                            angular_velocity: &s.angular_velocity,
                        };
                        let command = pilot.race_step(&mut r, state).map_err(status).map(|c| RaceCommand {
                            action: c.action,
                            target_gate: c.target_gate as u32,
                            laps: c.laps,
                        });
                        (Some(r), Some(command))
                    }
                    None => (racer, Some(Err(Status::invalid_argument("RaceRequest holds neither a RaceStart nor a DroneState")))),
                }
            }
        });
        Ok(Response::new(answers))
    }
}

/// Answers a stream's messages in order with `answer`, which takes the stream's state (a race,
/// or nothing) and gives it back with its reply (`None`: this message needs no answer); the
/// first refusal ends the stream with its status. Answers run on the async worker: anything
/// slow in them goes to the blocking pool.
fn answer_each<S, In, Out, Answer>(
    mut inbound: Streaming<In>,
    mut state: S,
    mut answer: impl FnMut(S, In) -> Answer + Send + 'static,
) -> Pin<Box<dyn Stream<Item = Result<Out, Status>> + Send>>
where
    S: Send + 'static,
    In: Send + 'static,
    Out: Send + 'static,
    Answer: std::future::Future<Output = (S, Option<Result<Out, Status>>)> + Send,
{
    let (tx, rx) = tokio::sync::mpsc::channel(16);
    tokio::spawn(async move {
        loop {
            let reply = match inbound.message().await {
                Ok(Some(message)) => {
                    let (next, reply) = answer(state, message).await;
                    state = next;
                    match reply {
                        Some(reply) => reply,
                        None => continue,
                    }
                }
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
