//! The time leases, stalls and replanning intervals are measured in.
//!
//! The executive reads its clock instead of `Instant::now()` so that a test
//! (or a simulation running faster than real time) can move time on by hand:
//! tokio's paused time cannot be used here, because it auto-advances whenever
//! the runtime waits on SQLite's own threads.

use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Duration;

use tokio::time::Instant;

/// Wall-clock time, or time moved on by hand.
#[derive(Debug, Clone, Default)]
pub enum Clock {
    /// tokio's clock (real time outside paused tests).
    #[default]
    Tokio,
    /// Time that only moves when [`ManualClock::advance`] is called.
    Manual(Arc<ManualClock>),
}

impl Clock {
    /// A clock that moves by hand, and its handle.
    pub fn manual() -> (Self, Arc<ManualClock>) {
        let handle = Arc::new(ManualClock { start: Instant::now(), elapsed_us: AtomicU64::new(0) });
        (Self::Manual(Arc::clone(&handle)), handle)
    }

    /// Now.
    pub fn now(&self) -> Instant {
        match self {
            Self::Tokio => Instant::now(),
            Self::Manual(clock) => clock.now(),
        }
    }
}

/// See [`Clock::Manual`].
#[derive(Debug)]
pub struct ManualClock {
    start: Instant,
    elapsed_us: AtomicU64,
}

impl ManualClock {
    /// Moves time on by `by`.
    pub fn advance(&self, by: Duration) {
        self.elapsed_us.fetch_add(by.as_micros() as u64, Ordering::SeqCst);
    }

    fn now(&self) -> Instant {
        self.start + Duration::from_micros(self.elapsed_us.load(Ordering::SeqCst))
    }
}
