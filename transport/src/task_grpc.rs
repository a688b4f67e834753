//! The `dronerace.v1.TaskController` gRPC adapter: serves a [`LocalTasks`] on the network,
//! converting messages both ways and mapping [`TaskServiceError`] to status codes in one place.
//! Calls run on the blocking pool (they lock and fsync); changes are snapshotted before they
//! are answered, so nothing acknowledged is lost when the process dies.

use std::net::SocketAddr;
use std::pin::Pin;
use std::sync::Arc;

use taskctl::{LocalTasks, Summary, SwitchEvent, TaskError, TaskEvent, TaskInfo, TaskService, TaskServiceError};
use tokio::sync::broadcast;
use tokio_stream::Stream;
use tonic::{Code, Request, Response, Status};

use crate::convert::{track_from_proto, track_to_proto};
use crate::link::check_actor_name;
use crate::refusal;
use crate::security::{Caller, MAX_MESSAGE_BYTES};
use proto::v1;
use proto::v1::task_controller_server::{TaskController as TaskControllerRpc, TaskControllerServer};

/// The gRPC face of a [`LocalTasks`].
pub struct TaskControllerService {
    tasks: Arc<LocalTasks>,
}

/// The one place service errors become status codes (the client reads them back in
/// `task_client::status_error`).
fn status(e: TaskServiceError) -> Status {
    let code = match &e {
        TaskServiceError::Refused(refusal) => match refusal {
            TaskError::UnknownEnv { .. } | TaskError::UnknownActor(_) => Code::NotFound,
            TaskError::NotFinite { .. } | TaskError::RewardCount { .. } => Code::InvalidArgument,
            TaskError::RolloutTooFarAhead { .. } => Code::OutOfRange,
            TaskError::StaleIteration { .. } | TaskError::StaleRollout { .. } => Code::AlreadyExists,
            TaskError::NoRoom { .. } => Code::ResourceExhausted,
            TaskError::RangeChanged { .. } => Code::FailedPrecondition,
            TaskError::Generate(_) | TaskError::NoEnvironments => Code::Internal,
        },
        TaskServiceError::RefusedRemotely(_) | TaskServiceError::BadAnswer(_) => Code::Internal,
        // Not applied; the same call may succeed once the disk recovers.
        TaskServiceError::Snapshot { .. } | TaskServiceError::Unavailable(_) => Code::Unavailable,
    };
    refusal::status(code, e.to_string())
}

/// The actor a request speaks for, refused before any state is kept unless the name is valid
/// and the caller's token may speak for it.
fn speaking_for<T>(request: &Request<T>, actor: &str) -> Result<(), Status> {
    check_actor_name(actor).map_err(|e| refusal::status(Code::InvalidArgument, e.to_string()))?;
    Caller::of(request).may_speak_for(actor)
}

pub(crate) fn switch_to_proto(e: &SwitchEvent) -> v1::SwitchEvent {
    v1::SwitchEvent {
        rollout: e.iteration,
        env: e.env as u32,
        old_track: e.old_track.clone(),
        new_track: e.new_track.clone(),
        new_seed: e.new_seed,
        rho: e.rho,
        q: e.q,
    }
}

pub(crate) fn switch_from_proto(e: &v1::SwitchEvent) -> SwitchEvent {
    SwitchEvent {
        iteration: e.rollout,
        env: e.env as usize,
        old_track: e.old_track.clone(),
        new_track: e.new_track.clone(),
        new_seed: e.new_seed,
        rho: e.rho,
        q: e.q,
    }
}

fn task_to_proto(t: &TaskInfo) -> v1::Task {
    v1::Task {
        env: t.env as u32,
        actor: t.actor.clone().unwrap_or_default(),
        track: Some(track_to_proto(&t.track)),
        window_length: t.window_length as u32,
        rho: t.rho,
        q: t.q,
        switches: t.switches,
        last_rollout: t.last_rollout,
    }
}

/// A task as the client reads it; an answer without a valid track is a bad answer.
pub(crate) fn task_from_proto(t: &v1::Task) -> Result<TaskInfo, TaskServiceError> {
    let track = t.track.as_ref().ok_or_else(|| TaskServiceError::BadAnswer(format!("task {}: no track", t.env)))?;
    let track = track_from_proto(track).map_err(|e| TaskServiceError::BadAnswer(format!("task {}: {e}", t.env)))?;
    Ok(TaskInfo {
        env: t.env as usize,
        actor: (!t.actor.is_empty()).then(|| t.actor.clone()),
        track: Arc::new(track),
        window_length: t.window_length as usize,
        rho: t.rho,
        q: t.q,
        switches: t.switches,
        last_rollout: t.last_rollout,
    })
}

pub(crate) fn summary_from_proto(s: &v1::Summary) -> Summary {
    Summary { envs: s.envs as usize, switches: s.switches, mean_q: s.mean_q }
}

fn event_to_proto(e: &TaskEvent) -> v1::TaskEvent {
    let event = match e {
        TaskEvent::Registered(r) => v1::task_event::Event::Registered(v1::ActorRegistered {
            actor: r.actor.clone(),
            first_env: r.first_env as u32,
            envs: r.envs as u32,
        }),
        TaskEvent::Switched(s) => v1::task_event::Event::Switched(switch_to_proto(s)),
    };
    v1::TaskEvent { event: Some(event) }
}

impl TaskControllerService {
    /// Serves `tasks`.
    pub fn new(tasks: Arc<LocalTasks>) -> Self {
        Self { tasks }
    }

    /// The tonic server with message limits.
    pub fn into_server(self) -> TaskControllerServer<Self> {
        TaskControllerServer::new(self).max_decoding_message_size(MAX_MESSAGE_BYTES).max_encoding_message_size(MAX_MESSAGE_BYTES)
    }

    /// Runs `call` on the blocking pool (it may wait for the lock or an fsync); a call that
    /// panics answers `internal` and leaves the service usable.
    async fn blocking<T: Send + 'static>(
        &self,
        call: impl FnOnce(&LocalTasks) -> Result<T, TaskServiceError> + Send + 'static,
    ) -> Result<Response<T>, Status> {
        let tasks = self.tasks.clone();
        match tokio::task::spawn_blocking(move || call(&tasks)).await {
            Ok(result) => result.map(Response::new).map_err(status),
            Err(e) => Err(Status::internal(format!("task controller call failed: {e}"))),
        }
    }
}

type EventStream = Pin<Box<dyn Stream<Item = Result<v1::TaskEvent, Status>> + Send>>;

#[tonic::async_trait]
impl TaskControllerRpc for TaskControllerService {
    async fn register(&self, request: Request<v1::RegisterRequest>) -> Result<Response<v1::RegisterResponse>, Status> {
        speaking_for(&request, &request.get_ref().actor)?;
        let r = request.into_inner();
        self.blocking(move |t| {
            let registration = t.register(&r.actor, r.envs as usize)?;
            Ok(v1::RegisterResponse {
                first_env: registration.first_env as u32,
                tracks: registration.tracks.iter().map(|t| track_to_proto(t)).collect(),
                next_rollout: registration.next_rollout,
            })
        })
        .await
    }

    async fn report(&self, request: Request<v1::ReportRequest>) -> Result<Response<v1::ReportResponse>, Status> {
        speaking_for(&request, &request.get_ref().actor)?;
        let r = request.into_inner();
        self.blocking(move |t| {
            let switches = t.report(&r.actor, r.rollout, &r.cumulative_rewards)?;
            let switches = switches.iter().map(|(env, track)| v1::Assignment { env: *env as u32, track: Some(track_to_proto(track)) });
            Ok(v1::ReportResponse { switches: switches.collect() })
        })
        .await
    }

    async fn get_task(&self, request: Request<v1::GetTaskRequest>) -> Result<Response<v1::Task>, Status> {
        let env = request.into_inner().env as usize;
        self.blocking(move |t| t.task(env).map(|info| task_to_proto(&info))).await
    }

    async fn list_tasks(&self, _: Request<v1::ListTasksRequest>) -> Result<Response<v1::ListTasksResponse>, Status> {
        self.blocking(|t| Ok(v1::ListTasksResponse { tasks: t.tasks()?.iter().map(task_to_proto).collect() })).await
    }

    async fn get_summary(&self, _: Request<v1::SummaryRequest>) -> Result<Response<v1::Summary>, Status> {
        self.blocking(|t| {
            let s = t.summary()?;
            Ok(v1::Summary { envs: s.envs as u32, switches: s.switches, mean_q: s.mean_q })
        })
        .await
    }

    async fn get_switch_history(&self, request: Request<v1::SwitchHistoryRequest>) -> Result<Response<v1::SwitchHistoryResponse>, Status> {
        let from = request.into_inner().from;
        self.blocking(move |t| Ok(v1::SwitchHistoryResponse { events: t.switch_history(from)?.iter().map(switch_to_proto).collect() }))
            .await
    }

    type WatchEventsStream = EventStream;

    async fn watch_events(&self, _: Request<v1::WatchEventsRequest>) -> Result<Response<EventStream>, Status> {
        let mut events = self.tasks.subscribe();
        let stream = async_stream(move |tx| async move {
            loop {
                match events.recv().await {
                    Ok(e) => {
                        if tx.send(Ok(event_to_proto(&e))).await.is_err() {
                            return;
                        }
                    }
                    Err(broadcast::error::RecvError::Lagged(n)) => {
                        let _ = tx.send(Err(Status::data_loss(format!("{n} events were dropped: read faster")))).await;
                        return;
                    }
                    Err(broadcast::error::RecvError::Closed) => return,
                }
            }
        });
        Ok(Response::new(stream))
    }
}

/// A stream fed by a spawned task.
fn async_stream<F, Fut>(produce: F) -> EventStream
where
    F: FnOnce(tokio::sync::mpsc::Sender<Result<v1::TaskEvent, Status>>) -> Fut,
    Fut: std::future::Future<Output = ()> + Send + 'static,
{
    let (tx, rx) = tokio::sync::mpsc::channel(64);
    tokio::spawn(produce(tx));
    Box::pin(tokio_stream::wrappers::ReceiverStream::new(rx))
}

/// Serves the task controller on `addr` until `shutdown` resolves.
pub async fn serve(
    addr: SocketAddr,
    security: &crate::Security,
    service: TaskControllerService,
    shutdown: impl std::future::Future<Output = ()>,
) -> Result<(), Box<dyn std::error::Error + Send + Sync>> {
    security.check_listen(&addr)?;
    let listener = tokio::net::TcpListener::bind(addr).await?;
    crate::with_discovery(security.server()?, &["dronerace.v1.TaskController"], security.token_check())
        .await
        .add_service(tonic::service::interceptor::InterceptedService::new(service.into_server(), security.token_check()))
        .serve_with_incoming_shutdown(crate::listener::incoming(listener), shutdown)
        .await?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use racetracks::generator::TrackGenerator;
    use taskctl::{SwitchParams, TaskController};

    #[test]
    fn messages_and_refusals_cross_the_adapter_intact() {
        let controller = TaskController::new(4, TrackGenerator::default(), SwitchParams::default(), 5).unwrap();
        let local = Arc::new(LocalTasks::new(controller, None));
        let service = TaskControllerService::new(local.clone());
        let rt = tokio::runtime::Builder::new_multi_thread().worker_threads(1).enable_all().build().unwrap();
        rt.block_on(async {
            let registered = service.register(Request::new(v1::RegisterRequest { actor: "a".into(), envs: 4 })).await.unwrap();
            assert_eq!(registered.into_inner().tracks.len(), 4);
            let listed = service.list_tasks(Request::new(v1::ListTasksRequest {})).await.unwrap().into_inner();
            let decoded: Vec<TaskInfo> = listed.tasks.iter().map(|t| task_from_proto(t).unwrap()).collect();
            assert_eq!(decoded, local.tasks().unwrap());
            let e = service.get_task(Request::new(v1::GetTaskRequest { env: 9 })).await.unwrap_err();
            assert_eq!(e.code(), tonic::Code::NotFound, "{e:?}");
            let e = service.register(Request::new(v1::RegisterRequest { actor: "a".into(), envs: 3 })).await.unwrap_err();
            assert_eq!(e.code(), tonic::Code::FailedPrecondition, "{e:?}");
        });
    }

    /// What a hostile client of the task controller tried: speaking for another actor with its
    /// own actor token, a 3.9 MB name (echoed whole into `grpc-message` before), and a report
    /// numbered 2^64 − 1 (which froze the curriculum). Each is refused with its own code and a
    /// bounded message, and the honest actor carries on.
    #[test]
    fn hostile_registrations_and_reports_are_refused_by_code() {
        let controller = TaskController::new(4, TrackGenerator::default(), SwitchParams::default(), 5).unwrap();
        let service = TaskControllerService::new(Arc::new(LocalTasks::new(controller, None)));
        fn as_actor<T>(name: &str, message: T) -> Request<T> {
            let mut request = Request::new(message);
            request.extensions_mut().insert(Caller::Actor(name.into()));
            request
        }
        let rt = tokio::runtime::Builder::new_multi_thread().worker_threads(1).enable_all().build().unwrap();
        rt.block_on(async {
            service.register(as_actor("a", v1::RegisterRequest { actor: "a".into(), envs: 2 })).await.unwrap();
            let e = service.register(as_actor("a", v1::RegisterRequest { actor: "b".into(), envs: 2 })).await.unwrap_err();
            assert_eq!(e.code(), tonic::Code::PermissionDenied, "{e:?}");
            let report = |actor: &str, rollout| v1::ReportRequest { actor: actor.into(), rollout, cumulative_rewards: vec![1.0, 1.0] };
            let e = service.report(as_actor("b", report("a", 0))).await.unwrap_err();
            assert_eq!(e.code(), tonic::Code::PermissionDenied, "{e:?}");
            let long = "n".repeat(3_900_000);
            let e = service.report(Request::new(report(&long, 0))).await.unwrap_err();
            assert_eq!(e.code(), tonic::Code::InvalidArgument);
            assert!(e.message().len() <= crate::refusal::MAX_STATUS_MESSAGE, "{} bytes", e.message().len());
            let e = service.report(as_actor("a", report("a", u64::MAX))).await.unwrap_err();
            assert_eq!(e.code(), tonic::Code::OutOfRange, "{e:?}");
            service.report(as_actor("a", report("a", 0))).await.unwrap();
        });
    }
}
