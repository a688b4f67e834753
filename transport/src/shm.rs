//! The iceoryx2 transport: rollouts and weights through shared memory on one machine.
//!
//! Two publish–subscribe services per run: `dronerace/<run>/rollouts` (every actor publishes,
//! the learner subscribes) and `dronerace/<run>/weights` (the learner publishes with a history
//! of one, so an actor that starts or restarts gets the newest weights at once). Payloads are
//! byte slices in the wire formats of `policy`; the receiver decodes straight from shared memory.
//! Services are sized for the actor count; resources of processes killed with -9 are removed by
//! the next process that opens the run (dead-node cleanup).

use std::time::{Duration, Instant};

use iceoryx2::port::publisher::Publisher;
use iceoryx2::port::subscriber::Subscriber;
use iceoryx2::port::update_connections::UpdateConnections;
use iceoryx2::prelude::*;
use rollout::RolloutChunk;

use crate::link::{ActorLink, Admission, Delivery, LearnerLink, LinkError, Received, Refusal, WeightsUpdate};

/// Longest actor name a rollout header carries.
const NAME_BYTES: usize = 64;

/// Header of a rollout sample.
#[derive(Debug, Clone, Copy, ZeroCopySend)]
#[repr(C)]
pub struct RolloutHeader {
    learner_epoch: u64,
    name_len: u32,
    name: [u8; NAME_BYTES],
}

impl Default for RolloutHeader {
    fn default() -> Self {
        Self { learner_epoch: 0, name_len: 0, name: [0; NAME_BYTES] }
    }
}

/// Header of a weights sample.
#[derive(Debug, Clone, Copy, Default, ZeroCopySend)]
#[repr(C)]
pub struct WeightsHeader {
    learner_epoch: u64,
    version: u64,
    max_policy_lag: u32,
}

/// Which run's services to use, and how many actors they must hold.
#[derive(Clone, Debug, PartialEq)]
pub struct ShmConfig {
    /// Run identifier (unique per run on a machine; `[A-Za-z0-9_-]`).
    pub run: String,
    /// Most actor processes at once (restarts overlap briefly, so services hold twice this).
    pub max_actors: usize,
}

impl ShmConfig {
    fn service(&self, what: &str) -> String {
        format!("dronerace/{}/{what}", self.run)
    }
}

fn node() -> Result<Node<ipc::Service>, LinkError> {
    // iceoryx2 warns on stdout that it runs on its built-in defaults; that is intended here.
    set_log_level_from_env_or(LogLevel::Error);
    // Our processes handle Ctrl-C themselves; iceoryx2 must not install its own handler.
    let node = NodeBuilder::new()
        .signal_handling_mode(SignalHandlingMode::Disabled)
        .create::<ipc::Service>()
        .map_err(|e| LinkError::new("iceoryx2 node", e))?;
    // A process killed with -9 leaves its ports registered; free them before opening services.
    node.try_cleanup_dead_nodes();
    Ok(node)
}

type RolloutService = iceoryx2::service::port_factory::publish_subscribe::PortFactory<ipc::Service, [u8], RolloutHeader>;
type WeightsService = iceoryx2::service::port_factory::publish_subscribe::PortFactory<ipc::Service, [u8], WeightsHeader>;

fn rollout_service(node: &Node<ipc::Service>, config: &ShmConfig) -> Result<RolloutService, LinkError> {
    let name = config.service("rollouts");
    let slots = 2 * config.max_actors.max(1);
    node.service_builder(&name.as_str().try_into().map_err(|e| LinkError::new(&name, e))?)
        .publish_subscribe::<[u8]>()
        .user_header::<RolloutHeader>()
        .max_publishers(slots)
        .max_subscribers(2)
        .max_nodes(slots + 4)
        .subscriber_max_buffer_size(2 * slots)
        .history_size(0)
        .open_or_create()
        .map_err(|e| LinkError::new(&name, e))
}

fn weights_service(node: &Node<ipc::Service>, config: &ShmConfig) -> Result<WeightsService, LinkError> {
    let name = config.service("weights");
    let slots = 2 * config.max_actors.max(1);
    node.service_builder(&name.as_str().try_into().map_err(|e| LinkError::new(&name, e))?)
        .publish_subscribe::<[u8]>()
        .user_header::<WeightsHeader>()
        .max_publishers(2)
        .max_subscribers(slots)
        .max_nodes(slots + 4)
        .subscriber_max_buffer_size(2)
        .history_size(1)
        .open_or_create()
        .map_err(|e| LinkError::new(&name, e))
}

/// The actor's end over iceoryx2.
pub struct ShmActorLink {
    rollouts: Publisher<ipc::Service, [u8], RolloutHeader>,
    weights: Subscriber<ipc::Service, [u8], WeightsHeader>,
    // Declared last: ports must be dropped before their node.
    _node: Node<ipc::Service>,
}

impl ShmActorLink {
    /// Opens (or creates) the run's services.
    pub fn open(config: &ShmConfig) -> Result<Self, LinkError> {
        let node = node()?;
        let rollouts = rollout_service(&node, config)?
            .publisher_builder()
            .initial_max_slice_len(4 << 20)
            .allocation_strategy(AllocationStrategy::PowerOfTwo)
            .max_loaned_samples(1)
            .create()
            .map_err(|e| LinkError::new("rollout publisher", e))?;
        let weights = weights_service(&node, config)?
            .subscriber_builder()
            .history_request(1)
            .create()
            .map_err(|e| LinkError::new("weights subscriber", e))?;
        Ok(Self { rollouts, weights, _node: node })
    }
}

impl ActorLink for ShmActorLink {
    fn send_rollout(&mut self, actor: &str, learner_epoch: u64, chunk: &RolloutChunk) -> Result<(), LinkError> {
        let bytes = chunk.to_bytes();
        let mut sample = self.rollouts.loan_slice_uninit(bytes.len()).map_err(|e| LinkError::new("rollout loan", e))?;
        let header = sample.user_header_mut();
        let name = actor.as_bytes();
        let n = name.len().min(NAME_BYTES);
        header.learner_epoch = learner_epoch;
        header.name_len = n as u32;
        header.name[..n].copy_from_slice(&name[..n]);
        sample.write_from_slice(&bytes).send().map_err(|e| LinkError::new("rollout send", e))?;
        Ok(())
    }

    fn newest_weights(&mut self) -> Result<Option<WeightsUpdate>, LinkError> {
        let mut newest = None;
        while let Some(sample) = self.weights.receive().map_err(|e| LinkError::new("weights receive", e))? {
            let h = *sample.user_header();
            newest = Some(WeightsUpdate {
                learner_epoch: h.learner_epoch,
                version: h.version,
                max_policy_lag: h.max_policy_lag,
                blob: sample.payload().to_vec(),
            });
        }
        Ok(newest)
    }
}

/// The learner's end over iceoryx2.
pub struct ShmLearnerLink {
    rollouts: Subscriber<ipc::Service, [u8], RolloutHeader>,
    weights: Publisher<ipc::Service, [u8], WeightsHeader>,
    admission: Option<Admission>,
    _node: Node<ipc::Service>,
}

impl ShmLearnerLink {
    /// Opens (or creates) the run's services.
    pub fn open(config: &ShmConfig) -> Result<Self, LinkError> {
        let node = node()?;
        let rollouts =
            rollout_service(&node, config)?.subscriber_builder().create().map_err(|e| LinkError::new("rollout subscriber", e))?;
        let weights = weights_service(&node, config)?
            .publisher_builder()
            .initial_max_slice_len(1 << 20)
            .allocation_strategy(AllocationStrategy::PowerOfTwo)
            .max_loaned_samples(1)
            .create()
            .map_err(|e| LinkError::new("weights publisher", e))?;
        Ok(Self { rollouts, weights, admission: None, _node: node })
    }
}

impl LearnerLink for ShmLearnerLink {
    fn admit(&mut self, admission: Admission) {
        self.admission = Some(admission);
    }

    fn receive(&mut self, timeout: Duration) -> Result<Option<Received>, LinkError> {
        let deadline = Instant::now() + timeout;
        loop {
            if let Some(sample) = self.rollouts.receive().map_err(|e| LinkError::new("rollout receive", e))? {
                let h = sample.user_header();
                let name = &h.name[..(h.name_len as usize).min(NAME_BYTES)];
                let actor = String::from_utf8_lossy(name).into_owned();
                // Nothing is decoded before there is an admission to decode against: its limits
                // bound what the bytes may make the learner allocate.
                let Some(admission) = &self.admission else {
                    return Ok(Some(Received::Refused { actor, refusal: Refusal::Starting }));
                };
                return Ok(Some(match RolloutChunk::from_bytes(sample.payload(), &admission.limits()) {
                    Ok(chunk) => Admission::receive(Some(admission), Delivery { actor, learner_epoch: h.learner_epoch, chunk }),
                    Err(e) => Received::Refused { actor, refusal: Refusal::Malformed(e.to_string()) },
                }));
            }
            // A subscriber gets the weights history only when the publisher updates its
            // connections: do it while waiting, so actors that start late get the newest weights.
            self.weights.update_connections().map_err(|e| LinkError::new("weights connections", e))?;
            if Instant::now() >= deadline {
                return Ok(None);
            }
            // Rollouts arrive every few hundred milliseconds at most: polling at 1 kHz is free.
            std::thread::sleep(Duration::from_millis(1));
        }
    }

    fn publish(&mut self, weights: &WeightsUpdate) -> Result<(), LinkError> {
        let mut sample = self.weights.loan_slice_uninit(weights.blob.len()).map_err(|e| LinkError::new("weights loan", e))?;
        *sample.user_header_mut() =
            WeightsHeader { learner_epoch: weights.learner_epoch, version: weights.version, max_policy_lag: weights.max_policy_lag };
        sample.write_from_slice(&weights.blob).send().map_err(|e| LinkError::new("weights send", e))?;
        Ok(())
    }
}

/// Removes the shared-memory resources of iceoryx2 processes that died without cleaning up
/// (opening a node does it; services go with their last node).
pub fn cleanup_dead_nodes() -> Result<(), LinkError> {
    node().map(drop)
}
