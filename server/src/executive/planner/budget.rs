//! A CPU budget for the planning threads, for an executive under a CPU
//! limit.
//!
//! Under a CFS quota (a container's `limits: cpu`), once the process has
//! spent a period's quota every thread of it waits for the next period,
//! 100 ms by default. A plan spends CPU in bursts, at full speed on its
//! threads; their low priority orders the threads inside the quota but
//! cannot give back quota already spent, so the requests behind a plan
//! waited for the next period (`docs/benchmarks.md`, "An executive under a
//! CPU limit"). With a budget, the planning threads spend at most `cores`
//! on average: each piece of a plan is charged, in the thread's own CPU
//! time, to a token bucket that refills at that rate, and a thread whose
//! charges run more than [`BURST`] ahead sleeps until they do not.

use std::cell::Cell;
use std::sync::Mutex;
use std::time::{Duration, Instant};

use exploration::workers::Pace;
use prometheus_client::metrics::counter::Counter;

/// CPU the planning threads may spend ahead of their rate before one of
/// them waits: small against a quota period, so that one plan cannot spend
/// a period's quota at once.
pub(crate) const BURST: Duration = Duration::from_millis(2);

/// The least budget kept, in cores: below it a plan of a second would wait
/// for hours.
pub(crate) const LEAST_CORES: f64 = 0.001;

/// Holds the planning threads to `cores` of CPU on average.
#[derive(Debug)]
pub(crate) struct PlannerBudget {
    cores: f64,
    bucket: Mutex<Bucket>,
    /// Seconds planning threads slept to keep to the budget.
    waited: Counter<f64, std::sync::atomic::AtomicU64>,
}

impl PlannerBudget {
    /// A budget of `cores` (finite, at least [`LEAST_CORES`]), counting the time threads
    /// wait for it in `waited`.
    pub(crate) fn new(cores: f64, waited: Counter<f64, std::sync::atomic::AtomicU64>) -> Self {
        Self { cores, bucket: Mutex::new(Bucket::default()), waited }
    }
}

impl Pace for PlannerBudget {
    fn piece_done(&self) {
        let used = cpu_since_last_charge();
        let wait = self.bucket.lock().unwrap_or_else(|e| e.into_inner()).charge(Instant::now(), used, self.cores);
        if !wait.is_zero() {
            self.waited.inc_by(wait.as_secs_f64());
            std::thread::sleep(wait);
        }
    }
}

/// CPU spent beyond the allowance so far.
#[derive(Debug, Default)]
struct Bucket {
    /// Seconds of CPU charged and not yet allowed for.
    debt: f64,
    /// When it was last charged.
    at: Option<Instant>,
}

impl Bucket {
    /// Charges `used` CPU at `now`, the allowance having grown by `cores`
    /// per second since the last charge; how long the charging thread must
    /// wait for the debt to fall back to [`BURST`].
    fn charge(&mut self, now: Instant, used: Duration, cores: f64) -> Duration {
        let elapsed = self.at.map_or(Duration::ZERO, |at| now.saturating_duration_since(at));
        self.at = Some(self.at.map_or(now, |at| at.max(now)));
        self.debt = (self.debt - elapsed.as_secs_f64() * cores).max(0.0) + used.as_secs_f64();
        let ahead = self.debt - BURST.as_secs_f64();
        if ahead > 0.0 { Duration::from_secs_f64(ahead / cores) } else { Duration::ZERO }
    }
}

thread_local! {
    /// The calling thread's CPU time when it was last charged.
    static CHARGED: Cell<Duration> = const { Cell::new(Duration::ZERO) };
}

/// CPU time the calling thread spent since it was last charged (since it
/// started, the first time).
fn cpu_since_last_charge() -> Duration {
    let now = thread_cpu_time();
    CHARGED.with(|charged| {
        let used = now.saturating_sub(charged.get());
        charged.set(now);
        used
    })
}

/// The calling thread's CPU time.
fn thread_cpu_time() -> Duration {
    let t = rustix::time::clock_gettime(rustix::time::ClockId::ThreadCPUTime);
    Duration::new(u64::try_from(t.tv_sec).unwrap_or(0), u32::try_from(t.tv_nsec).unwrap_or(0))
}

#[cfg(test)]
mod tests {
    use super::*;

    const MS: Duration = Duration::from_millis(1);

    #[test]
    fn within_the_rate_nothing_waits() {
        let mut bucket = Bucket::default();
        let start = Instant::now();
        // A quarter of a core: 1 ms of CPU every 4 ms of time.
        for k in 0..100 {
            assert_eq!(bucket.charge(start + 4 * k * MS, MS, 0.25), Duration::ZERO, "charge {k}");
        }
    }

    #[test]
    fn a_burst_waits_until_the_rate_allows_it() {
        let mut bucket = Bucket::default();
        let start = Instant::now();
        // 10 ms of CPU at once against half a core: 8 ms beyond the burst,
        // which half a core allows for in 16 ms.
        assert_eq!(bucket.charge(start, 10 * MS, 0.5), 16 * MS);
        // Having waited, nothing more is owed beyond the burst.
        assert_eq!(bucket.charge(start + 16 * MS, Duration::ZERO, 0.5), Duration::ZERO);
        // One more millisecond, at once: 1 ms beyond, 2 ms of waiting.
        assert_eq!(bucket.charge(start + 16 * MS, MS, 0.5), 2 * MS);
    }

    #[test]
    fn idle_time_is_not_saved_up_beyond_the_burst() {
        let mut bucket = Bucket::default();
        let start = Instant::now();
        assert_eq!(bucket.charge(start, Duration::ZERO, 0.5), Duration::ZERO);
        // A minute idle, then 10 ms at once: still 8 ms beyond the burst.
        assert_eq!(bucket.charge(start + Duration::from_secs(60), 10 * MS, 0.5), 16 * MS);
    }

    #[test]
    fn over_a_long_run_the_threads_get_the_rate() {
        // Two threads charging 3 ms pieces alternately, each waiting what it
        // is told: the CPU charged over the time taken is the rate.
        let mut bucket = Bucket::default();
        let start = Instant::now();
        let mut clocks = [start, start];
        let mut charged = Duration::ZERO;
        for k in 0..1000 {
            let t = &mut clocks[k % 2];
            *t += 3 * MS;
            charged += 3 * MS;
            *t += bucket.charge(*t, 3 * MS, 0.2);
        }
        let elapsed = clocks.iter().max().unwrap().duration_since(start);
        let rate = charged.as_secs_f64() / elapsed.as_secs_f64();
        assert!((rate - 0.2).abs() < 0.01, "rate {rate}");
    }

    #[test]
    fn a_thread_is_charged_its_own_cpu_time() {
        let _ = cpu_since_last_charge();
        let spin = Instant::now();
        while spin.elapsed() < 20 * MS {
            std::hint::black_box(spin.elapsed());
        }
        let used = cpu_since_last_charge();
        // The thread ran for 20 ms of wall time; on a busy machine it got
        // less of the CPU, never more.
        assert!(used <= spin.elapsed() + MS, "{used:?}");
        assert!(used > Duration::ZERO);
        let asleep = cpu_since_last_charge();
        std::thread::sleep(20 * MS);
        assert!(cpu_since_last_charge() < 5 * MS, "sleeping is not charged ({asleep:?} before)");
    }
}
