//! The gRPC transport: actors stream rollouts to the learner's `PushRollouts` and watch its
//! `WatchWeights`; the learner's service adapter refuses bad rollouts on arrival (answering the
//! actor at once), the link admits what it hands over, and `Status` answers from the
//! [`LearnerBoard`].

use std::pin::Pin;
use std::sync::Arc;
use std::sync::mpsc::{Receiver, RecvTimeoutError, SyncSender, TrySendError};
use std::time::Duration;

// parking_lot's lock does not poison: a panic in one request cannot fail every later one.
use parking_lot::Mutex;

use prost::bytes::Bytes;
use rollout::RolloutChunk;
use tokio::runtime::Handle;
use tokio::sync::{mpsc, watch};
use tokio_stream::Stream;
use tokio_stream::wrappers::ReceiverStream;
use tonic::codegen::InterceptedService;
use tonic::transport::Channel;
use tonic::{Code, Request, Response, Status, Streaming};

use crate::board::LearnerBoard;
use crate::budget::{ByteBudget, OverBudget, Reservation};
use crate::chunking::{Reassembler, split};
use crate::link::{ActorLink, Admission, Delivery, LearnerLink, LinkError, Received, Refusal, WeightsUpdate};
use crate::refusal;
use crate::security::{AddToken, Caller, MAX_MESSAGE_BYTES, Security, SecurityError};
use proto::v1;
use proto::v1::learner_client::LearnerClient;
use proto::v1::learner_server::{Learner, LearnerServer};

/// A learner client carrying the bearer token.
pub type AuthedLearnerClient = LearnerClient<InterceptedService<Channel, AddToken>>;

/// A learner client for `url` with message limits and the token.
pub fn learner_client(url: &str, security: &Security) -> Result<AuthedLearnerClient, SecurityError> {
    Ok(LearnerClient::with_interceptor(security.channel(url)?, security.token_header())
        .max_decoding_message_size(MAX_MESSAGE_BYTES)
        .max_encoding_message_size(MAX_MESSAGE_BYTES))
}

/// The learner's `Status` at `url`, asked and waited for up to `timeout` (blocks).
pub fn learner_status(url: &str, security: &Security, timeout: std::time::Duration) -> Result<proto::v1::StatusResponse, LinkError> {
    let context = format!("Learner/Status at {url}");
    let rt = tokio::runtime::Builder::new_current_thread().enable_all().build().map_err(|e| LinkError::new(&context, e))?;
    rt.block_on(async {
        let mut client = learner_client(url, security).map_err(|e| LinkError::new(&context, e))?;
        match tokio::time::timeout(timeout, client.status(proto::v1::StatusRequest {})).await {
            Ok(Ok(reply)) => Ok(reply.into_inner()),
            Ok(Err(status)) => Err(LinkError::new(&context, status.message())),
            Err(_) => Err(LinkError::new(&context, format!("no answer within {} s", timeout.as_secs_f64()))),
        }
    })
}

/// The actor's end over gRPC (calls run on the given tokio runtime; methods block).
pub struct GrpcActorLink {
    runtime: Handle,
    client: AuthedLearnerClient,
    newest: Arc<Mutex<Option<WeightsUpdate>>>,
    watcher: tokio::task::JoinHandle<()>,
}

impl GrpcActorLink {
    /// Connects lazily to the learner at `url` and starts watching its weights (reconnecting
    /// by itself whenever the learner goes away).
    pub fn connect(runtime: Handle, url: &str, security: &Security) -> Result<Self, SecurityError> {
        let client = {
            let _guard = runtime.enter();
            learner_client(url, security)?
        };
        let newest = Arc::new(Mutex::new(None));
        let watcher = runtime.spawn(watch_weights(client.clone(), newest.clone()));
        Ok(Self { runtime, client, newest, watcher })
    }
}

impl Drop for GrpcActorLink {
    fn drop(&mut self) {
        self.watcher.abort();
    }
}

async fn watch_weights(mut client: AuthedLearnerClient, newest: Arc<Mutex<Option<WeightsUpdate>>>) {
    loop {
        match client.watch_weights(v1::WatchWeightsRequest {}).await {
            Ok(response) => {
                let mut stream = response.into_inner();
                let mut parts = Reassembler::default();
                loop {
                    match stream.message().await {
                        Ok(Some(p)) => match parts.push(p.part, p.parts, &p.data) {
                            Ok(Some(blob)) => {
                                let update = WeightsUpdate {
                                    learner_epoch: p.learner_epoch,
                                    version: p.version,
                                    max_policy_lag: p.max_policy_lag,
                                    blob,
                                };
                                *newest.lock() = Some(update);
                            }
                            Ok(None) => {}
                            Err(e) => {
                                tracing::warn!("weights stream: {e}");
                                break;
                            }
                        },
                        Ok(None) => break,
                        Err(status) => {
                            tracing::debug!("weights stream ended: {status}");
                            break;
                        }
                    }
                }
            }
            Err(status) => tracing::debug!("learner not reachable for weights: {status}"),
        }
        tokio::time::sleep(Duration::from_millis(500)).await;
    }
}

impl ActorLink for GrpcActorLink {
    fn send_rollout(&mut self, actor: &str, learner_epoch: u64, chunk: &RolloutChunk) -> Result<(), LinkError> {
        let messages: Vec<v1::RolloutPart> = split(Bytes::from(chunk.to_bytes()))
            .into_iter()
            .map(|(part, parts, data)| v1::RolloutPart {
                actor: actor.to_string(),
                learner_epoch,
                policy_version: chunk.policy_version,
                part,
                parts,
                data,
            })
            .collect();
        let mut client = self.client.clone();
        self.runtime
            .block_on(client.push_rollouts(tokio_stream::iter(messages)))
            .map_err(|s| LinkError(format!("push rollout: {}: {}", s.code(), s.message())))?;
        Ok(())
    }

    fn newest_weights(&mut self) -> Result<Option<WeightsUpdate>, LinkError> {
        Ok(self.newest.lock().take())
    }
}

/// The service's rollout check at arrival: answers the actor at once; the link checks again on
/// receipt (the version moves while rollouts queue).
fn check_on_arrival(board: &LearnerBoard, actor: &str, epoch: u64, chunk: &RolloutChunk) -> Result<(), Status> {
    Admission::check_current(board.admission().as_ref(), actor, epoch, chunk).map_err(|r| match r {
        // Not a bad rollout: it came too early, and the same one may be admitted shortly.
        Refusal::Starting => Status::unavailable(r.to_string()),
        Refusal::Malformed(m) => {
            board.count_refused();
            refusal::status(Code::InvalidArgument, m)
        }
        wrong @ Refusal::WrongVersion { .. } => {
            board.count_refused();
            refusal::status(Code::FailedPrecondition, wrong.to_string())
        }
    })
}

/// Newest weights as the messages of a `WatchWeights` stream: split into parts once when
/// published, and shared by every watcher (parts are reference-counted `Bytes`, so N watchers
/// cost no N copies of the blob).
type WeightsWatch = Arc<watch::Sender<Option<Arc<Vec<v1::WeightsPart>>>>>;

/// A decoded rollout on its way to the training loop, with the budget it holds until taken.
type Queued = (Delivery, Reservation);

/// The `Learner` service adapter.
pub struct LearnerService {
    board: Arc<LearnerBoard>,
    weights: WeightsWatch,
    deliveries: Option<SyncSender<Queued>>,
    budget: Arc<ByteBudget>,
}

/// Serves the learner's gRPC services (`dronerace.v1.Learner` with health and reflection) on
/// `listener` until `shutdown`; call it inside the runtime that is to run the connections.
pub async fn serve_learner(
    listener: tokio::net::TcpListener,
    security: Security,
    service: LearnerService,
    shutdown: impl std::future::Future<Output = ()>,
) -> Result<(), Box<dyn std::error::Error + Send + Sync>> {
    crate::with_discovery(security.server()?, &["dronerace.v1.Learner"], security.token_check())
        .await
        .add_service(InterceptedService::new(service.into_server(), security.token_check()))
        .serve_with_incoming_shutdown(crate::listener::incoming(listener), shutdown)
        .await?;
    Ok(())
}

impl LearnerService {
    /// A service taking rollouts over gRPC, and the link the training loop reads them from;
    /// both read and write `board`. Rollouts between arrival and training hold at most
    /// `budget_bytes` (the rollout queue's length is the budget's business, not a count).
    pub fn with_rollouts(board: Arc<LearnerBoard>, budget_bytes: usize) -> (Self, GrpcLearnerLink) {
        let weights: WeightsWatch = Arc::new(watch::channel(None).0);
        let (tx, rx) = std::sync::mpsc::sync_channel(4096);
        let link = GrpcLearnerLink { board: board.clone(), weights: weights.clone(), deliveries: rx };
        (Self { board, weights, deliveries: Some(tx), budget: ByteBudget::new(budget_bytes) }, link)
    }

    /// A service answering `Status` only, from `board`: rollouts and weights go over iceoryx2.
    pub fn status_only(board: Arc<LearnerBoard>) -> Self {
        Self { board, weights: Arc::new(watch::channel(None).0), deliveries: None, budget: ByteBudget::new(0) }
    }

    /// The budget its rollouts hold.
    pub fn budget(&self) -> Arc<ByteBudget> {
        self.budget.clone()
    }

    /// The tonic server with message limits.
    pub fn into_server(self) -> LearnerServer<Self> {
        LearnerServer::new(self).max_decoding_message_size(MAX_MESSAGE_BYTES).max_encoding_message_size(MAX_MESSAGE_BYTES)
    }
}

/// The learner's end over gRPC.
pub struct GrpcLearnerLink {
    board: Arc<LearnerBoard>,
    weights: WeightsWatch,
    deliveries: Receiver<Queued>,
}

impl LearnerLink for GrpcLearnerLink {
    fn admit(&mut self, admission: Admission) {
        self.board.set_admission(admission);
    }

    fn receive(&mut self, timeout: Duration) -> Result<Option<Received>, LinkError> {
        match self.deliveries.recv_timeout(timeout) {
            // The service refused what was wrong on arrival, answering the actor at once; the
            // version may have moved on while the rollout was queued, so it is checked again.
            // Taken off the queue: the training loop's batch holds it now, not the budget.
            Ok((d, _released)) => Ok(Some(Admission::receive(self.board.admission().as_ref(), d))),
            Err(RecvTimeoutError::Timeout) => Ok(None),
            Err(RecvTimeoutError::Disconnected) => Err(LinkError("the gRPC server stopped".into())),
        }
    }

    fn publish(&mut self, weights: &WeightsUpdate) -> Result<(), LinkError> {
        let parts = split(Bytes::from(weights.blob.clone()))
            .into_iter()
            .map(|(part, parts, data)| v1::WeightsPart {
                learner_epoch: weights.learner_epoch,
                version: weights.version,
                max_policy_lag: weights.max_policy_lag,
                part,
                parts,
                data,
            })
            .collect();
        self.weights.send_replace(Some(Arc::new(parts)));
        Ok(())
    }
}

/// What a learner whose actors use iceoryx2 answers to the transport calls.
fn shm_only() -> Status {
    Status::failed_precondition("this learner exchanges rollouts and weights over iceoryx2 (--transport shm)")
}

type PartStream = Pin<Box<dyn Stream<Item = Result<v1::WeightsPart, Status>> + Send>>;

#[tonic::async_trait]
impl Learner for LearnerService {
    async fn push_rollouts(&self, request: Request<Streaming<v1::RolloutPart>>) -> Result<Response<v1::PushSummary>, Status> {
        let Some(deliveries) = &self.deliveries else { return Err(shm_only()) };
        let over_budget = |e: OverBudget| Status::resource_exhausted(e.to_string());
        let caller = Caller::of(&request);
        let mut stream = request.into_inner();
        let mut parts = Reassembler::default();
        let mut held = Reservation::new(&self.budget);
        let mut accepted = 0;
        while let Some(part) = stream.message().await? {
            // An actor's token speaks for that actor alone: checked before anything is kept.
            caller.may_speak_for(&part.actor).inspect_err(|_| self.board.count_refused())?;
            // Reserved before the reassembler copies the part in.
            held.resize(parts.buffered() + part.data.len()).map_err(over_budget)?;
            let Some(bytes) =
                parts.push(part.part, part.parts, &part.data).map_err(|e| refusal::status(Code::InvalidArgument, e.to_string()))?
            else {
                continue;
            };
            // Nothing is decoded without an admission: its limits bound the header, and what the
            // header announces is reserved before decoding starts.
            let Some(admission) = self.board.admission() else { return Err(Status::unavailable(Refusal::Starting.to_string())) };
            let limits = admission.limits();
            let transitions = RolloutChunk::announced_transitions(&bytes, &limits).map_err(|e| {
                self.board.count_refused();
                refusal::status(Code::InvalidArgument, e.to_string())
            })?;
            held.resize(bytes.len() + limits.decoded_bytes(transitions)).map_err(over_budget)?;
            // Decoding a large rollout takes milliseconds of CPU: not on the async workers, which
            // also answer Status and stream weights.
            let decoded = tokio::task::spawn_blocking(move || RolloutChunk::from_bytes(&bytes, &limits))
                .await
                .map_err(|e| Status::internal(format!("decoding a rollout: {e}")))?;
            let chunk = decoded.map_err(|e| {
                self.board.count_refused();
                refusal::status(Code::InvalidArgument, e.to_string())
            })?;
            held.resize(limits.decoded_bytes(chunk.transitions())).map_err(over_budget)?;
            if chunk.policy_version != part.policy_version {
                self.board.count_refused();
                return Err(Status::invalid_argument("policy_version differs from the chunk's own"));
            }
            check_on_arrival(&self.board, &part.actor, part.learner_epoch, &chunk)?;
            let delivery = Delivery { actor: part.actor, learner_epoch: part.learner_epoch, chunk };
            let queued = std::mem::replace(&mut held, Reservation::new(&self.budget));
            match deliveries.try_send((delivery, queued)) {
                Ok(()) => accepted += 1,
                Err(TrySendError::Full(_)) => return Err(Status::resource_exhausted("the learner's rollout queue is full")),
                Err(TrySendError::Disconnected(_)) => return Err(Status::unavailable("the learner is stopping")),
            }
        }
        // A stream that ends mid-payload delivered nothing of it.
        if parts.is_partial() {
            return Err(Status::invalid_argument("the stream ended inside a rollout; its parts were discarded"));
        }
        Ok(Response::new(v1::PushSummary { accepted }))
    }

    type WatchWeightsStream = PartStream;

    async fn watch_weights(&self, _: Request<v1::WatchWeightsRequest>) -> Result<Response<PartStream>, Status> {
        if self.deliveries.is_none() {
            return Err(shm_only());
        }
        let mut updates = self.weights.subscribe();
        let (tx, rx) = mpsc::channel(8);
        tokio::spawn(async move {
            loop {
                let current = updates.borrow_and_update().clone();
                for message in current.iter().flat_map(|parts| parts.iter()) {
                    if tx.send(Ok(message.clone())).await.is_err() {
                        return;
                    }
                }
                if updates.changed().await.is_err() {
                    return;
                }
            }
        });
        Ok(Response::new(Box::pin(ReceiverStream::new(rx))))
    }

    async fn status(&self, _: Request<v1::StatusRequest>) -> Result<Response<v1::StatusResponse>, Status> {
        let s = self.board.status();
        Ok(Response::new(v1::StatusResponse {
            learner_epoch: s.learner_epoch,
            iteration: s.iteration,
            env_steps: s.env_steps,
            sps: s.sps,
            connected_actors: s.connected_actors,
            policy_lag: s.policy_lag,
            refused_chunks: self.board.refused(),
        }))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::link::LearnerStatus;
    use crate::security::Security;
    use std::alloc::{GlobalAlloc, Layout, System};
    use std::sync::atomic::{AtomicUsize, Ordering};

    /// Counts the bytes this test binary holds, and the most it held since the last reset.
    struct Counting;
    static HELD: AtomicUsize = AtomicUsize::new(0);
    static PEAK: AtomicUsize = AtomicUsize::new(0);

    // SAFETY: forwards to the system allocator unchanged; only counts.
    unsafe impl GlobalAlloc for Counting {
        unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
            let held = HELD.fetch_add(layout.size(), Ordering::SeqCst) + layout.size();
            PEAK.fetch_max(held, Ordering::SeqCst);
            // SAFETY: the caller's contract is System's.
            unsafe { System.alloc(layout) }
        }
        unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
            HELD.fetch_sub(layout.size(), Ordering::SeqCst);
            // SAFETY: the caller's contract is System's.
            unsafe { System.dealloc(ptr, layout) }
        }
    }

    #[global_allocator]
    static ALLOCATOR: Counting = Counting;

    /// The tests that measure allocations run one at a time.
    static MEASURING: Mutex<()> = Mutex::new(());

    /// A learner service on a local port for a run of 8 environments × 16 steps.
    fn learner(rt: &tokio::runtime::Runtime, images: bool, budget: usize) -> (String, Arc<ByteBudget>) {
        learner_behind(rt, images, budget, &Security::default())
    }

    /// [`learner`] behind `security`'s token check.
    fn learner_behind(rt: &tokio::runtime::Runtime, images: bool, budget: usize, security: &Security) -> (String, Arc<ByteBudget>) {
        let board = Arc::new(LearnerBoard::default());
        board.set_admission(Admission {
            learner_epoch: 1,
            version: 0,
            max_policy_lag: 0,
            observation_dim: 3,
            action_dim: 2,
            images,
            total_envs: 8,
            rollout_steps: 16,
        });
        let (service, link) = LearnerService::with_rollouts(board, budget);
        let held = service.budget();
        std::mem::forget(link); // keeps the queue open for the test's lifetime
        let listener = rt.block_on(tokio::net::TcpListener::bind("127.0.0.1:0")).unwrap();
        let url = format!("http://{}", listener.local_addr().unwrap());
        let service = tonic::service::interceptor::InterceptedService::new(service.into_server(), security.token_check());
        let server = security.server().unwrap().add_service(service);
        let incoming = {
            let _runtime = rt.enter();
            crate::listener::incoming(listener)
        };
        rt.spawn(server.serve_with_incoming(incoming));
        (url, held)
    }

    /// Pushes pre-encoded rollout bytes as one payload; the status, and the most bytes this
    /// process held above what it held before the push.
    fn push(rt: &tokio::runtime::Runtime, url: &str, bytes: Bytes) -> (Result<u64, Status>, usize) {
        push_as(rt, url, bytes, "a", &Security::default())
    }

    /// [`push`] as `actor`, with `security`'s token.
    fn push_as(rt: &tokio::runtime::Runtime, url: &str, bytes: Bytes, actor: &str, security: &Security) -> (Result<u64, Status>, usize) {
        let messages: Vec<v1::RolloutPart> = split(bytes)
            .into_iter()
            .map(|(part, parts, data)| v1::RolloutPart { actor: actor.into(), learner_epoch: 1, policy_version: 0, part, parts, data })
            .collect();
        let _guard = rt.enter();
        let mut client = learner_client(url, security).unwrap();
        let before = HELD.load(Ordering::SeqCst);
        PEAK.store(before, Ordering::SeqCst);
        let answer = rt.block_on(client.push_rollouts(tokio_stream::iter(messages))).map(|r| r.into_inner().accepted);
        (answer, PEAK.load(Ordering::SeqCst).saturating_sub(before))
    }

    /// 64 environments × 1,024 steps of zero images: ~2.5 MB on the wire, 462 MB of images decoded.
    fn amplifying() -> Bytes {
        let mut chunk = RolloutChunk::zeroed(0, 0, 64, 1024, 3, 2);
        chunk.images = vec![0; chunk.transitions() * sim::camera::IMAGE_PIXELS];
        Bytes::from(chunk.to_bytes())
    }

    #[test]
    #[allow(clippy::print_stderr, reason = "the figure BENCHMARKS.md quotes")]
    fn the_amplifying_rollout_is_refused_without_the_learner_allocating_it() {
        let _one_at_a_time = MEASURING.lock();
        let rt = tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build().unwrap();
        let bytes = amplifying();
        assert!(bytes.len() < 3 << 20, "{} bytes on the wire", bytes.len());
        for images in [false, true] {
            let (url, budget) = learner(&rt, images, 64 << 20);
            let (answer, peak) = push(&rt, &url, bytes.clone());
            let status = answer.unwrap_err();
            assert_eq!(status.code(), tonic::Code::InvalidArgument, "{status:?}");
            let expected = if images { "more than the run's 8 × 16" } else { "more than the run's" };
            assert!(status.message().contains(expected), "{}", status.message());
            assert!(peak < 16 << 20, "the learner side held {peak} more bytes (images: {images})");
            eprintln!("amplifying rollout of {} bytes (images: {images}): refused, {peak} bytes held at most", bytes.len());
            assert_eq!(budget.used(), 0, "everything reserved was given back");
        }
    }

    #[test]
    fn rollouts_beyond_the_byte_budget_are_refused_and_within_it_accepted() {
        let _one_at_a_time = MEASURING.lock();
        let rt = tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build().unwrap();
        let chunk = RolloutChunk::zeroed(0, 0, 8, 16, 3, 2);
        let limits = Admission {
            learner_epoch: 1,
            version: 0,
            max_policy_lag: 0,
            observation_dim: 3,
            action_dim: 2,
            images: false,
            total_envs: 8,
            rollout_steps: 16,
        }
        .limits();
        let needed = chunk.to_bytes().len() + limits.decoded_bytes(8 * 16);
        // (the chunk is as large as the run allows, so its header announces the run's maximum)
        let (url, budget) = learner(&rt, false, needed);
        assert_eq!(push(&rt, &url, Bytes::from(chunk.to_bytes())).0.unwrap(), 1);
        assert_eq!(budget.used(), limits.decoded_bytes(8 * 16), "the queued chunk holds its decoded size until taken");
        let (answer, _) = push(&rt, &url, Bytes::from(chunk.to_bytes()));
        let status = answer.unwrap_err();
        assert_eq!(status.code(), tonic::Code::ResourceExhausted, "{status:?}");
        assert!(status.message().contains("budget"), "{}", status.message());
    }

    /// With one token for every actor, any actor could send rollouts under another's name. An
    /// actor's own token sends under its name only.
    #[test]
    fn an_actor_token_pushes_under_its_own_name_only() {
        let rt = tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build().unwrap();
        let dir = tempfile::tempdir().unwrap();
        let token_file = |name: &str, text: &str| {
            let path = dir.path().join(name);
            std::fs::write(&path, text).unwrap();
            Security::load(&crate::NetworkConfig { token_file: Some(path), ..Default::default() }).unwrap()
        };
        let run = token_file("run", "s3cret");
        let (url, _) = learner_behind(&rt, false, 64 << 20, &run);
        let actor_b = token_file("b", &run.actor_token("b").unwrap());
        let chunk = || Bytes::from(RolloutChunk::zeroed(0, 0, 2, 16, 3, 2).to_bytes());
        let refused = push_as(&rt, &url, chunk(), "a", &actor_b).0.unwrap_err();
        assert_eq!(refused.code(), tonic::Code::PermissionDenied, "{refused:?}");
        assert_eq!(push_as(&rt, &url, chunk(), "b", &actor_b).0.unwrap(), 1);
        assert_eq!(push_as(&rt, &url, chunk(), "a", &run).0.unwrap(), 1, "the run's token speaks for any actor");
    }

    #[test]
    fn status_answers_from_the_board() {
        let board = Arc::new(LearnerBoard::default());
        let service = LearnerService::status_only(board.clone());
        board.set_status(LearnerStatus { iteration: 3, ..Default::default() });
        board.count_refused();
        let rt = tokio::runtime::Builder::new_current_thread().build().unwrap();
        let status = rt.block_on(service.status(Request::new(v1::StatusRequest {}))).unwrap().into_inner();
        assert_eq!((status.iteration, status.refused_chunks), (3, 1));
    }
}
