//! The time leases, stalls and replanning intervals are measured in.
//!
//! The executive reads its clock instead of `Instant::now()` so that a test
//! or a simulation can move time on by hand: tokio's paused time cannot be
//! used here, because it auto-advances whenever the runtime waits on
//! SQLite's own threads. On a manual clock the lease and stall sweep runs
//! when time is moved on, not on the wall clock, and [`ManualClock::step`]
//! waits for it: a simulation then gives the same run on any machine at any
//! load.

use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Duration;

use tokio::sync::watch;
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
        let handle = Arc::new(ManualClock {
            start: Instant::now(),
            elapsed_us: AtomicU64::new(0),
            moves: watch::Sender::new(0),
            swept: watch::Sender::new(0),
        });
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
    /// Counts the moves of time.
    moves: watch::Sender<u64>,
    /// The last move the executive's sweep has handled.
    swept: watch::Sender<u64>,
}

impl ManualClock {
    /// Moves time on by `by`; the executive sweeps soon after.
    pub fn advance(&self, by: Duration) {
        self.move_on(by);
    }

    /// Moves time on by `by` and waits until the executive's lease and
    /// stall sweep has handled the new time (its effects are committed), so
    /// that the next request sees them whatever the machine's speed.
    pub async fn step(&self, by: Duration) {
        let moved = self.move_on(by);
        let mut swept = self.swept.subscribe();
        // An executive that has stopped sweeping (shut down) is not waited for.
        let _ = swept.wait_for(|s| *s >= moved).await;
    }

    fn move_on(&self, by: Duration) -> u64 {
        self.elapsed_us.fetch_add(by.as_micros().min(u128::from(u64::MAX)) as u64, Ordering::SeqCst);
        let mut moved = 0;
        self.moves.send_modify(|m| {
            *m += 1;
            moved = *m;
        });
        moved
    }

    /// A receiver that sees every move of time (the sweeper waits on it).
    pub(crate) fn moves(&self) -> watch::Receiver<u64> {
        self.moves.subscribe()
    }

    /// The sweep has handled move `moved`.
    pub(crate) fn mark_swept(&self, moved: u64) {
        self.swept.send_modify(|s| *s = (*s).max(moved));
    }

    fn now(&self) -> Instant {
        self.start + Duration::from_micros(self.elapsed_us.load(Ordering::SeqCst))
    }
}
