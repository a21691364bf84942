//! `fleet-sim load`: many missions × many robots against one executive, in
//! wall-clock time at the rates real robots send, to measure the service
//! rather than exploration.
//!
//! Every robot is its own gRPC client with its own connection and its own
//! assignment stream. It sends heartbeats and map patches of its sensor
//! footprint on a fixed schedule, open-loop: a request is sent when it is
//! due whether or not the previous one was answered, and its latency counts
//! from when it was due, so a slow executive cannot hide its latency by
//! slowing the senders down. Robots drive at their speed, in a straight
//! line, towards the targets they are given; reaching one is a trigger whose
//! delay until the next assignment arrives on the stream is measured too.
//!
//! A second phase measures capacity, closed-loop: map updates and, in the
//! same run, an empty unary call (the health check), the transport's limit.

use std::collections::BTreeMap;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use hdrhistogram::Histogram;
use serde::Serialize;
use tokio::sync::watch;
use tokio::task::JoinSet;
use tokio_util::sync::CancellationToken;
use tonic::Code;
use tonic::service::interceptor::InterceptedService;
use tonic::transport::Channel;

use exploration::fusion::UNKNOWN_PERCENT;
use exploration::grid::Cell;
use exploration::math::Point2;
use exploration_proto::Bearer;
use exploration_proto::client::ClientTls;
use exploration_proto::v1 as pb;
use exploration_proto::v1::fleet_client::FleetClient;
use exploration_proto::v1::missions_client::MissionsClient;

use crate::fleet::{SimError, WorldSpec};
use crate::world::{StartChoice, World};

type Fleet = FleetClient<InterceptedService<Channel, Bearer>>;
type Missions = MissionsClient<InterceptedService<Channel, Bearer>>;

/// What a load run does.
#[derive(Debug, Clone)]
pub struct LoadConfig {
    /// Missions at once.
    pub missions: usize,
    /// Robots per mission.
    pub robots: usize,
    /// How long the robots run at their rates.
    pub duration: Duration,
    /// Heartbeats per robot per second.
    pub heartbeat_hz: f64,
    /// Map updates per robot per second.
    pub map_hz: f64,
    /// Robots' speed, metres per second.
    pub speed_mps: f64,
    /// Sensor range: the patches are the sensor's footprint, metres.
    pub sensor_range_m: f64,
    /// The world every mission explores.
    pub world: WorldSpec,
    /// Cell size, metres.
    pub cell_size: f64,
    /// Coordination policy.
    pub policy: String,
    /// Seed of every random choice.
    pub seed: u64,
    /// An executive to load; `None` starts one in this process.
    pub server: Option<String>,
    /// Operator token of `server`.
    pub token: Option<String>,
    /// TLS towards `server`.
    pub tls: Option<ClientTls>,
    /// The executive's process, for its CPU and memory (the embedded one
    /// shares this process with the load generator).
    pub executive_pid: Option<u32>,
    /// How long the closed-loop capacity phase runs; none when zero.
    pub capacity: Duration,
    /// Concurrent callers in the capacity phase; one per robot when `None`.
    /// A durable map update waits for its group's commit, so a few callers
    /// measure that wait rather than how many updates the executive can
    /// take (64 callers got 56-64 % of what 1 000 got through).
    pub capacity_callers: Option<usize>,
    /// How the map patches carry their cells.
    pub cell_encoding: CellEncoding,
}

/// How a load's map patches carry their cells.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum CellEncoding {
    /// One byte per cell, as ROS's `nav_msgs/OccupancyGrid` holds it
    /// (`OCCUPANCY_PERCENT`): what a ROS robot has at hand.
    #[default]
    OccupancyPercent,
    /// A float per cell and a byte of the unknown mask (`PROBABILITY`).
    Probability,
}

impl CellEncoding {
    /// The name `--cell-encoding` takes.
    pub fn name(self) -> &'static str {
        match self {
            Self::OccupancyPercent => "occupancy-percent",
            Self::Probability => "probability",
        }
    }
}

impl std::str::FromStr for CellEncoding {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            _ if s == Self::OccupancyPercent.name() => Ok(Self::OccupancyPercent),
            _ if s == Self::Probability.name() => Ok(Self::Probability),
            _ => Err(format!("{s:?}: expected occupancy-percent or probability")),
        }
    }
}

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
    fn of(histogram: &Histogram<u64>) -> Self {
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
            let statuses: Vec<String> = call.statuses.iter().map(|(k, v)| format!("{k} {v}")).collect();
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
struct Triggers {
    answered: Histogram<u64>,
    ended_by_completion: u64,
    pending: u64,
    unanswered: u64,
    /// Mission → when it was first seen completed.
    completed: BTreeMap<u64, Instant>,
    /// The slowest answered: delay, when reported, mission, robot.
    slowest: Vec<(Duration, Instant, u64, u64)>,
}

impl Triggers {
    fn new() -> Self {
        Self {
            answered: new_histogram(),
            ended_by_completion: 0,
            pending: 0,
            unanswered: 0,
            completed: BTreeMap::new(),
            slowest: Vec::new(),
        }
    }

    fn answer(&mut self, delay: Duration, reported: Instant, mission: u64, robot: u64) {
        self.answered.saturating_record(delay.as_micros() as u64);
        self.slowest.push((delay, reported, mission, robot));
        self.slowest.sort_by_key(|s| std::cmp::Reverse(s.0));
        self.slowest.truncate(SLOWEST_TRIGGERS);
    }
}

/// Latencies and statuses of every call, shared by the robots.
#[derive(Debug)]
struct Recorder {
    latency: Mutex<BTreeMap<&'static str, Histogram<u64>>>,
    statuses: Mutex<BTreeMap<(&'static str, String), u64>>,
}

impl Recorder {
    fn new() -> Self {
        Self { latency: Mutex::new(BTreeMap::new()), statuses: Mutex::new(BTreeMap::new()) }
    }

    fn record(&self, call: &'static str, due: Instant, code: Code) {
        if code == Code::Ok {
            let micros = due.elapsed().as_micros().min(u128::from(u64::MAX)) as u64;
            let mut latency = self.latency.lock().unwrap_or_else(|e| e.into_inner());
            let histogram = latency.entry(call).or_insert_with(new_histogram);
            histogram.saturating_record(micros.max(1));
        }
        let mut statuses = self.statuses.lock().unwrap_or_else(|e| e.into_inner());
        *statuses.entry((call, format!("{code:?}"))).or_default() += 1;
    }
}

fn new_histogram() -> Histogram<u64> {
    // 1 µs to 1 h, three significant digits.
    Histogram::new_with_bounds(1, 3_600_000_000, 3).unwrap_or_else(|_| Histogram::new(3).expect("3 digits"))
}

/// One simulated robot's shared state.
#[derive(Debug)]
struct Robot {
    id: u64,
    mission: u64,
    client: Fleet,
    /// Its own connection, which `client` uses.
    connection: Channel,
    /// Its newest assignment, from its stream, and when it arrived.
    assignment: watch::Receiver<Option<(pb::Assignment, Instant)>>,
    /// Highest map sequence number acknowledged, and how many were.
    acked_seq: AtomicU64,
    acked: AtomicU64,
    next_seq: AtomicU64,
}

/// A world point on the map, as a robot reports it.
fn pose_at(point: Point2, heading: f64) -> pb::Pose {
    pb::Pose { x: point.x, y: point.y, theta: heading }
}

/// The footprint of the sensor at `at`: the truth within range, the rest
/// of the square unknown, in `encoding`.
fn footprint(world: &World, at: Point2, range_m: f64, encoding: CellEncoding) -> pb::MapPatch {
    let frame = world.frame;
    let r = (range_m / frame.resolution).ceil() as i32;
    let centre = frame.cell_from_world_unchecked(&at);
    let x0 = (centre.x - r).clamp(0, frame.width as i32 - 1);
    let y0 = (centre.y - r).clamp(0, frame.height as i32 - 1);
    let x1 = (centre.x + r).clamp(0, frame.width as i32 - 1);
    let y1 = (centre.y + r).clamp(0, frame.height as i32 - 1);
    let (width, height) = ((x1 - x0 + 1) as u32, (y1 - y0 + 1) as u32);
    // Per cell: None where the sensor does not reach, else whether it is blocked.
    let cells = (y0..=y1).flat_map(|y| (x0..=x1).map(move |x| Cell::new(x, y))).map(|cell| {
        // Squared, in integers: the generator shares the machine with the
        // executive, and a square root per cell was a tenth of its CPU.
        let inside = cell.distance_squared(centre) <= i64::from(r) * i64::from(r);
        inside.then(|| world.blocked[frame.index(cell)])
    });
    let mut patch = pb::MapPatch { x: x0 as u32, y: y0 as u32, width, height, ..Default::default() };
    match encoding {
        CellEncoding::OccupancyPercent => {
            patch.encoding = pb::CellEncoding::OccupancyPercent as i32;
            patch.occupancy =
                cells.map(|c| c.map_or(UNKNOWN_PERCENT, |blocked| if blocked { 95 } else { 5 })).collect();
        }
        CellEncoding::Probability => {
            patch.encoding = pb::CellEncoding::Probability as i32;
            (patch.values, patch.unknown) =
                cells.map(|c| (if c == Some(true) { 0.95 } else { 0.05 }, u8::from(c.is_none()))).unzip();
        }
    }
    patch
}

/// Robot `k`'s start: spread over the reachable cells, the same for a seed.
fn start_of(world: &World, rng: &mut exploration::rng::SplitMix64) -> Point2 {
    let reachable: Vec<usize> = (0..world.reachable.len()).filter(|&i| world.reachable[i]).collect();
    let i = reachable[rng.below(reachable.len() as u64) as usize];
    world.frame.world_from_cell(world.frame.cell(i))
}

/// Runs a load test (see the module).
pub async fn run(config: &LoadConfig) -> Result<LoadReport, SimError> {
    if config.missions == 0 || config.robots == 0 {
        return Err(SimError::Config("a load test needs at least one mission and one robot".into()));
    }
    let world = Arc::new(config.world.build(Some(config.cell_size), StartChoice::Auto, config.seed)?);
    let embedded = match &config.server {
        Some(_) => None,
        None => Some(crate::fleet::EmbeddedExecutive::start_durable(config.token.clone()).await?),
    };
    let url = embedded.as_ref().map_or_else(|| config.server.clone().unwrap_or_default(), |e| e.url.clone());
    let token = embedded.as_ref().map_or(config.token.clone(), |e| Some(e.token.clone()));
    let result = run_against(config, world, &url, token.as_deref()).await;
    if let Some(executive) = embedded {
        executive.stop().await?;
    }
    result
}

fn rpc(what: &'static str) -> impl Fn(tonic::Status) -> SimError {
    move |status| SimError::Rpc { what, status }
}

async fn run_against(
    config: &LoadConfig,
    world: Arc<World>,
    url: &str,
    token: Option<&str>,
) -> Result<LoadReport, SimError> {
    let channel = |url: &str| {
        exploration_proto::client::endpoint(url, config.tls.as_ref())
            .map(|e| e.tcp_nodelay(true).timeout(Duration::from_secs(10)).connect_lazy())
            .map_err(|e| SimError::Executive(format!("bad executive URL or TLS settings for {url}: {e}")))
    };
    let bearer = |token: Option<&str>| {
        Bearer::new(token).map_err(|e| SimError::Executive(format!("the token is not valid metadata: {e}")))
    };
    let mut missions: Missions = MissionsClient::with_interceptor(channel(url)?, bearer(token)?);
    let frame = world.frame;
    let mut rng = exploration::rng::SplitMix64::new(config.seed);
    let stop = CancellationToken::new();
    let _stop_streams = stop.clone().drop_guard();
    let mut robots = Vec::new();
    let mut mission_ids = Vec::new();
    for m in 0..config.missions {
        let mission = missions
            .create_mission(pb::CreateMissionRequest {
                name: format!("load {m}"),
                frame: Some(pb::MapFrame {
                    resolution: frame.resolution,
                    origin: Some(pb::Point { x: frame.origin.x, y: frame.origin.y }),
                    width: frame.width,
                    height: frame.height,
                }),
                policy: Some(pb::PolicySpec { name: config.policy.clone(), params: Default::default() }),
                // Generous lease and stall times: the load must not depend on them.
                lifecycle: Some(pb::LifecycleSettings { lease_s: 600.0, stall_s: 600.0, rendezvous: None }),
                ..Default::default()
            })
            .await
            .map_err(rpc("CreateMission"))?
            .into_inner();
        mission_ids.push(mission.id);
        for k in 0..config.robots {
            let start = start_of(&world, &mut rng);
            let registration = pb::RegisterRobotRequest {
                mission_id: mission.id,
                name: format!("robot-{k}"),
                capabilities: Some(pb::RobotCapabilities {
                    sensor_range_m: config.sensor_range_m,
                    field_of_view_rad: std::f64::consts::TAU,
                    speed_mps: config.speed_mps,
                    footprint_radius_m: 0.0,
                }),
                pose: Some(pose_at(start, 0.0)),
            };
            let mut registrar = FleetClient::with_interceptor(channel(url)?, bearer(token)?);
            let answer = registrar.register_robot(registration).await.map_err(rpc("RegisterRobot"))?.into_inner();
            let id = answer.robot.map_or(0, |r| r.id);
            let connection = channel(url)?;
            let client = FleetClient::with_interceptor(connection.clone(), bearer(Some(&answer.token))?)
                .max_decoding_message_size(exploration_proto::MAX_MESSAGE_BYTES);
            let (tx, rx) = watch::channel(None);
            tokio::spawn(follow(client.clone(), id, tx, stop.clone()));
            robots.push((
                Arc::new(Robot {
                    id,
                    mission: mission.id,
                    client,
                    connection,
                    assignment: rx,
                    acked_seq: AtomicU64::new(0),
                    acked: AtomicU64::new(0),
                    next_seq: AtomicU64::new(1),
                }),
                start,
            ));
        }
    }
    let recorder = Arc::new(Recorder::new());
    let triggers = Arc::new(Mutex::new(Triggers::new()));
    let before = config.executive_pid.map(process_cpu);
    let started = Instant::now();
    let until = started + config.duration;
    let mut drivers = JoinSet::new();
    for (robot, start) in &robots {
        drivers.spawn(drive(
            Arc::clone(robot),
            *start,
            Arc::clone(&world),
            config.clone(),
            Arc::clone(&recorder),
            Arc::clone(&triggers),
            until,
        ));
    }
    // An empty call beside the robots, open-loop at 20 Hz: what the machine
    // and the transport alone add to every call's latency in this run.
    let probe = {
        let channel = channel(url)?;
        let recorder = Arc::clone(&recorder);
        tokio::spawn(async move {
            let mut health = tonic_health::pb::health_client::HealthClient::new(channel);
            let mut due = Instant::now();
            while due < until {
                tokio::time::sleep_until(due.into()).await;
                let request = tonic_health::pb::HealthCheckRequest { service: String::new() };
                let code = health.check(request).await.map_or_else(|s| s.code(), |_| Code::Ok);
                recorder.record("Health (empty)", due, code);
                due += Duration::from_millis(50);
            }
        })
    };
    while let Some(done) = drivers.join_next().await {
        done.map_err(|e| SimError::Executive(format!("a robot task failed: {e}")))?;
    }
    let _ = probe.await;
    let elapsed = started.elapsed().as_secs_f64();
    let executive = config.executive_pid.map(|pid| {
        let cpu = process_cpu(pid) - before.unwrap_or(0.0);
        let (rss, peak) = process_memory(pid);
        ProcessReport {
            pid,
            cpu_s: cpu,
            cores: cpu / elapsed,
            rss_mib: rss,
            peak_rss_mib: peak,
            shared_with_load_generator: pid == std::process::id(),
        }
    });
    // Every acknowledged update is in the store.
    let mut in_store = true;
    let mut acknowledged = 0;
    for &mission_id in &mission_ids {
        let stored =
            missions.get_mission(pb::GetMissionRequest { mission_id }).await.map_err(rpc("GetMission"))?.into_inner();
        let listed =
            missions.list_robots(pb::ListRobotsRequest { mission_id }).await.map_err(rpc("ListRobots"))?.into_inner();
        let mine: Vec<&Arc<Robot>> = robots.iter().map(|(r, _)| r).filter(|r| r.mission == mission_id).collect();
        let acked: u64 = mine.iter().map(|r| r.acked.load(Ordering::Acquire)).sum();
        acknowledged += acked;
        in_store &= stored.map_updates >= acked;
        for robot in mine {
            let seq = listed.robots.iter().find(|r| r.id == robot.id).map_or(0, |r| r.last_map_seq);
            in_store &= seq >= robot.acked_seq.load(Ordering::Acquire);
        }
    }
    let capacity = if config.capacity.is_zero() { None } else { Some(capacity(url, config, &robots, &world).await?) };
    stop.cancel();
    let per_robot = config.heartbeat_hz + config.map_hz;
    let total_robots = config.missions * config.robots;
    let mut calls: BTreeMap<String, CallReport> = BTreeMap::new();
    {
        let latency = recorder.latency.lock().unwrap_or_else(|e| e.into_inner());
        for ((call, code), count) in recorder.statuses.lock().unwrap_or_else(|e| e.into_inner()).iter() {
            let report = calls.entry((*call).to_owned()).or_default();
            report.statuses.insert(code.clone(), *count);
            report.throughput_per_s += *count as f64 / elapsed;
            if let Some(histogram) = latency.get(call) {
                report.latency_ms = Latency::of(histogram);
            }
        }
    }
    let triggers = &*triggers.lock().unwrap_or_else(|e| e.into_inner());
    Ok(LoadReport {
        cell_encoding: config.cell_encoding,
        missions: config.missions,
        robots: total_robots,
        duration_s: elapsed,
        offered_per_s: per_robot * total_robots as f64,
        calls,
        trigger_to_assignment_ms: Latency::of(&triggers.answered),
        triggers_ended_by_completion: triggers.ended_by_completion,
        triggers_pending_at_end: triggers.pending,
        triggers_unanswered: triggers.unanswered,
        slowest_triggers: triggers
            .slowest
            .iter()
            .map(|&(delay, reported, mission, robot)| SlowTrigger {
                reported_s: reported.saturating_duration_since(started).as_secs_f64(),
                mission,
                robot,
                delay_ms: delay.as_secs_f64() * 1e3,
            })
            .collect(),
        missions_completed_s: triggers
            .completed
            .iter()
            .map(|(&mission, &at)| (mission, at.saturating_duration_since(started).as_secs_f64()))
            .collect(),
        map_updates_acknowledged: acknowledged,
        acknowledged_in_store: in_store,
        executive,
        capacity,
    })
}

/// Keeps a robot's newest assignment from its stream, reconnecting.
async fn follow(
    mut client: Fleet,
    robot_id: u64,
    tx: watch::Sender<Option<(pb::Assignment, Instant)>>,
    stop: CancellationToken,
) {
    loop {
        let answer = tokio::select! {
            () = stop.cancelled() => return,
            answer = client.watch_assignment(pb::WatchAssignmentRequest { robot_id }) => answer,
        };
        if let Ok(answer) = answer {
            let mut stream = answer.into_inner();
            loop {
                let message = tokio::select! {
                    () = stop.cancelled() => return,
                    message = stream.message() => message,
                };
                let Ok(Some(assignment)) = message else { break };
                let arrived = Instant::now();
                tx.send_if_modified(|now| {
                    let newer = now.as_ref().is_none_or(|(a, _)| assignment.version > a.version);
                    if newer {
                        *now = Some((assignment, arrived));
                    }
                    newer
                });
            }
        }
        tokio::select! {
            () = stop.cancelled() => return,
            () = tokio::time::sleep(Duration::from_millis(200)) => {}
        }
    }
}

/// Drives one robot until `until`: moves it, and sends its heartbeats and
/// map updates when they are due, each on its own task (open-loop).
async fn drive(
    robot: Arc<Robot>,
    start: Point2,
    world: Arc<World>,
    config: LoadConfig,
    recorder: Arc<Recorder>,
    triggers: Arc<Mutex<Triggers>>,
    until: Instant,
) {
    let frame = world.frame;
    let heartbeat_every = Duration::from_secs_f64(1.0 / config.heartbeat_hz.max(1e-3));
    let map_every = Duration::from_secs_f64(1.0 / config.map_hz.max(1e-3));
    // Robots start out of phase, as real ones would.
    let offset = Duration::from_secs_f64((robot.id % 97) as f64 / 97.0 * heartbeat_every.as_secs_f64());
    let origin = Instant::now() + offset;
    let (mut next_heartbeat, mut next_map) = (origin, origin);
    let mut position = start;
    let mut heading = 0.0;
    let mut last_move = origin;
    // The task reached and when, until the next one arrives.
    let mut waiting: Option<(u64, Instant)> = None;
    let mut reported = None;
    let mut seen_completed = false;
    let mut requests = JoinSet::new();
    let mut assignment = robot.assignment.clone();
    loop {
        let due = next_heartbeat.min(next_map);
        if due >= until {
            break;
        }
        tokio::time::sleep_until(due.into()).await;
        let now = Instant::now();
        let current = assignment.borrow_and_update().clone();
        let target = current.as_ref().filter(|(a, _)| a.task_id != 0).and_then(|(a, _)| Some((a.task_id, a.target?)));
        let explores = current.as_ref().is_some_and(|(a, _)| {
            matches!(pb::TaskKind::try_from(a.kind), Ok(pb::TaskKind::Explore | pb::TaskKind::Pin | pb::TaskKind::Goto))
        });
        if let Some((a, arrived)) = &current {
            if !seen_completed && a.mission_state == pb::MissionState::Completed as i32 {
                seen_completed = true;
                let mut triggers = triggers.lock().unwrap_or_else(|e| e.into_inner());
                triggers.completed.entry(robot.mission).or_insert(*arrived);
            }
            // The answer to an arrival: the next task, or the mission's end.
            if let Some((task, reported)) = waiting {
                if explores && a.task_id != task {
                    let delay = arrived.saturating_duration_since(reported).max(Duration::from_micros(1));
                    let mut triggers = triggers.lock().unwrap_or_else(|e| e.into_inner());
                    triggers.answer(delay, reported, robot.mission, robot.id);
                    waiting = None;
                } else if a.mission_state == pb::MissionState::Completed as i32 {
                    triggers.lock().unwrap_or_else(|e| e.into_inner()).ended_by_completion += 1;
                    waiting = None;
                }
            }
        }
        // Move towards the target at the robot's speed.
        let dt = now.duration_since(last_move).as_secs_f64();
        last_move = now;
        let mut arrived = None;
        if let Some((task, goal)) = target {
            let goal = Point2::new(goal.x, goal.y);
            let to_goal = goal - position;
            let step = config.speed_mps * dt;
            if to_goal.norm() <= step.max(frame.resolution) {
                position = goal;
                if reported != Some(task) {
                    arrived = Some(task);
                }
            } else {
                heading = to_goal.y.atan2(to_goal.x);
                position += to_goal * (step / to_goal.norm());
            }
        }
        if due == next_heartbeat {
            next_heartbeat += heartbeat_every;
            let (state, task_id) = match (arrived, target) {
                (Some(task), _) => (pb::RobotState::Arrived, task),
                (None, Some((task, _))) => (pb::RobotState::Moving, task),
                (None, None) => (pb::RobotState::Idle, 0),
            };
            if let Some(task) = arrived {
                reported = Some(task);
                // Arriving home or at a hold ends nothing the executive must answer.
                if explores {
                    waiting = Some((task, due));
                }
            }
            let request = pb::HeartbeatRequest {
                robot_id: robot.id,
                pose: Some(pose_at(position, heading)),
                state: state as i32,
                task_id,
                ..Default::default()
            };
            let (mut client, recorder) = (robot.client.clone(), Arc::clone(&recorder));
            requests.spawn(async move {
                let code = client.heartbeat(request).await.map_or_else(|s| s.code(), |_| Code::Ok);
                recorder.record("Heartbeat", due, code);
            });
        } else {
            next_map += map_every;
            let seq = robot.next_seq.fetch_add(1, Ordering::AcqRel);
            let request = pb::UpdateMapRequest {
                robot_id: robot.id,
                seq,
                pose: Some(pose_at(position, heading)),
                patches: vec![footprint(&world, position, config.sensor_range_m, config.cell_encoding)],
                ..Default::default()
            };
            let (robot, recorder) = (Arc::clone(&robot), Arc::clone(&recorder));
            requests.spawn(async move {
                let code = match robot.client.clone().update_map(request).await {
                    Ok(_) => {
                        robot.acked.fetch_add(1, Ordering::AcqRel);
                        robot.acked_seq.fetch_max(seq, Ordering::AcqRel);
                        Code::Ok
                    }
                    Err(status) => status.code(),
                };
                recorder.record("UpdateMap", due, code);
            });
        }
        // Answered requests are collected as they come.
        while requests.try_join_next().is_some() {}
    }
    while requests.join_next().await.is_some() {}
    if let Some((_, reported)) = waiting {
        let mut triggers = triggers.lock().unwrap_or_else(|e| e.into_inner());
        if reported + TRIGGER_GRACE >= until {
            triggers.pending += 1;
        } else {
            triggers.unanswered += 1;
        }
    }
}

/// A robot and where it stands.
type Placed = (Arc<Robot>, Point2);

/// The closed-loop phase: as many empty calls, then as many map updates, as
/// `callers` concurrent callers get answered. Each caller goes round its
/// share of the robots, on each robot's own connection, for both kinds of
/// call; the empty call is also timed over one shared connection.
async fn capacity(
    url: &str,
    config: &LoadConfig,
    robots: &[(Arc<Robot>, Point2)],
    world: &Arc<World>,
) -> Result<CapacityReport, SimError> {
    let callers = config.capacity_callers.unwrap_or(robots.len()).max(1);
    let shares: Arc<Vec<Vec<Placed>>> = Arc::new(
        (0..callers)
            .map(|c| robots.iter().skip(c).step_by(callers).cloned().collect::<Vec<_>>())
            .filter(|mine| !mine.is_empty())
            .collect(),
    );
    let shared = exploration_proto::client::endpoint(url, config.tls.as_ref())
        .map_err(|e| SimError::Executive(e.to_string()))?
        .connect_lazy();
    let empty_one_connection = closed_loop(config.capacity, callers, None, move |_| empty_call(shared.clone())).await.0;
    let mine = Arc::clone(&shares);
    let empty = closed_loop(config.capacity, shares.len(), None, move |c| {
        let (robot, _) = &mine[c.caller][c.round % mine[c.caller].len()];
        empty_call(robot.connection.clone())
    })
    .await
    .0;
    let (range, encoding, world, mine) =
        (config.sensor_range_m, config.cell_encoding, Arc::clone(world), Arc::clone(&shares));
    let (updates, latency) = closed_loop(config.capacity, shares.len(), Some(new_histogram()), move |c| {
        let (robot, at) = &mine[c.caller][c.round % mine[c.caller].len()];
        let request = pb::UpdateMapRequest {
            robot_id: robot.id,
            seq: robot.next_seq.fetch_add(1, Ordering::AcqRel),
            pose: Some(pose_at(*at, 0.0)),
            patches: vec![footprint(&world, *at, range, encoding)],
            ..Default::default()
        };
        let mut client = robot.client.clone();
        async move { client.update_map(request).await.is_ok() }
    })
    .await;
    let latency = Latency::of(&latency.unwrap_or_else(new_histogram));
    Ok(CapacityReport {
        callers,
        empty_calls_per_s: empty,
        empty_calls_one_connection_per_s: empty_one_connection,
        map_updates_per_s: updates,
        share: if empty > 0.0 { updates / empty } else { 0.0 },
        map_update_latency_ms: latency,
    })
}

/// One empty unary call on `connection`; whether it was answered OK.
fn empty_call(connection: Channel) -> impl std::future::Future<Output = bool> + Send {
    let mut health = tonic_health::pb::health_client::HealthClient::new(connection);
    async move { health.check(tonic_health::pb::HealthCheckRequest { service: String::new() }).await.is_ok() }
}

/// Which call a closed-loop caller makes next.
#[derive(Debug, Clone, Copy)]
struct Turn {
    caller: usize,
    round: usize,
}

/// `callers` callers each making the call `call` returns, one after the
/// other, for `length`: calls answered OK per second, and their latency
/// when `latency` is given. The empty calls are not timed: a lock per call
/// around one histogram would slow the very reference they are.
async fn closed_loop<F, Fut>(
    length: Duration,
    callers: usize,
    latency: Option<hdrhistogram::Histogram<u64>>,
    call: F,
) -> (f64, Option<hdrhistogram::Histogram<u64>>)
where
    F: Fn(Turn) -> Fut + Send + Sync + 'static,
    Fut: std::future::Future<Output = bool> + Send + 'static,
{
    let go = Arc::new(AtomicBool::new(true));
    let count = Arc::new(AtomicU64::new(0));
    let timed = latency.is_some();
    let latency = Arc::new(Mutex::new(latency.unwrap_or_else(new_histogram)));
    let call = Arc::new(call);
    let mut workers = JoinSet::new();
    for caller in 0..callers {
        let (go, count, latency, call) = (Arc::clone(&go), Arc::clone(&count), Arc::clone(&latency), Arc::clone(&call));
        workers.spawn(async move {
            let mut round = 0;
            while go.load(Ordering::Acquire) {
                let sent = Instant::now();
                if call(Turn { caller, round }).await {
                    count.fetch_add(1, Ordering::AcqRel);
                    if timed {
                        let micros = sent.elapsed().as_micros().max(1) as u64;
                        latency.lock().unwrap_or_else(|e| e.into_inner()).saturating_record(micros);
                    }
                }
                round += 1;
            }
        });
    }
    let started = Instant::now();
    tokio::time::sleep(length).await;
    go.store(false, Ordering::Release);
    let rate = count.load(Ordering::Acquire) as f64 / started.elapsed().as_secs_f64();
    while workers.join_next().await.is_some() {}
    let histogram = timed.then(|| latency.lock().unwrap_or_else(|e| e.into_inner()).clone());
    (rate, histogram)
}

/// CPU time of a process so far, seconds (Linux `/proc`; 0 elsewhere).
fn process_cpu(pid: u32) -> f64 {
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
    fn a_footprint_holds_the_truth_within_range_and_nothing_beyond() {
        let world = crate::generate::generate(crate::generate::Generator::Empty, 10.0, 10.0, 0.5, 1, StartChoice::Auto)
            .unwrap();
        let at = world.frame.world_from_cell(Cell::new(10, 10));
        let patch = footprint(&world, at, 2.0, CellEncoding::Probability);
        assert_eq!((patch.width, patch.height), (9, 9), "4 cells either side");
        assert_eq!(patch.values.len(), 81);
        let known = patch.unknown.iter().filter(|&&u| u == 0).count();
        assert!(known > 40 && known < 81, "a disc inside its square: {known}");
        // The same cells as bytes: a percentage where known, 255 elsewhere.
        let bytes = footprint(&world, at, 2.0, CellEncoding::OccupancyPercent);
        assert_eq!((bytes.x, bytes.y, bytes.width, bytes.height), (patch.x, patch.y, 9, 9));
        assert!(bytes.values.is_empty() && bytes.unknown.is_empty());
        for ((&byte, &unknown), &value) in bytes.occupancy.iter().zip(&patch.unknown).zip(&patch.values) {
            let expected = if unknown == 1 { UNKNOWN_PERCENT } else { (value * 100.0).round() as u8 };
            assert_eq!(byte, expected);
        }
        // At a corner the square is clipped to the map.
        let corner =
            footprint(&world, world.frame.world_from_cell(Cell::new(0, 0)), 2.0, CellEncoding::OccupancyPercent);
        assert_eq!((corner.x, corner.y, corner.width, corner.height), (0, 0, 5, 5));
    }

    #[test]
    fn own_process_statistics_are_read() {
        let (rss, peak) = process_memory(std::process::id());
        assert!(rss > 0.0 && peak >= rss);
        assert!(process_cpu(std::process::id()) >= 0.0);
    }
}
