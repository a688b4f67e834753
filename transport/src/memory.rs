//! The transport for training in one process: the same [`ActorLink`] and [`LearnerLink`] the
//! processes use, over a queue and a slot in memory, so the in-process mode runs the actor and
//! learner loops of the distributed runtime unchanged.

use std::collections::VecDeque;
use std::sync::Arc;
use std::time::Duration;

use parking_lot::{Condvar, Mutex};
use rollout::RolloutChunk;

use crate::link::{ActorLink, Admission, Delivery, LearnerLink, LinkError, Received, WeightsUpdate};

#[derive(Default)]
struct Channel {
    rollouts: Mutex<VecDeque<Delivery>>,
    arrived: Condvar,
    /// The newest weights and how many were published before them.
    weights: Mutex<(u64, Option<WeightsUpdate>)>,
}

/// The actor's end of an in-memory link; a clone is another actor's end of the same link.
#[derive(Clone)]
pub struct MemoryActorLink {
    channel: Arc<Channel>,
    seen: u64,
}

/// The learner's end of an in-memory link.
pub struct MemoryLearnerLink {
    channel: Arc<Channel>,
    admission: Option<Admission>,
}

/// A connected pair: rollouts sent on the first arrive on the second, weights the other way.
pub fn memory_link() -> (MemoryActorLink, MemoryLearnerLink) {
    let channel = Arc::new(Channel::default());
    (MemoryActorLink { channel: channel.clone(), seen: 0 }, MemoryLearnerLink { channel, admission: None })
}

impl ActorLink for MemoryActorLink {
    fn send_rollout(&mut self, actor: &str, learner_epoch: u64, chunk: &RolloutChunk) -> Result<(), LinkError> {
        let delivery = Delivery { actor: actor.to_string(), learner_epoch, chunk: chunk.clone() };
        self.channel.rollouts.lock().push_back(delivery);
        self.channel.arrived.notify_one();
        Ok(())
    }

    fn newest_weights(&mut self) -> Result<Option<WeightsUpdate>, LinkError> {
        let weights = self.channel.weights.lock();
        if weights.0 == self.seen {
            return Ok(None);
        }
        self.seen = weights.0;
        Ok(weights.1.clone())
    }
}

impl LearnerLink for MemoryLearnerLink {
    fn admit(&mut self, admission: Admission) {
        self.admission = Some(admission);
    }

    fn receive(&mut self, timeout: Duration) -> Result<Option<Received>, LinkError> {
        let mut rollouts = self.channel.rollouts.lock();
        if rollouts.is_empty() {
            self.channel.arrived.wait_for(&mut rollouts, timeout);
        }
        Ok(rollouts.pop_front().map(|d| Admission::receive(self.admission.as_ref(), d)))
    }

    fn publish(&mut self, weights: &WeightsUpdate) -> Result<(), LinkError> {
        let mut newest = self.channel.weights.lock();
        *newest = (newest.0 + 1, Some(weights.clone()));
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::link::Refusal;

    #[test]
    fn rollouts_arrive_in_order_admitted_and_only_the_newest_weights_are_picked_up_once() {
        let (mut actor, mut learner) = memory_link();
        assert_eq!(actor.newest_weights().unwrap(), None);
        for version in [1, 2] {
            learner.publish(&WeightsUpdate { learner_epoch: 7, version, max_policy_lag: 0, blob: vec![version as u8] }).unwrap();
        }
        assert_eq!(actor.newest_weights().unwrap().map(|w| w.version), Some(2));
        assert_eq!(actor.newest_weights().unwrap(), None, "picked up once");
        actor.send_rollout("a", 7, &RolloutChunk::zeroed(2, 0, 2, 1, 3, 4)).unwrap();
        let early = learner.receive(Duration::ZERO).unwrap();
        assert!(matches!(early, Some(Received::Refused { refusal: Refusal::Starting, .. })), "nothing is admitted before admit: {early:?}");
        learner.admit(Admission {
            learner_epoch: 7,
            version: 2,
            max_policy_lag: 0,
            observation_dim: 3,
            action_dim: 4,
            images: false,
            total_envs: 4,
            rollout_steps: 1,
        });
        for (version, first_env) in [(2, 0), (2, 2), (1, 0)] {
            actor.send_rollout("a", 7, &RolloutChunk::zeroed(version, first_env, 2, 1, 3, 4)).unwrap();
        }
        let mut next = || learner.receive(Duration::ZERO).unwrap().unwrap();
        let order: Vec<usize> = (0..2)
            .map(|_| match next() {
                Received::Rollout(d) => d.chunk.first_env,
                other => panic!("{other:?}"),
            })
            .collect();
        assert_eq!(order, [0, 2]);
        assert!(matches!(next(), Received::Refused { refusal, .. } if refusal.kind() == "too_old"), "admitted at the link");
        assert_eq!(learner.receive(Duration::from_millis(10)).unwrap(), None);
    }
}
