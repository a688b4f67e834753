//! What the learner's training loop shares with whatever answers for it (the `Learner` gRPC
//! service's `Status` and its rollout check), whichever transport carries the rollouts.

use std::sync::atomic::{AtomicU64, Ordering};

// parking_lot's lock does not poison: a panic in one request cannot fail every later one.
use parking_lot::Mutex;

use crate::link::{Admission, LearnerStatus};

/// The learner's current admission, status and refused-rollout count.
#[derive(Debug, Default)]
pub struct LearnerBoard {
    admission: Mutex<Option<Admission>>,
    status: Mutex<LearnerStatus>,
    refused: AtomicU64,
}

impl LearnerBoard {
    /// Rollouts admitted from now on.
    pub fn set_admission(&self, admission: Admission) {
        *self.admission.lock() = Some(admission);
    }

    /// The current admission (`None` while the learner is starting).
    pub fn admission(&self) -> Option<Admission> {
        *self.admission.lock()
    }

    /// Replaces the status.
    pub fn set_status(&self, status: LearnerStatus) {
        *self.status.lock() = status;
    }

    /// The status as last set.
    pub fn status(&self) -> LearnerStatus {
        self.status.lock().clone()
    }

    /// Counts a refused rollout.
    pub fn count_refused(&self) {
        self.refused.fetch_add(1, Ordering::Relaxed);
    }

    /// Rollouts refused so far.
    pub fn refused(&self) -> u64 {
        self.refused.load(Ordering::Relaxed)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A thread that panics while holding the status lock must not fail later requests.
    #[test]
    fn a_panic_while_holding_a_lock_does_not_break_later_requests() {
        let board = std::sync::Arc::new(LearnerBoard::default());
        let holder = board.clone();
        let crashed = std::thread::spawn(move || {
            let _held = holder.status.lock();
            panic!("bug while holding the lock");
        })
        .join();
        assert!(crashed.is_err());
        board.set_status(LearnerStatus { iteration: 3, ..Default::default() });
        assert_eq!(board.status().iteration, 3);
    }
}
