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
use proto::v1::race_request::Kind;
use proto::v1::{ActRequest, ActResponse, DescribeRequest, DroneState, PilotDescription, RaceCommand, RaceRequest};
use sim::{Racer, Track};
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
    let mut service = PilotService::new(Arc::new(Policy::from_blob(&blob)?));
    if let Some(path) = &args.track {
        service = service.with_track(Arc::new(racetracks::read_track(path)?));
    }
    let stop = stop_flag()?;
    let rt = async_runtime(1)?;
    let listener = rt.block_on(tokio::net::TcpListener::bind(args.listen)).with_context(|| format!("serve: binding {}", args.listen))?;
    crate::services::spawn_health(&rt, args.health_listen, &["dronerace.v1.Pilot"], stop.clone())?;
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
    /// What a `Race` flies when its start names no track.
    track: Option<Arc<Track>>,
}

impl PilotService {
    /// Serves `policy`.
    pub fn new(policy: Arc<Policy>) -> Self {
        Self { policy, track: None }
    }

    /// Races on `track` when a `RaceStart` names none.
    pub fn with_track(self, track: Arc<Track>) -> Self {
        Self { track: Some(track), ..self }
    }

    /// The race a `RaceStart` begins: its track file's text, or the server's track.
    fn start_race(&self, track_toml: &str) -> Result<Racer, Status> {
        let track = if track_toml.trim().is_empty() {
            self.track.clone().ok_or_else(|| {
                Status::invalid_argument("RaceStart.track_toml is empty and this server has no --track: send the track file's text")
            })?
        } else {
            let parsed = racetracks::parse_track(track_toml, std::path::Path::new("RaceStart.track_toml"))
                .map_err(|e| Status::invalid_argument(e.to_string()))?;
            Arc::new(parsed)
        };
        Ok(Racer::new(track, self.policy.observation_layout()))
    }

    /// The command for one drone state of a race.
    fn race_step(&self, racer: &mut Racer, state: &DroneState) -> Result<RaceCommand, Status> {
        let body = body_state(state)?;
        let observation = racer.observe(&body);
        let action = self.act(&observation)?.action;
        let flown: [f32; 4] = action.as_slice().try_into().map_err(|_| Status::internal("the policy's action is not 4 numbers"))?;
        racer.acted(&flown);
        Ok(RaceCommand { action, target_gate: racer.target_gate() as u32, laps: racer.laps() })
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
        let action = finite(self.policy.deterministic_actions(observation))?;
        Ok(ActResponse { action, policy_version: self.policy.version() })
    }
}

/// The action if every number of it is finite: a drone must never be sent NaN. Policy files
/// are checked for finite weights when read; this holds the line for whatever slips past.
fn finite(action: Vec<f32>) -> Result<Vec<f32>, Status> {
    match action.iter().position(|a| !a.is_finite()) {
        Some(i) => Err(Status::internal(format!("the policy produced action[{i}] = {}; nothing is sent", action[i]))),
        None => Ok(action),
    }
}

/// A `DroneState` as the simulator's body state; INVALID_ARGUMENT naming the field whose length
/// is wrong or that holds a non-finite number or a quaternion far from unit length.
fn body_state(state: &DroneState) -> Result<sim::quadrotor::BodyState, Status> {
    let field = |name: &str, values: &[f64], len: usize| -> Result<(), Status> {
        if values.len() != len {
            return Err(Status::invalid_argument(format!("DroneState.{name} has {} numbers; it needs {len}", values.len())));
        }
        if let Some(i) = values.iter().position(|v| !v.is_finite()) {
            return Err(Status::invalid_argument(format!("DroneState.{name}[{i}] is {}, not a finite number", values[i])));
        }
        Ok(())
    };
    field("position", &state.position, 3)?;
    field("velocity", &state.velocity, 3)?;
    field("orientation", &state.orientation, 4)?;
    field("angular_velocity", &state.angular_velocity, 3)?;
    let q = &state.orientation;
    let norm = q.iter().map(|v| v * v).sum::<f64>().sqrt();
    if (norm - 1.0).abs() > 1e-3 {
        return Err(Status::invalid_argument(format!("DroneState.orientation has norm {norm}; it must be a unit quaternion (w, x, y, z)")));
    }
    let v3 = |v: &[f64]| sim::nalgebra::Vector3::new(v[0], v[1], v[2]);
    Ok(sim::quadrotor::BodyState {
        position: v3(&state.position),
        attitude: sim::nalgebra::Quaternion::new(q[0], q[1], q[2], q[3]),
        velocity: v3(&state.velocity),
        body_rates: v3(&state.angular_velocity),
    })
}

type ActionStream = Pin<Box<dyn Stream<Item = Result<ActResponse, Status>> + Send>>;
type CommandStream = Pin<Box<dyn Stream<Item = Result<RaceCommand, Status>> + Send>>;

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
        let service = self.clone();
        Ok(Response::new(answer_each(request.into_inner(), move |request: ActRequest| Some(service.act(&request.observation)))))
    }

    type RaceStream = CommandStream;

    /// A `RaceStart`, then a command per `DroneState`; a refused message ends the stream with
    /// its status (INVALID_ARGUMENT naming the field).
    async fn race(&self, request: Request<Streaming<RaceRequest>>) -> Result<Response<Self::RaceStream>, Status> {
        let service = self.clone();
        let mut racer: Option<Racer> = None;
        Ok(Response::new(answer_each(request.into_inner(), move |request: RaceRequest| match request.kind {
            Some(Kind::Start(start)) => match service.start_race(&start.track_toml) {
                Ok(r) => {
                    racer = Some(r);
                    None
                }
                Err(status) => Some(Err(status)),
            },
            Some(Kind::State(state)) => Some(match racer.as_mut() {
                Some(r) => service.race_step(r, &state),
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

#[cfg(test)]
mod tests {
    use super::*;
    use policy::{ActorCritic, Architecture, Device, ObsNormalizer, WeightsBlob};

    #[test]
    fn a_policy_file_with_nan_weights_is_refused_and_no_nan_action_is_sent() {
        let arch = Architecture::cpu();
        let net = ActorCritic::new(&arch, -0.5, 1, &Device::flex());
        let mut blob = WeightsBlob::from_model(1, &arch, &ObsNormalizer::new(arch.observation_dim), &net);
        let healthy = PilotService::new(Arc::new(Policy::from_blob(&blob).unwrap()));
        assert!(healthy.act(&vec![0.1; arch.observation_dim]).unwrap().action.iter().all(|a| a.is_finite()));
        // A file with a NaN weight is refused when read, naming the parameter. (Built in memory
        // and flown, such a network acts with zeros on this backend, not NaN: only the check
        // when the file is read tells the policy is broken.)
        blob.params[1].values[3] = f32::NAN;
        let error = WeightsBlob::from_bytes(&blob.to_bytes()).unwrap_err().to_string();
        assert!(error.contains("parameter 1") && error.contains("not a finite weight"), "{error}");
        // Whatever slips past, the service never sends a non-finite action.
        let status = finite(vec![0.5, f32::NAN, 0.0, 1.0]).unwrap_err();
        assert_eq!(status.code(), tonic::Code::Internal, "{status:?}");
        assert!(status.message().contains("action[1]"), "{}", status.message());
        assert_eq!(finite(vec![0.5, -1.0]).unwrap(), vec![0.5, -1.0]);
    }
}
