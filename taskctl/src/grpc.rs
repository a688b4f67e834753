//! The `dronerace.v1.TaskController` gRPC adapter: converts messages and errors around a
//! [`TaskController`], snapshots after every change before answering (so nothing acknowledged
//! is lost when the process dies), and broadcasts assignment and switch events.

use std::net::SocketAddr;
use std::path::PathBuf;
use std::pin::Pin;
use std::sync::Arc;

use proto::convert::track_to_proto;
use proto::security::MAX_MESSAGE_BYTES;
use proto::transport::check_actor_name;
use proto::v1;
use proto::v1::task_controller_server::{TaskController as TaskControllerRpc, TaskControllerServer};
use tokio::sync::broadcast;
use tokio_stream::Stream;
use tonic::{Request, Response, Status};

use crate::controller::{EnvSlot, SwitchEvent, TaskController, TaskError};

/// The service: the controller, where its snapshot goes, and the event feed.
pub struct TaskControllerService {
    /// An async lock: a request that panics cannot poison it for the ones after, and it may be
    /// held across the snapshot write, which runs on the blocking pool.
    controller: Arc<tokio::sync::Mutex<TaskController>>,
    snapshot: PathBuf,
    events: broadcast::Sender<v1::TaskEvent>,
}

fn status(e: TaskError) -> Status {
    match e {
        TaskError::UnknownEnv { .. } | TaskError::UnknownActor(_) => Status::not_found(e.to_string()),
        TaskError::NotFinite { .. } | TaskError::RewardCount { .. } => Status::invalid_argument(e.to_string()),
        TaskError::StaleIteration { .. } | TaskError::StaleRollout { .. } => Status::already_exists(e.to_string()),
        TaskError::NoRoom { .. } => Status::resource_exhausted(e.to_string()),
        TaskError::RangeChanged { .. } => Status::failed_precondition(e.to_string()),
        TaskError::Generate(_) | TaskError::NoEnvironments => Status::internal(e.to_string()),
    }
}

fn switch_event(e: &SwitchEvent) -> v1::SwitchEvent {
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

fn task(controller: &TaskController, env: usize, slot: &EnvSlot) -> v1::Task {
    let actor = controller.actors().iter().find(|a| (a.first_env..a.first_env + a.envs).contains(&env));
    v1::Task {
        env: env as u32,
        actor: actor.map(|a| a.actor.clone()).unwrap_or_default(),
        track: Some(track_to_proto(&slot.track)),
        window_length: slot.window.len() as u32,
        rho: slot.rho,
        q: slot.q,
        switches: slot.switches,
        last_rollout: slot.last_iteration,
    }
}

impl TaskControllerService {
    /// Serves `controller`, writing its snapshot to `snapshot` after every change.
    pub fn new(controller: TaskController, snapshot: PathBuf) -> Self {
        Self { controller: Arc::new(tokio::sync::Mutex::new(controller)), snapshot, events: broadcast::channel(1024).0 }
    }

    /// The tonic server with message limits.
    pub fn into_server(self) -> TaskControllerServer<Self> {
        TaskControllerServer::new(self).max_decoding_message_size(MAX_MESSAGE_BYTES).max_encoding_message_size(MAX_MESSAGE_BYTES)
    }

    /// Applies `change` to a copy, persists the copy, then makes it current: a change is either
    /// durable and visible, or neither. Changes are serialised by the lock; the fsync runs off
    /// the async executor.
    async fn change<T>(&self, change: impl FnOnce(&mut TaskController) -> Result<T, TaskError>) -> Result<(T, TaskController), Status> {
        let mut guard = self.controller.lock().await;
        let mut next = guard.clone();
        let out = change(&mut next).map_err(status)?;
        let (path, bytes) = (self.snapshot.clone(), next.to_snapshot_bytes());
        tokio::task::spawn_blocking(move || racetracks::files::write_atomic(&path, &bytes))
            .await
            .map_err(|e| Status::internal(format!("snapshot writer: {e}")))?
            .map_err(|e| Status::internal(format!("{}: {e}", self.snapshot.display())))?;
        *guard = next.clone();
        Ok((out, next))
    }
}

type EventStream = Pin<Box<dyn Stream<Item = Result<v1::TaskEvent, Status>> + Send>>;

#[tonic::async_trait]
impl TaskControllerRpc for TaskControllerService {
    async fn register(&self, request: Request<v1::RegisterRequest>) -> Result<Response<v1::RegisterResponse>, Status> {
        let r = request.into_inner();
        check_actor_name(&r.actor).map_err(Status::invalid_argument)?;
        let (range, controller) = self.change(|c| c.register(&r.actor, r.envs as usize)).await?;
        let tracks = controller.slots()[range.first_env..range.first_env + range.envs].iter().map(|s| track_to_proto(&s.track)).collect();
        let event = v1::task_event::Event::Registered(v1::ActorRegistered {
            actor: range.actor.clone(),
            first_env: range.first_env as u32,
            envs: range.envs as u32,
        });
        let _ = self.events.send(v1::TaskEvent { event: Some(event) });
        Ok(Response::new(v1::RegisterResponse { first_env: range.first_env as u32, tracks, next_rollout: range.next_rollout }))
    }

    async fn report(&self, request: Request<v1::ReportRequest>) -> Result<Response<v1::ReportResponse>, Status> {
        let r = request.into_inner();
        let ((switches, history_before), controller) = self
            .change(|c| {
                let history_before = c.history().len();
                c.report_rollout(&r.actor, r.rollout, &r.cumulative_rewards).map(|s| (s, history_before))
            })
            .await?;
        for e in &controller.history()[history_before..] {
            let _ = self.events.send(v1::TaskEvent { event: Some(v1::task_event::Event::Switched(switch_event(e))) });
        }
        let switches =
            switches.into_iter().map(|(env, track)| v1::Assignment { env: env as u32, track: Some(track_to_proto(&track)) }).collect();
        Ok(Response::new(v1::ReportResponse { switches }))
    }

    async fn get_task(&self, request: Request<v1::GetTaskRequest>) -> Result<Response<v1::Task>, Status> {
        let env = request.into_inner().env as usize;
        let c = self.controller.lock().await;
        let slot = c.slots().get(env).ok_or_else(|| status(TaskError::UnknownEnv { env, envs: c.len() }))?;
        Ok(Response::new(task(&c, env, slot)))
    }

    async fn list_tasks(&self, _: Request<v1::ListTasksRequest>) -> Result<Response<v1::ListTasksResponse>, Status> {
        let c = self.controller.lock().await;
        let tasks = c.slots().iter().enumerate().map(|(env, slot)| task(&c, env, slot)).collect();
        Ok(Response::new(v1::ListTasksResponse { tasks }))
    }

    async fn get_summary(&self, _: Request<v1::SummaryRequest>) -> Result<Response<v1::Summary>, Status> {
        let c = self.controller.lock().await;
        // Counted as the in-process trainer counts them, so both modes report the same number.
        Ok(Response::new(v1::Summary { envs: c.len() as u32, switches: c.history().len() as u64, mean_q: c.mean_q() }))
    }

    async fn get_switch_history(&self, request: Request<v1::SwitchHistoryRequest>) -> Result<Response<v1::SwitchHistoryResponse>, Status> {
        let from = request.into_inner().from;
        let c = self.controller.lock().await;
        let events = c.history().iter().skip(usize::try_from(from).unwrap_or(usize::MAX)).map(switch_event).collect();
        Ok(Response::new(v1::SwitchHistoryResponse { events }))
    }

    type WatchEventsStream = EventStream;

    async fn watch_events(&self, _: Request<v1::WatchEventsRequest>) -> Result<Response<EventStream>, Status> {
        let mut events = self.events.subscribe();
        let stream = async_stream(move |tx| async move {
            loop {
                match events.recv().await {
                    Ok(e) => {
                        if tx.send(Ok(e)).await.is_err() {
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
    security: &proto::Security,
    service: TaskControllerService,
    shutdown: impl std::future::Future<Output = ()>,
) -> Result<(), Box<dyn std::error::Error + Send + Sync>> {
    security.check_listen(&addr)?;
    let (health, reflection) = proto::health_and_reflection(&["dronerace.v1.TaskController"]).await;
    security
        .server()?
        .add_service(health)
        .add_service(reflection)
        .add_service(tonic::service::interceptor::InterceptedService::new(service.into_server(), security.token_check()))
        .serve_with_shutdown(addr, shutdown)
        .await?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::switching::SwitchParams;
    use racetracks::generator::TrackGenerator;

    /// A request whose handler panics mid-change must leave the service usable: the lock is
    /// not poisoned, the state is the one before the failed change, later changes persist.
    #[test]
    fn a_request_that_panics_does_not_break_the_ones_after() {
        let dir = tempfile::tempdir().unwrap();
        let controller = TaskController::new(4, TrackGenerator::default(), SwitchParams::default(), 5).unwrap();
        let service = Arc::new(TaskControllerService::new(controller, dir.path().join("snapshot")));
        let rt = tokio::runtime::Builder::new_current_thread().enable_all().build().unwrap();
        rt.block_on(async {
            let panicking = service.clone();
            let crashed =
                tokio::spawn(async move { panicking.change(|_| -> Result<(), TaskError> { panic!("handler bug") }).await.map(|_| ()) })
                    .await;
            assert!(crashed.is_err_and(|e| e.is_panic()));
            let registered = service.register(Request::new(v1::RegisterRequest { actor: "a".into(), envs: 4 })).await.unwrap().into_inner();
            assert_eq!(registered.tracks.len(), 4);
            let listed = service.list_tasks(Request::new(v1::ListTasksRequest {})).await.unwrap().into_inner();
            assert_eq!(listed.tasks.len(), 4);
            let summary = service.get_summary(Request::new(v1::SummaryRequest {})).await.unwrap().into_inner();
            assert_eq!((summary.envs, summary.switches, summary.mean_q), (4, 0, None));
        });
        let restored = TaskController::restore(&dir.path().join("snapshot")).unwrap();
        assert_eq!(restored.slots().len(), 4, "the change after the panic was persisted");
    }
}
