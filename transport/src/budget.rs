//! A byte budget for rollouts in flight at the learner: the parts being reassembled, the chunks
//! being decoded and the decoded chunks waiting for the training loop, across every stream.
//! Each holder reserves before it allocates, so the learner's rollout memory stays under the
//! budget whatever its peers send; a push that would exceed it is refused (RESOURCE_EXHAUSTED):
//! that rollout is lost, and its actor collects another once its wait for new weights times out.

use std::sync::Arc;
use std::sync::atomic::{AtomicUsize, Ordering};

/// The shared budget.
#[derive(Debug)]
pub struct ByteBudget {
    used: AtomicUsize,
    limit: usize,
}

impl ByteBudget {
    /// A budget of `limit` bytes, nothing reserved.
    pub fn new(limit: usize) -> Arc<Self> {
        Arc::new(Self { used: AtomicUsize::new(0), limit })
    }

    /// Bytes reserved now.
    pub fn used(&self) -> usize {
        self.used.load(Ordering::SeqCst)
    }

    /// The budget.
    pub fn limit(&self) -> usize {
        self.limit
    }
}

/// Bytes one holder has reserved; released when dropped.
#[derive(Debug)]
pub struct Reservation {
    budget: Arc<ByteBudget>,
    bytes: usize,
}

/// A reservation the budget cannot take.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
#[error("{wanted} more bytes of rollouts would exceed the learner's budget of {limit} ({used} in flight)")]
pub struct OverBudget {
    /// Bytes asked for beyond what the holder had.
    pub wanted: usize,
    /// Bytes in flight when asked.
    pub used: usize,
    /// The budget.
    pub limit: usize,
}

impl Reservation {
    /// An empty reservation on `budget`.
    pub fn new(budget: &Arc<ByteBudget>) -> Self {
        Self { budget: budget.clone(), bytes: 0 }
    }

    /// Makes this reservation exactly `bytes`: shrinking always succeeds; growing fails, holding
    /// what it held, when the budget lacks the difference.
    pub fn resize(&mut self, bytes: usize) -> Result<(), OverBudget> {
        let budget = &self.budget;
        if bytes <= self.bytes {
            budget.used.fetch_sub(self.bytes - bytes, Ordering::SeqCst);
            self.bytes = bytes;
            return Ok(());
        }
        let wanted = bytes - self.bytes;
        budget
            .used
            .fetch_update(Ordering::SeqCst, Ordering::SeqCst, |used| used.checked_add(wanted).filter(|&u| u <= budget.limit))
            .map_err(|used| OverBudget { wanted, used, limit: budget.limit })?;
        self.bytes = bytes;
        Ok(())
    }

    /// Bytes held.
    pub fn bytes(&self) -> usize {
        self.bytes
    }
}

impl Drop for Reservation {
    fn drop(&mut self) {
        self.budget.used.fetch_sub(self.bytes, Ordering::SeqCst);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reservations_share_the_budget_and_give_back_what_they_held() {
        let budget = ByteBudget::new(100);
        let mut a = Reservation::new(&budget);
        let mut b = Reservation::new(&budget);
        a.resize(60).unwrap();
        assert_eq!(b.resize(41), Err(OverBudget { wanted: 41, used: 60, limit: 100 }));
        assert_eq!((b.bytes(), budget.used()), (0, 60), "a refused growth holds what it held");
        b.resize(40).unwrap();
        a.resize(10).unwrap();
        assert_eq!(budget.used(), 50);
        drop(b);
        assert_eq!(budget.used(), 10);
        drop(a);
        assert_eq!(budget.used(), 0);
    }
}
