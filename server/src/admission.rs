//! Refusing robots' calls while a queue stands, instead of letting it grow.
//!
//! When robots send more than the executive can answer, calls wait: for a
//! core, for their mission, for the disk. A burst that drains is harmless;
//! a queue that stands only makes every call late. The test is CoDel's
//! (Nichols and Jacobson, "Controlling Queue Delay", ACM Queue 10(5), 2012),
//! applied to calls instead of packets: a queue stands when no call has
//! been answered within the *target* for a whole *interval*, while some
//! were in flight. Periodic stalls (a CPU quota's throttled part of each
//! period) never look like one, because the calls made between them go
//! through within the target. As CoDel remembers its drop rate, the test
//! remembers overload: the first queue must stand five intervals, so that
//! one slow fsync at ordinary rates refuses nothing, but within fifty
//! intervals of a refusal one interval is enough.
//!
//! Each of the robots' frequent calls (map updates, heartbeats, bids) has
//! its own test: most heartbeats only say where a robot is and never wait
//! for the disk, so they would hide a queue of map updates behind them.
//! While a queue stands, calls of its kind are refused as they arrive with
//! RESOURCE_EXHAUSTED, before their request is decoded, so that the CPU
//! and the disk go to the calls admitted, and with a retry hint of ten
//! intervals, long enough for a robot sending at 1–2 Hz to hold a call or
//! two of that kind (the project's clients and `fleet-sim load` honour it).
//! It is deemed gone at the first call answered within the target, or as
//! soon as none of its kind is in flight.
//!
//! A call is timed from when it reaches this layer, so these tests miss the
//! queue that forms before: when the process has too little CPU, calls wait
//! in the sockets and in the runtime's queue of tasks, and at twice the
//! saturation point some calls of each kind were answered in time within
//! every interval while most waited 60–80 ms. A probe that wakes on a timer
//! and then queues behind the tasks waiting for a worker measures that
//! queue ([`RuntimeLag`]): while it has come back later than the target for
//! a whole interval, every robot call is refused, whatever its kind.
//! Nothing refused was applied, so nothing acknowledged is lost. The
//! mission queue limit ([`crate::ExecutiveSettings::max_queued_per_mission`])
//! still bounds one busy mission among idle ones, which these process-wide
//! tests do not see.
//!
//! It is off unless asked for (`--shed-target-ms`). Robots that send at
//! their own rates gain from it under a CPU limit, where at twice the
//! saturation point it halved the map updates' p99 (and brought it to about
//! 100 ms with a 10 ms target and a 50 ms interval, 64–88 ms with a 25 ms
//! interval, which refused about one call in a thousand at the real rates);
//! but callers that send
//! again as soon as they are answered (a fleet manager relaying as fast as
//! it can, the capacity phase of `fleet-sim load`) hold a queue standing
//! by design, and there it cost a tenth to a third of the updates answered
//! (docs/benchmarks.md).

use std::pin::Pin;
use std::sync::{Arc, Mutex};
use std::task::{Context, Poll};
use std::time::Duration;

use tokio::time::Instant;

use crate::clock::Clock;
use crate::metrics::Metrics;

/// The calls tested and refused: the robots' frequent ones.
const ROBOT_CALLS: [&str; 3] =
    ["/exploration.v1.Fleet/UpdateMap", "/exploration.v1.Fleet/Heartbeat", "/exploration.v1.Fleet/SubmitBids"];

/// When a queue stands (see the module).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct QueueDelay {
    /// A call answered within this shows there is no standing queue.
    pub target: Duration,
    /// How long no call may be answered within the target before calls
    /// are refused (five times as long for a first queue).
    pub interval: Duration,
}

/// One kind of call in flight, and since when a queue may have stood.
#[derive(Debug)]
pub struct StandingQueue {
    delay: QueueDelay,
    state: Mutex<QueueState>,
}

/// A first queue must stand this many intervals before calls are
/// refused: a stall of the disk or of the process at ordinary rates
/// (127 ms once in a minute at 1 000 robots' real rates) is not overload.
const FIRST_INTERVALS: u32 = 5;

/// For this many intervals after a refusal a queue that stands one
/// interval is refused again: overload that came back. (With ten, runs at
/// twice the saturation point refused 3–9 % of the map updates instead of
/// about a third, and kept most of their p99.)
const MEMORY_INTERVALS: u32 = 50;

/// A refused caller is asked to hold its calls of that kind this many
/// intervals (a second at the default interval). Robots send each kind at
/// 1–2 Hz, so a shorter hint would hold nothing back; and a refusal still
/// costs the executive about half of what an admitted call does (the
/// transport), so the excess must stop at its senders, not at the door:
/// refused but sent again on schedule, twice the saturation point leaves
/// no CPU for the calls admitted (docs/benchmarks.md).
const HOLD_INTERVALS: u32 = 10;

#[derive(Debug)]
struct QueueState {
    in_flight: usize,
    /// The last time there was surely no standing queue: nothing in
    /// flight, or a call answered within the target.
    calm_at: Instant,
    /// When a call was last refused.
    refused_at: Option<Instant>,
}

impl StandingQueue {
    /// No call in flight yet.
    pub fn new(delay: QueueDelay, now: Instant) -> Self {
        Self { delay, state: Mutex::new(QueueState { in_flight: 0, calm_at: now, refused_at: None }) }
    }

    /// How long a queue must stand before calls are refused: one interval
    /// soon after the last refusal, [`FIRST_INTERVALS`] otherwise.
    fn patience(&self, state: &QueueState, now: Instant) -> Duration {
        let memory = self.delay.interval.saturating_mul(MEMORY_INTERVALS);
        match state.refused_at {
            Some(at) if now.saturating_duration_since(at) <= memory => self.delay.interval,
            _ => self.delay.interval.saturating_mul(FIRST_INTERVALS),
        }
    }

    /// Whether a call arriving `now` is admitted; if so, it is in flight
    /// until [`Self::answered`].
    pub fn admit(&self, now: Instant) -> bool {
        let mut state = self.state.lock().unwrap_or_else(|e| e.into_inner());
        if state.in_flight == 0 {
            state.calm_at = now;
        } else if now.saturating_duration_since(state.calm_at) >= self.patience(&state, now) {
            state.refused_at = Some(now);
            return false;
        }
        state.in_flight += 1;
        true
    }

    /// An admitted call was answered `now`, having arrived at `arrived`.
    pub fn answered(&self, arrived: Instant, now: Instant) {
        let mut state = self.state.lock().unwrap_or_else(|e| e.into_inner());
        state.in_flight = state.in_flight.saturating_sub(1);
        if state.in_flight == 0 || now.saturating_duration_since(arrived) < self.delay.target {
            state.calm_at = state.calm_at.max(now);
        }
    }
}

/// How often the runtime's timer is set: short against the target, cheap
/// (two hundred wake-ups a second).
const LAG_PROBE: Duration = Duration::from_millis(5);

/// Lateness a timer has on a runtime that keeps up: tokio rounds a sleep up
/// to its next millisecond tick. A smaller target would call every wake-up
/// late.
const LAG_RESOLUTION: Duration = Duration::from_millis(2);

/// The shortest time without a wake-up in time that counts: a few timers'
/// worth, since between two wake-ups none can come. A shorter interval
/// would refuse between any two.
const LAG_PATIENCE: Duration = Duration::from_millis(20);

/// The queue no call's own time shows: calls that wait for a worker of the
/// runtime before they reach this layer (in the sockets, in the runtime's
/// queue of tasks), which is where they wait when the process has too
/// little CPU for what it is sent. A probe set for [`LAG_PROBE`] that then
/// goes to the back of its worker's queue ([`BackOfTheQueue`]) comes back
/// late by about as long, so the same test applies to its lateness: a
/// queue stands when no probe has come back within the target for an
/// interval. While it stands every robot call is refused, of whatever kind.
/// (A timer's wake-up alone jumps the queue: at twice the saturation point
/// the map updates' p99 was 1.8 times what it is with the probe queueing.)
#[derive(Debug)]
pub struct RuntimeLag {
    delay: QueueDelay,
    /// The last wake-up within the target.
    calm_at: Mutex<Instant>,
}

impl RuntimeLag {
    /// Calm as of `now`.
    pub fn new(delay: QueueDelay, now: Instant) -> Self {
        Self { delay, calm_at: Mutex::new(now) }
    }

    /// The probe came back `late` after its timer's time (woken, then
    /// queued behind the waiting tasks), at `now`.
    pub fn woke(&self, late: Duration, now: Instant) {
        if late < self.delay.target.max(LAG_RESOLUTION) {
            let mut calm_at = self.calm_at.lock().unwrap_or_else(|e| e.into_inner());
            *calm_at = (*calm_at).max(now);
        }
    }

    /// Whether a call arriving `now` is admitted: refused once no wake-up
    /// has come in time for an interval. The queues' first patience of
    /// five intervals is not needed here, since the disk's stalls do not
    /// hold the runtime, and with it the test never fired at twice the
    /// saturation point: some wake-up came in time within every half
    /// second (docs/benchmarks.md).
    pub fn admit(&self, now: Instant) -> bool {
        let calm_at = *self.calm_at.lock().unwrap_or_else(|e| e.into_inner());
        now.saturating_duration_since(calm_at) < self.delay.interval.max(LAG_PATIENCE)
    }

    /// Sets the timer again and again, each time queueing behind the tasks
    /// waiting once it has woken, on the runtime this is called on,
    /// for as long as `lag` is held elsewhere. This test runs on the
    /// runtime's time, not the executive's clock: lateness is real, and a
    /// clock a test moves by hand would look like a runtime that stopped.
    fn probe(lag: &Arc<Self>) -> tokio::task::JoinHandle<()> {
        let lag = Arc::downgrade(lag);
        tokio::spawn(async move {
            loop {
                let set = Instant::now();
                tokio::time::sleep(LAG_PROBE).await;
                BackOfTheQueue::default().await;
                let now = Instant::now();
                let late = now.saturating_duration_since(set).saturating_sub(LAG_PROBE);
                let Some(lag) = lag.upgrade() else { return };
                lag.woke(late, now);
            }
        })
    }
}

/// Goes once to the back of the worker's queue of tasks. Tokio runs a task
/// woken by a timer, by another task or by `yield_now` ahead of the tasks
/// already queued (its LIFO slot, or after the next poll of the drivers),
/// so a probe woken that way does not wait behind the queued calls; a task
/// that wakes itself while it is polled is queued behind them.
#[derive(Debug, Default)]
struct BackOfTheQueue {
    queued: bool,
}

impl Future for BackOfTheQueue {
    type Output = ();

    fn poll(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<()> {
        if self.queued {
            return Poll::Ready(());
        }
        self.queued = true;
        cx.waker().wake_by_ref();
        Poll::Pending
    }
}

/// Refuses robots' calls while a queue of their kind stands, or while the
/// runtime runs late (see the module); without a [`QueueDelay`] it admits
/// every call.
#[derive(Debug, Clone)]
pub struct AdmissionLayer {
    /// One per kind of call in [`ROBOT_CALLS`].
    queues: Vec<(&'static str, Arc<StandingQueue>)>,
    lag: Option<Arc<RuntimeLag>>,
    clock: Clock,
    metrics: Arc<Metrics>,
}

impl AdmissionLayer {
    /// The tests with `delay` on `clock`'s time, or none. With a delay it
    /// sets the runtime's timer, so it is made on the runtime that serves.
    pub fn new(delay: Option<QueueDelay>, clock: Clock, metrics: Arc<Metrics>) -> Self {
        let Some(delay) = delay else { return Self { queues: Vec::new(), lag: None, clock, metrics } };
        let queues = ROBOT_CALLS.map(|path| (path, Arc::new(StandingQueue::new(delay, clock.now())))).to_vec();
        let lag = Arc::new(RuntimeLag::new(delay, Instant::now()));
        RuntimeLag::probe(&lag);
        Self { queues, lag: Some(lag), clock, metrics }
    }
}

impl AdmissionLayer {
    /// RESOURCE_EXHAUSTED for a `method` call refused for `reason` (the
    /// metric's name), asking the caller to hold that kind of call for
    /// [`HOLD_INTERVALS`] of `delay`.
    fn refusal(
        &self,
        reason: &'static str,
        method: &str,
        why: String,
        delay: QueueDelay,
    ) -> http::Response<tonic::body::Body> {
        self.metrics.shed(reason);
        let hold = delay.interval.saturating_mul(HOLD_INTERVALS);
        let message = format!("{why}: {method} refused to shed load; hold calls of this kind for the hint ({hold:?})");
        crate::error::overloaded_for(message, hold).into_http()
    }
}

impl<S> tower::Layer<S> for AdmissionLayer {
    type Service = Admission<S>;

    fn layer(&self, inner: S) -> Self::Service {
        Admission { inner, layer: self.clone() }
    }
}

/// See [`AdmissionLayer`].
#[derive(Debug, Clone)]
pub struct Admission<S> {
    inner: S,
    layer: AdmissionLayer,
}

/// An admitted call in flight; answered when dropped, also when its
/// caller stops waiting (the call itself runs to its end regardless).
struct InFlight {
    queue: Arc<StandingQueue>,
    clock: Clock,
    arrived: Instant,
}

impl Drop for InFlight {
    fn drop(&mut self) {
        self.queue.answered(self.arrived, self.clock.now());
    }
}

type BoxFuture<T> = Pin<Box<dyn std::future::Future<Output = T> + Send>>;

impl<S, B> tower::Service<http::Request<B>> for Admission<S>
where
    S: tower::Service<http::Request<B>, Response = http::Response<tonic::body::Body>>,
    S::Future: Send + 'static,
    S::Error: Send + 'static,
{
    type Response = S::Response;
    type Error = S::Error;
    type Future = BoxFuture<Result<Self::Response, S::Error>>;

    fn poll_ready(&mut self, cx: &mut Context<'_>) -> Poll<Result<(), Self::Error>> {
        self.inner.poll_ready(cx)
    }

    fn call(&mut self, request: http::Request<B>) -> Self::Future {
        let path = request.uri().path();
        let Some(queue) = self.layer.queues.iter().find(|(p, _)| *p == path).map(|(_, q)| Arc::clone(q)) else {
            return Box::pin(self.inner.call(request));
        };
        let method = path.trim_start_matches('/');
        if let Some(lag) = self.layer.lag.as_ref().filter(|lag| !lag.admit(Instant::now())) {
            let why =
                format!("the executive's queue of tasks has stood longer than {:?} for a while", lag.delay.target);
            return Box::pin(std::future::ready(Ok(self.layer.refusal("runtime lag", method, why, lag.delay))));
        }
        let arrived = self.layer.clock.now();
        if !queue.admit(arrived) {
            let why =
                format!("{method} calls have been answered late for a while (none within {:?})", queue.delay.target);
            return Box::pin(std::future::ready(Ok(self.layer.refusal("standing queue", method, why, queue.delay))));
        }
        let in_flight = InFlight { queue, clock: self.layer.clock.clone(), arrived };
        let response = self.inner.call(request);
        Box::pin(async move {
            let response = response.await;
            drop(in_flight);
            response
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ms(n: u64) -> Duration {
        Duration::from_millis(n)
    }

    fn queue(start: Instant) -> StandingQueue {
        StandingQueue::new(QueueDelay { target: ms(20), interval: ms(100) }, start)
    }

    /// Calls arrive every ms from `from` to `to` and each is answered
    /// `wait` later; returns the times (ms) of the refused ones.
    fn steady(q: &StandingQueue, start: Instant, from: u64, to: u64, wait: u64) -> Vec<u64> {
        let mut admitted = std::collections::VecDeque::new();
        let mut refused = Vec::new();
        for t in from..to {
            let now = start + ms(t);
            while admitted.front().is_some_and(|&a| a + wait <= t) {
                let a = admitted.pop_front().unwrap();
                q.answered(start + ms(a), start + ms(a + wait));
            }
            if q.admit(now) {
                admitted.push_back(t);
            } else {
                refused.push(t);
            }
        }
        for a in admitted {
            q.answered(start + ms(a), start + ms(a + wait));
        }
        refused
    }

    #[test]
    fn calls_that_overlap_but_go_through_in_time_are_all_admitted() {
        let start = Instant::now();
        let q = queue(start);
        // Always about 15 in flight, each answered within the target.
        assert_eq!(steady(&q, start, 0, 2_000, 15), Vec::<u64>::new());
    }

    #[test]
    fn a_first_queue_is_refused_after_five_intervals_and_a_returning_one_after_one() {
        let start = Instant::now();
        let q = queue(start);
        // Every call waits 30 ms, over the target: calm at 0 (nothing in
        // flight), never since.
        let refused = steady(&q, start, 0, 700, 30);
        assert_eq!(refused.first(), Some(&500), "a first queue stands five intervals");
        // Refused calls are not in flight: the admitted ones drain, the
        // last at 529 ms, and with nothing in flight the next is admitted.
        assert!(refused.contains(&528));
        assert!(!refused.contains(&529), "nothing in flight ends the refusals");
        // The queue forms again at once: within the memory, one interval is
        // enough.
        let again = refused.iter().find(|&&t| t > 529).copied();
        assert_eq!(again, Some(629));
        // Over fifty intervals after the last refusal, five again.
        let later = 700 + 5_001;
        let refused = steady(&q, start, later, later + 700, 30);
        assert_eq!(refused.first(), Some(&(later + 500)));
    }

    #[test]
    fn one_call_on_time_ends_the_refusals() {
        let start = Instant::now();
        let q = queue(start);
        assert!(q.admit(start), "a call that will be stuck");
        assert!(q.admit(start + ms(495)));
        assert!(!q.admit(start + ms(500)), "one call in flight for five intervals, none on time");
        q.answered(start + ms(495), start + ms(505));
        assert!(q.admit(start + ms(506)), "one answered in 10 ms, though the first is still in flight");
    }

    #[test]
    fn stalls_shorter_than_five_intervals_refuse_nothing_at_first() {
        let start = Instant::now();
        let q = queue(start);
        // Calls every ms; at 1 s the process stalls for 400 ms: calls then
        // are answered when it ends.
        let mut in_flight = Vec::new();
        for t in 0..3_000u64 {
            let now = start + ms(t);
            let answer = if (1_000..1_400).contains(&t) { 1_401 } else { t + 2 };
            in_flight.retain(|&(a, at)| {
                let due = at <= t;
                if due {
                    q.answered(start + ms(a), start + ms(at));
                }
                !due
            });
            assert!(q.admit(now), "refused at {t} ms");
            in_flight.push((t, answer));
        }
    }

    #[test]
    fn a_cpu_quotas_throttled_periods_refuse_nothing() {
        // A quarter-core quota: the process runs 25 ms of every 100 and is
        // frozen for the rest. Calls arriving while it is frozen are
        // answered 1 ms after it runs again, the others within 1 ms.
        let start = Instant::now();
        let q = queue(start);
        let mut in_flight: Vec<(u64, u64)> = Vec::new();
        for t in (0..5_000u64).step_by(2) {
            in_flight.retain(|&(a, at)| {
                let due = at <= t;
                if due {
                    q.answered(start + ms(a), start + ms(at));
                }
                !due
            });
            let phase = t % 100;
            let answer = if phase < 25 { t + 1 } else { t + 101 - phase };
            assert!(q.admit(start + ms(t)), "refused at {t} ms");
            in_flight.push((t, answer));
        }
    }

    fn lag(start: Instant) -> RuntimeLag {
        RuntimeLag::new(QueueDelay { target: ms(20), interval: ms(100) }, start)
    }

    /// The timer wakes `late(t)` after its time, set every 5 ms from `from`
    /// to `to`; a call arrives every ms. Returns the times of the refused.
    fn timed(l: &RuntimeLag, start: Instant, from: u64, to: u64, late: impl Fn(u64) -> u64) -> Vec<u64> {
        let mut wake = from + 5 + late(from);
        let mut refused = Vec::new();
        for t in from..to {
            if t == wake {
                l.woke(ms(late(t)), start + ms(t));
                wake = t + 5 + late(t);
            }
            if !l.admit(start + ms(t)) {
                refused.push(t);
            }
        }
        refused
    }

    #[test]
    fn a_runtime_that_wakes_its_timer_in_time_refuses_nothing() {
        let start = Instant::now();
        assert!(timed(&lag(start), start, 0, 3_000, |_| 19).is_empty());
    }

    #[test]
    fn a_runtime_late_for_an_interval_refuses_every_call_until_its_timer_wakes_in_time() {
        let start = Instant::now();
        let l = lag(start);
        // In time for 300 ms, then 20 ms late (the target is not "in time").
        let refused = timed(&l, start, 0, 600, |t| if t < 300 { 2 } else { 20 });
        let last_in_time = 294; // wake-ups every 7 ms while in time: 7, 14, … 294
        assert_eq!(refused.first(), Some(&(last_in_time + 100)), "refused one interval after");
        assert_eq!(refused.len(), 600 - (last_in_time as usize + 100), "and every call after");
        l.woke(ms(1), start + ms(600));
        assert!(l.admit(start + ms(601)), "one wake-up in time ends it");
    }

    #[test]
    fn the_smallest_settings_do_not_call_a_runtime_that_keeps_up_late() {
        // --shed-target-ms 1 --shed-interval-ms 1: timers wake a tick late,
        // and an interval is shorter than the time between two of them.
        let start = Instant::now();
        let l = RuntimeLag::new(QueueDelay { target: ms(1), interval: ms(1) }, start);
        assert!(timed(&l, start, 0, 2_000, |_| 1).is_empty());
        // A runtime that does run late is still refused, 20 ms after the
        // last wake-up in time (every 6 ms: … 1 998).
        assert_eq!(timed(&l, start, 2_000, 2_100, |_| 30).first(), Some(&2_018));
    }

    #[test]
    fn a_cpu_quotas_throttled_periods_do_not_look_like_a_late_runtime() {
        // A quarter-core quota: a timer due while the process is frozen
        // wakes when it runs again, up to 75 ms late; one due while it runs
        // wakes in time.
        let start = Instant::now();
        let frozen = |t: u64| if t % 100 < 25 { 0 } else { 100 - t % 100 };
        assert!(timed(&lag(start), start, 0, 5_000, frozen).is_empty());
    }

    #[tokio::test]
    async fn the_probe_keeps_calls_admitted_on_a_runtime_that_keeps_up_and_ends_with_the_layer() {
        let now = Instant::now();
        let l = Arc::new(lag(now.checked_sub(ms(1_000)).unwrap_or(now)));
        assert!(now.checked_sub(ms(1_000)).is_none() || !l.admit(now), "nothing woke for a second");
        let probe = RuntimeLag::probe(&l);
        // Real time: the first wake-up within 20 ms of its time is enough,
        // however busy the machine running the tests is.
        let deadline = Instant::now() + Duration::from_secs(10);
        while !l.admit(Instant::now()) {
            assert!(Instant::now() < deadline, "the probe never woke in time");
            tokio::time::sleep(LAG_PROBE).await;
        }
        drop(l);
        let ended = tokio::time::timeout(Duration::from_secs(10), probe).await;
        assert!(matches!(ended, Ok(Ok(()))), "the probe ends once the layer is gone: {ended:?}");
    }

    /// The probe's wait ends only after every task queued before it on its
    /// worker has run: it measures the queue the calls wait in. (Awaiting
    /// `tokio::task::yield_now` instead, it resumed after 59 of the 200.)
    #[test]
    fn the_probe_waits_behind_every_task_already_queued() {
        let runtime = tokio::runtime::Builder::new_multi_thread().worker_threads(1).enable_all().build().unwrap();
        let ran_before = runtime.block_on(async {
            tokio::spawn(async {
                // Fewer than the worker's queue holds (256), so none go to
                // the runtime's shared queue.
                let ran = Arc::new(std::sync::atomic::AtomicUsize::new(0));
                for _ in 0..200 {
                    let ran = ran.clone();
                    tokio::spawn(async move {
                        ran.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                    });
                }
                BackOfTheQueue::default().await;
                ran.load(std::sync::atomic::Ordering::Relaxed)
            })
            .await
            .unwrap()
        });
        assert_eq!(ran_before, 200);
    }
}
