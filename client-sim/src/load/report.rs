//! What a load run measured, and the screen of text that shows it.

use std::collections::BTreeMap;
use std::sync::Mutex;
use std::time::{Duration, Instant};

use hdrhistogram::Histogram;
use serde::Serialize;
use tonic::Code;

use super::CellEncoding;

/// Latency figures of one kind of call, milliseconds.
#[derive(Debug, Clone, Default, Serialize)]
pub struct Latency {
    /// Calls measured.
    pub count: u64,
    /// Median.
    pub p50: f64,
    /// 99th percentile.
    pub p99: f64,
    /// 99.9th percentile.
    pub p999: f64,
    /// Slowest.
    pub max: f64,
}

impl Latency {
    pub(super) fn of(histogram: &Histogram<u64>) -> Self {
        let ms = |us: u64| us as f64 / 1000.0;
        Self {
            count: histogram.len(),
            p50: ms(histogram.value_at_quantile(0.5)),
            p99: ms(histogram.value_at_quantile(0.99)),
            p999: ms(histogram.value_at_quantile(0.999)),
            max: ms(histogram.max()),
        }
    }
}

/// One kind of call during the real-rate phase.
#[derive(Debug, Clone, Default, Serialize)]
pub struct CallReport {
    /// Answered per second.
    pub throughput_per_s: f64,
    /// From when each call was due to its answer (successful calls).
    pub latency_ms: Latency,
    /// Answers by status (`Ok` included).
    pub statuses: BTreeMap<String, u64>,
    /// Calls not sent when due because the executive had asked the robot to
    /// hold them (a retry hint on a refusal).
    pub held: u64,
}

/// The executive process's use of the machine.
#[derive(Debug, Clone, Default, Serialize)]
pub struct ProcessReport {
    /// Its pid.
    pub pid: u32,
    /// CPU time over the real-rate phase, seconds.
    pub cpu_s: f64,
    /// CPU time per second of the phase: 1.0 is one core busy.
    pub cores: f64,
    /// Resident memory at the end, MiB.
    pub rss_mib: f64,
    /// Peak resident memory, MiB.
    pub peak_rss_mib: f64,
    /// Whether the load generator ran in the same process.
    pub shared_with_load_generator: bool,
}

impl ProcessReport {
    /// Process `pid`'s use over the `elapsed` seconds since its CPU time
    /// was `cpu_before`.
    pub(super) fn since(pid: u32, cpu_before: f64, elapsed: f64) -> Self {
        let cpu = process_cpu(pid) - cpu_before;
        let (rss, peak) = process_memory(pid);
        Self {
            pid,
            cpu_s: cpu,
            cores: cpu / elapsed,
            rss_mib: rss,
            peak_rss_mib: peak,
            shared_with_load_generator: pid == std::process::id(),
        }
    }
}

/// The closed-loop phase: the most calls per second the executive answers.
#[derive(Debug, Clone, Default, Serialize)]
pub struct CapacityReport {
    /// Concurrent callers.
    pub callers: usize,
    /// Empty unary calls (the health check) per second, each caller going
    /// round its robots' own connections as the map updates do.
    pub empty_calls_per_s: f64,
    /// The same over one shared connection, where HTTP/2 writes many
    /// answers at once: the transport at its cheapest.
    pub empty_calls_one_connection_per_s: f64,
    /// Map updates (a sensor footprint each) per second.
    pub map_updates_per_s: f64,
    /// Map updates as a share of empty calls.
    pub share: f64,
    /// Latency of the map updates in this phase.
    pub map_update_latency_ms: Latency,
}

/// What a load run measured.
#[derive(Debug, Clone, Default, Serialize)]
pub struct LoadReport {
    /// Missions.
    pub missions: usize,
    /// Robots in all.
    pub robots: usize,
    /// Length of the real-rate phase, seconds.
    pub duration_s: f64,
    /// Calls due per second over all robots.
    pub offered_per_s: f64,
    /// Per call: throughput, latency, statuses.
    pub calls: BTreeMap<String, CallReport>,
    /// From a robot reporting an exploration target reached to its next
    /// task arriving on its stream, milliseconds. (The executive first ends
    /// the task, and the robot's assignment is empty until the plan that
    /// gives it the next one.)
    pub trigger_to_assignment_ms: Latency,
    /// Triggers whose mission completed before a next task came: nothing
    /// was left to give.
    pub triggers_ended_by_completion: u64,
    /// Triggers reported in the last [`TRIGGER_GRACE`] of the phase and not
    /// answered by its end: too late to tell.
    pub triggers_pending_at_end: u64,
    /// Triggers reported earlier and never answered: the executive missed
    /// them.
    pub triggers_unanswered: u64,
    /// The slowest answered triggers, slowest first: when each came tells a
    /// start-up burst from a stall later in the run.
    pub slowest_triggers: Vec<SlowTrigger>,
    /// Per mission that completed (its frontier explored) during the phase:
    /// when, seconds from the start. Once a mission completes its robots
    /// get no more exploration targets, so later figures measure a fleet
    /// that reports but does not replan.
    pub missions_completed_s: BTreeMap<u64, f64>,
    /// Map updates acknowledged to the robots.
    pub map_updates_acknowledged: u64,
    /// Whether every acknowledged update is in the store (each mission's
    /// count and each robot's highest sequence number, read back).
    pub acknowledged_in_store: bool,
    /// The executive's process.
    pub executive: Option<ProcessReport>,
    /// The closed-loop phase.
    pub capacity: Option<CapacityReport>,
    /// How the map patches carried their cells.
    pub cell_encoding: CellEncoding,
}

impl LoadReport {
    /// A screen of text.
    pub fn summary(&self) -> String {
        let mut out = format!(
            "{} missions × {} robots for {:.0} s, {:.0} calls/s offered, map patches as {}\n",
            self.missions,
            self.robots / self.missions.max(1),
            self.duration_s,
            self.offered_per_s,
            self.cell_encoding.name()
        );
        out += &format!(
            "{:<15} {:>9} {:>8} {:>8} {:>8} {:>8}  statuses\n",
            "call", "calls/s", "p50 ms", "p99 ms", "p99.9", "max ms"
        );
        for (name, call) in &self.calls {
            let l = &call.latency_ms;
            let mut statuses: Vec<String> = call.statuses.iter().map(|(k, v)| format!("{k} {v}")).collect();
            if call.held > 0 {
                statuses.push(format!("held {}", call.held));
            }
            out += &format!(
                "{name:<15} {:>9.1} {:>8.2} {:>8.2} {:>8.2} {:>8.2}  {}\n",
                call.throughput_per_s,
                l.p50,
                l.p99,
                l.p999,
                l.max,
                statuses.join(", ")
            );
        }
        let t = &self.trigger_to_assignment_ms;
        out += &format!(
            "trigger → next task: {} answered, p50 {:.1} ms, p99 {:.1} ms, max {:.1} ms; \
             {} ended by the mission's completion, {} unanswered, {} pending at the end\n",
            t.count,
            t.p50,
            t.p99,
            t.max,
            self.triggers_ended_by_completion,
            self.triggers_unanswered,
            self.triggers_pending_at_end
        );
        if !self.slowest_triggers.is_empty() {
            let slowest: Vec<String> = self
                .slowest_triggers
                .iter()
                .map(|t| format!("{:.0} ms at {:.1} s (mission {})", t.delay_ms, t.reported_s, t.mission))
                .collect();
            out += &format!("slowest triggers: {}\n", slowest.join(", "));
        }
        if !self.missions_completed_s.is_empty() {
            let mut at: Vec<f64> = self.missions_completed_s.values().copied().collect();
            at.sort_by(f64::total_cmp);
            out += &format!(
                "missions explored completely: {} of {}, from {:.0} s to {:.0} s\n",
                at.len(),
                self.missions,
                at[0],
                at[at.len() - 1]
            );
        }
        out += &format!(
            "map updates acknowledged: {}; all in the store: {}\n",
            self.map_updates_acknowledged, self.acknowledged_in_store
        );
        if let Some(p) = &self.executive {
            out += &format!(
                "executive (pid {}{}): {:.2} cores, RSS {:.0} MiB (peak {:.0})\n",
                p.pid,
                if p.shared_with_load_generator { ", with the load generator" } else { "" },
                p.cores,
                p.rss_mib,
                p.peak_rss_mib
            );
        }
        if let Some(c) = &self.capacity {
            out += &format!(
                "capacity ({} callers): empty call {:.0}/s, map update {:.0}/s = {:.0} % of it (p99 {:.1} ms); \
                 empty call over one shared connection {:.0}/s ({:.0} %)\n",
                c.callers,
                c.empty_calls_per_s,
                c.map_updates_per_s,
                100.0 * c.share,
                c.map_update_latency_ms.p99,
                c.empty_calls_one_connection_per_s,
                100.0 * c.map_updates_per_s / c.empty_calls_one_connection_per_s.max(1e-9)
            );
        }
        out
    }
}

/// One answered trigger, for the list of the slowest.
#[derive(Debug, Clone, Serialize)]
pub struct SlowTrigger {
    /// When the robot reported its arrival, seconds from the start.
    pub reported_s: f64,
    /// Its mission.
    pub mission: u64,
    /// The robot.
    pub robot: u64,
    /// From the report to the next task, milliseconds.
    pub delay_ms: f64,
}

/// How many of the slowest triggers the report lists.
const SLOWEST_TRIGGERS: usize = 5;

/// How long before the end of the phase an unanswered trigger counts as
/// pending rather than missed: a few replanning intervals.
pub const TRIGGER_GRACE: Duration = Duration::from_secs(5);

/// Arrivals at exploration targets and what the executive answered, shared
/// by the robots.
#[derive(Debug)]
pub(super) struct Triggers {
    pub(super) answered: Histogram<u64>,
    pub(super) ended_by_completion: u64,
    pub(super) pending: u64,
    pub(super) unanswered: u64,
    /// Mission → when it was first seen completed.
    pub(super) completed: BTreeMap<u64, Instant>,
    /// The slowest answered: delay, when reported, mission, robot.
    slowest: Vec<(Duration, Instant, u64, u64)>,
}

impl Triggers {
    pub(super) fn new() -> Self {
        Self {
            answered: new_histogram(),
            ended_by_completion: 0,
            pending: 0,
            unanswered: 0,
            completed: BTreeMap::new(),
            slowest: Vec::new(),
        }
    }

    pub(super) fn answer(&mut self, delay: Duration, reported: Instant, mission: u64, robot: u64) {
        self.answered.saturating_record(delay.as_micros() as u64);
        self.slowest.push((delay, reported, mission, robot));
        self.slowest.sort_by_key(|s| std::cmp::Reverse(s.0));
        self.slowest.truncate(SLOWEST_TRIGGERS);
    }

    /// The slowest answered, with times from `started`.
    pub(super) fn slowest_since(&self, started: Instant) -> Vec<SlowTrigger> {
        self.slowest
            .iter()
            .map(|&(delay, reported, mission, robot)| SlowTrigger {
                reported_s: reported.saturating_duration_since(started).as_secs_f64(),
                mission,
                robot,
                delay_ms: delay.as_secs_f64() * 1e3,
            })
            .collect()
    }

    /// Mission → when it completed, seconds from `started`.
    pub(super) fn completed_since(&self, started: Instant) -> BTreeMap<u64, f64> {
        self.completed
            .iter()
            .map(|(&mission, &at)| (mission, at.saturating_duration_since(started).as_secs_f64()))
            .collect()
    }
}

/// Latencies and statuses of every call, shared by the robots.
#[derive(Debug)]
pub(super) struct Recorder {
    latency: Mutex<BTreeMap<&'static str, Histogram<u64>>>,
    statuses: Mutex<BTreeMap<(&'static str, String), u64>>,
    held: Mutex<BTreeMap<&'static str, u64>>,
}

impl Recorder {
    pub(super) fn new() -> Self {
        Self {
            latency: Mutex::new(BTreeMap::new()),
            statuses: Mutex::new(BTreeMap::new()),
            held: Mutex::new(BTreeMap::new()),
        }
    }

    /// A `call` due was held back at the executive's request.
    pub(super) fn held(&self, call: &'static str) {
        *self.held.lock().unwrap_or_else(|e| e.into_inner()).entry(call).or_default() += 1;
    }

    pub(super) fn record(&self, call: &'static str, due: Instant, code: Code) {
        if code == Code::Ok {
            let micros = due.elapsed().as_micros().min(u128::from(u64::MAX)) as u64;
            let mut latency = self.latency.lock().unwrap_or_else(|e| e.into_inner());
            let histogram = latency.entry(call).or_insert_with(new_histogram);
            histogram.saturating_record(micros.max(1));
        }
        let mut statuses = self.statuses.lock().unwrap_or_else(|e| e.into_inner());
        *statuses.entry((call, format!("{code:?}"))).or_default() += 1;
    }

    /// Per call: answered per second over `elapsed` seconds, latency, statuses.
    pub(super) fn calls(&self, elapsed: f64) -> BTreeMap<String, CallReport> {
        let mut calls: BTreeMap<String, CallReport> = BTreeMap::new();
        let latency = self.latency.lock().unwrap_or_else(|e| e.into_inner());
        for ((call, code), count) in self.statuses.lock().unwrap_or_else(|e| e.into_inner()).iter() {
            let report = calls.entry((*call).to_owned()).or_default();
            report.statuses.insert(code.clone(), *count);
            report.throughput_per_s += *count as f64 / elapsed;
            if let Some(histogram) = latency.get(call) {
                report.latency_ms = Latency::of(histogram);
            }
        }
        for (call, held) in self.held.lock().unwrap_or_else(|e| e.into_inner()).iter() {
            calls.entry((*call).to_owned()).or_default().held = *held;
        }
        calls
    }
}

pub(super) fn new_histogram() -> Histogram<u64> {
    // 1 µs to 1 h, three significant digits.
    Histogram::new_with_bounds(1, 3_600_000_000, 3).unwrap_or_else(|_| Histogram::new(3).expect("3 digits"))
}

/// CPU time of a process so far, seconds (Linux `/proc`; 0 elsewhere).
pub(super) fn process_cpu(pid: u32) -> f64 {
    let Ok(stat) = std::fs::read_to_string(format!("/proc/{pid}/stat")) else { return 0.0 };
    // Fields after the command name (which may hold spaces) start at ')'.
    let Some(rest) = stat.rsplit_once(')').map(|(_, r)| r) else { return 0.0 };
    let fields: Vec<&str> = rest.split_whitespace().collect();
    // utime and stime are fields 14 and 15 of the whole line: 11 and 12 here.
    let ticks: f64 = fields.get(11..13).map_or(0.0, |f| f.iter().filter_map(|v| v.parse::<f64>().ok()).sum());
    ticks / 100.0
}

/// Resident memory now and at its peak, MiB (Linux `/proc`; 0 elsewhere).
fn process_memory(pid: u32) -> (f64, f64) {
    let Ok(status) = std::fs::read_to_string(format!("/proc/{pid}/status")) else { return (0.0, 0.0) };
    let field = |name: &str| {
        status
            .lines()
            .find(|l| l.starts_with(name))
            .and_then(|l| l.split_whitespace().nth(1))
            .and_then(|v| v.parse::<f64>().ok())
            .map_or(0.0, |kib| kib / 1024.0)
    };
    (field("VmRSS:"), field("VmHWM:"))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn own_process_statistics_are_read() {
        let (rss, peak) = process_memory(std::process::id());
        assert!(rss > 0.0 && peak >= rss);
        assert!(process_cpu(std::process::id()) >= 0.0);
    }
}
