//! Planning turns: how many plans are made at once off the request path,
//! and which waiting plan goes next.
//!
//! A plan a robot is waiting for (a demand: its task ended, it joined, it
//! bid, ...) goes before the plans for map news alone, first come first
//! served within each; a plan that began to wait for map news and was
//! demanded meanwhile counts as demanded. Under load most plans are for map
//! news (on the 80 × 60 m office, about 1 000 plans a minute for 60–100
//! arrivals), and with one turn at a time an arrival queued behind up to one
//! plan of every other mission: 50 ms each, twenty missions, a second. A
//! mission with map news only keeps its robots on their tasks while it
//! waits, but not without end: a plan for map news that has waited
//! [`LONGEST_WAIT`] goes next whatever is demanded, so that a stream of
//! demands elsewhere cannot hold its mission's map news back for ever.

use std::collections::VecDeque;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};

use tokio::sync::oneshot;
use tokio::time::{Duration, Instant};

use crate::clock::Clock;

/// How long a plan for map news waits behind demanded ones at most, before
/// it goes first (on top of the plans being made when it would go).
pub(crate) const LONGEST_WAIT: Duration = Duration::from_secs(2);

/// A fixed number of turns, handed to the waiting plans demands first.
#[derive(Debug, Clone)]
pub(crate) struct Turns {
    inner: Arc<Mutex<Waiting>>,
}

#[derive(Debug)]
struct Waiting {
    free: usize,
    queue: VecDeque<Waiter>,
    /// What waits are measured on.
    clock: Clock,
}

#[derive(Debug)]
struct Waiter {
    /// Whether a robot waits for this plan, read when a turn is handed on:
    /// a demand that arrives while the plan waits counts.
    demanded: Arc<AtomicBool>,
    since: Instant,
    handed: oneshot::Sender<Turn>,
}

/// A turn held; dropping it hands it on.
#[derive(Debug)]
pub(crate) struct Turn {
    /// `None` once handed back.
    turns: Option<Arc<Mutex<Waiting>>>,
}

impl Turns {
    pub(crate) fn new(turns: usize, clock: Clock) -> Self {
        Self { inner: Arc::new(Mutex::new(Waiting { free: turns, queue: VecDeque::new(), clock })) }
    }

    /// A turn, at once if one is free, else when the plans before this one
    /// have had theirs: a plan that has waited [`LONGEST_WAIT`], then every
    /// plan that is `demanded` when a turn comes free, then the others in
    /// the order they came. `None` only if the turns are gone, which a
    /// handle to them rules out.
    pub(crate) async fn take(&self, demanded: Arc<AtomicBool>) -> Option<Turn> {
        let handed = {
            let mut waiting = self.lock();
            if waiting.free > 0 {
                waiting.free -= 1;
                return Some(self.turn());
            }
            let (sender, handed) = oneshot::channel();
            let since = waiting.clock.now();
            waiting.queue.push_back(Waiter { demanded, since, handed: sender });
            handed
        };
        handed.await.ok()
    }

    /// A turn if one is free now.
    #[cfg(test)]
    pub(crate) fn try_take(&self) -> Option<Turn> {
        let mut waiting = self.lock();
        (waiting.free > 0).then(|| {
            waiting.free -= 1;
            self.turn()
        })
    }

    fn turn(&self) -> Turn {
        Turn { turns: Some(Arc::clone(&self.inner)) }
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, Waiting> {
        self.inner.lock().unwrap_or_else(|e| e.into_inner())
    }
}

impl Drop for Turn {
    fn drop(&mut self) {
        let Some(inner) = self.turns.take() else { return };
        let mut waiting = inner.lock().unwrap_or_else(|e| e.into_inner());
        loop {
            let next = next_in_line(&waiting.queue, waiting.clock.now());
            let Some(next) = waiting.queue.remove(next) else {
                waiting.free += 1;
                return;
            };
            // A waiter that gave up (its task was cancelled) is passed over;
            // the turn it did not take is disarmed, not handed back twice.
            match next.handed.send(Turn { turns: Some(Arc::clone(&inner)) }) {
                Ok(()) => return,
                Err(mut refused) => refused.turns = None,
            }
        }
    }
}

/// Which waiter goes next: the first in line if it has waited too long
/// (the first has waited longest), else the first demanded one, else the
/// first.
fn next_in_line(queue: &VecDeque<Waiter>, now: Instant) -> usize {
    let overdue = queue.front().is_some_and(|w| now.duration_since(w.since) >= LONGEST_WAIT);
    if overdue {
        return 0;
    }
    queue.iter().position(|w| w.demanded.load(Ordering::Acquire)).unwrap_or(0)
}

#[cfg(test)]
mod tests {
    use std::sync::atomic::{AtomicBool, Ordering};
    use std::sync::{Arc, Mutex};

    use tokio::time::Duration;

    use super::{LONGEST_WAIT, Turn, Turns};
    use crate::clock::Clock;

    /// Runs the spawned tasks until none can move.
    async fn settle() {
        for _ in 0..20 {
            tokio::task::yield_now().await;
        }
    }

    /// The names of the plans in the order they had their turns.
    type Order = Arc<Mutex<Vec<&'static str>>>;

    /// A plan named `name` that waits for a turn, demanded while `demanded`
    /// holds, notes when it has it, and gives it back. It is queued once
    /// this returns.
    async fn wait_for_turn(
        turns: &Turns,
        order: &Order,
        name: &'static str,
        demanded: Arc<AtomicBool>,
    ) -> tokio::task::JoinHandle<()> {
        let (turns, order) = (turns.clone(), Arc::clone(order));
        let waiter = tokio::spawn(async move {
            let turn = turns.take(demanded).await.unwrap();
            order.lock().unwrap().push(name);
            settle().await;
            drop(turn);
        });
        settle().await;
        waiter
    }

    /// Hands the held turn on and waits for every plan to have had one.
    async fn release(held: Turn, waiters: Vec<tokio::task::JoinHandle<()>>) {
        drop(held);
        for waiter in waiters {
            waiter.await.unwrap();
        }
    }

    fn flag(demanded: bool) -> Arc<AtomicBool> {
        Arc::new(AtomicBool::new(demanded))
    }

    /// With the only turn held, two plans for map news wait; then a robot
    /// of the second one's mission arrives (a demand). The second goes
    /// first, then the first, then the turn is free again. First come first
    /// served (a semaphore) fails this, and so does an urgency fixed when a
    /// plan begins to wait.
    #[tokio::test(flavor = "current_thread")]
    async fn a_plan_demanded_while_it_waits_goes_before_map_news_that_waited_longer() {
        let turns = Turns::new(1, Clock::default());
        let held = turns.try_take().expect("one turn");
        let order = Order::default();
        let second = flag(false);
        let waiters = vec![
            wait_for_turn(&turns, &order, "first", flag(false)).await,
            wait_for_turn(&turns, &order, "second", Arc::clone(&second)).await,
        ];
        assert!(order.lock().unwrap().is_empty(), "both wait");
        second.store(true, Ordering::Release);
        release(held, waiters).await;
        assert_eq!(*order.lock().unwrap(), ["second", "first"]);
        assert!(turns.try_take().is_some(), "the turn came back");
    }

    /// Demands keep coming (here one waits whenever the turn is handed on),
    /// yet a plan for map news that has waited [`LONGEST_WAIT`] goes next.
    /// Without the bound it would wait behind every demand.
    #[tokio::test(flavor = "current_thread")]
    async fn map_news_waits_behind_demands_only_so_long() {
        let (clock, time) = Clock::manual();
        let turns = Turns::new(1, clock);
        let held = turns.try_take().expect("one turn");
        let order = Order::default();
        let mut waiters = vec![
            wait_for_turn(&turns, &order, "map news", flag(false)).await,
            wait_for_turn(&turns, &order, "demanded early", flag(true)).await,
        ];
        time.advance(LONGEST_WAIT);
        waiters.push(wait_for_turn(&turns, &order, "demanded late", flag(true)).await);
        release(held, waiters).await;
        assert_eq!(*order.lock().unwrap(), ["map news", "demanded early", "demanded late"]);
    }

    /// A demand still goes before map news that has not waited so long.
    #[tokio::test(flavor = "current_thread")]
    async fn map_news_just_short_of_the_bound_still_gives_way() {
        let (clock, time) = Clock::manual();
        let turns = Turns::new(1, clock);
        let held = turns.try_take().expect("one turn");
        let order = Order::default();
        let waiters = vec![
            wait_for_turn(&turns, &order, "map news", flag(false)).await,
            wait_for_turn(&turns, &order, "demanded", flag(true)).await,
        ];
        time.advance(LONGEST_WAIT - Duration::from_millis(1));
        release(held, waiters).await;
        assert_eq!(*order.lock().unwrap(), ["demanded", "map news"]);
    }

    /// A waiter cancelled while it waits is passed over, and no turn is
    /// lost or made: with two turns, two are free after all.
    #[tokio::test(flavor = "current_thread")]
    async fn a_cancelled_waiter_neither_loses_nor_makes_a_turn() {
        let turns = Turns::new(2, Clock::default());
        let (a, b) = (turns.try_take().unwrap(), turns.try_take().unwrap());
        let given_up = {
            let turns = turns.clone();
            tokio::spawn(async move { drop(turns.take(flag(true)).await) })
        };
        settle().await;
        given_up.abort();
        settle().await;
        drop(a);
        drop(b);
        let (c, d) = (turns.try_take(), turns.try_take());
        assert!(c.is_some() && d.is_some(), "both turns are free");
        assert!(turns.try_take().is_none(), "and there are only two");
    }
}
