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
//! A refusal with a retry hint (`grpc-retry-pushback-ms`) is the one
//! answer a robot heeds: it holds its calls of that kind until the hint has
//! passed, as the project's clients do, and the calls so held are counted
//! beside the answered ones (`--ignore-pushback` sends every call when due).
//!
//! A second phase measures capacity, closed-loop: map updates and, in the
//! same run, an empty unary call (the health check), the transport's limit.
//!
//! The rooms: this module sets a run up and puts its report together;
//! `drive` is what each robot does during the real-rate phase, `capacity`
//! the closed-loop phase, and `report` what a run measured and how it is
//! shown.

mod capacity;
mod drive;
mod report;

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

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

use crate::fleet::{SimError, WorldSpec, bearer};
use crate::world::{StartChoice, World};

pub use report::{CallReport, CapacityReport, Latency, LoadReport, ProcessReport, SlowTrigger, TRIGGER_GRACE};
use report::{Recorder, Triggers, process_cpu};

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
    /// Whether a robot refused with a retry hint holds its calls of that
    /// kind until the hint has passed, as the project's clients do (its
    /// map patches then go with its next update). Without it every call is
    /// sent when due, refused or not.
    pub honour_pushback: bool,
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

/// A robot and where it starts.
type Placed = (Arc<Robot>, Point2);
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

/// Opens the run's connections to one executive.
struct Connector<'a> {
    url: &'a str,
    tls: Option<&'a ClientTls>,
}

impl Connector<'_> {
    /// A connection of its own, opened when first used.
    fn channel(&self) -> Result<Channel, SimError> {
        exploration_proto::client::endpoint(self.url, self.tls)
            .map(|e| e.tcp_nodelay(true).timeout(Duration::from_secs(10)).connect_lazy())
            .map_err(|e| SimError::Fleet(format!("bad executive URL or TLS settings: {e}")))
    }
}

async fn run_against(
    config: &LoadConfig,
    world: Arc<World>,
    url: &str,
    token: Option<&str>,
) -> Result<LoadReport, SimError> {
    let connect = Connector { url, tls: config.tls.as_ref() };
    let mut missions: Missions = MissionsClient::with_interceptor(connect.channel()?, bearer(token)?);
    let stop = CancellationToken::new();
    let _stop_streams = stop.clone().drop_guard();
    let (mission_ids, robots) = register_fleet(config, &world, &connect, &mut missions, token, &stop).await?;

    let recorder = Arc::new(Recorder::new());
    let triggers = Arc::new(Mutex::new(Triggers::new()));
    let cpu_before = config.executive_pid.map(process_cpu);
    let started = Instant::now();
    real_rate_phase(config, &world, &connect, &robots, &recorder, &triggers, started + config.duration).await?;
    let elapsed = started.elapsed().as_secs_f64();
    let executive = config.executive_pid.map(|pid| ProcessReport::since(pid, cpu_before.unwrap_or(0.0), elapsed));

    let (acknowledged, in_store) = acknowledged_in_store(&mut missions, &mission_ids, &robots).await?;
    let capacity =
        if config.capacity.is_zero() { None } else { Some(capacity::measure(url, config, &robots, &world).await?) };
    stop.cancel();
    let total_robots = config.missions * config.robots;
    let triggers = &*triggers.lock().unwrap_or_else(|e| e.into_inner());
    Ok(LoadReport {
        cell_encoding: config.cell_encoding,
        missions: config.missions,
        robots: total_robots,
        duration_s: elapsed,
        offered_per_s: (config.heartbeat_hz + config.map_hz) * total_robots as f64,
        calls: recorder.calls(elapsed),
        trigger_to_assignment_ms: Latency::of(&triggers.answered),
        triggers_ended_by_completion: triggers.ended_by_completion,
        triggers_pending_at_end: triggers.pending,
        triggers_unanswered: triggers.unanswered,
        slowest_triggers: triggers.slowest_since(started),
        missions_completed_s: triggers.completed_since(started),
        map_updates_acknowledged: acknowledged,
        acknowledged_in_store: in_store,
        executive,
        capacity,
    })
}

/// Creates the missions and registers their robots, each with its own
/// connection and its assignment stream followed until `stop`: the
/// missions' ids, and the robots with where they start.
async fn register_fleet(
    config: &LoadConfig,
    world: &World,
    connect: &Connector<'_>,
    missions: &mut Missions,
    token: Option<&str>,
    stop: &CancellationToken,
) -> Result<(Vec<u64>, Vec<Placed>), SimError> {
    let mut rng = exploration::rng::SplitMix64::new(config.seed);
    let mut robots = Vec::new();
    let mut mission_ids = Vec::new();
    for m in 0..config.missions {
        let mission_id = create_mission(config, world, missions, m).await?;
        mission_ids.push(mission_id);
        for k in 0..config.robots {
            let start = start_of(world, &mut rng);
            let robot = register_robot(config, connect, token, mission_id, k, start, stop).await?;
            robots.push((Arc::new(robot), start));
        }
    }
    Ok((mission_ids, robots))
}

async fn create_mission(
    config: &LoadConfig,
    world: &World,
    missions: &mut Missions,
    m: usize,
) -> Result<u64, SimError> {
    let frame = world.frame;
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
    Ok(mission.id)
}

async fn register_robot(
    config: &LoadConfig,
    connect: &Connector<'_>,
    token: Option<&str>,
    mission_id: u64,
    k: usize,
    start: Point2,
    stop: &CancellationToken,
) -> Result<Robot, SimError> {
    let registration = pb::RegisterRobotRequest {
        mission_id,
        name: format!("robot-{k}"),
        capabilities: Some(pb::RobotCapabilities {
            sensor_range_m: config.sensor_range_m,
            field_of_view_rad: std::f64::consts::TAU,
            speed_mps: config.speed_mps,
            footprint_radius_m: 0.0,
        }),
        pose: Some(pose_at(start, 0.0)),
    };
    let mut registrar = FleetClient::with_interceptor(connect.channel()?, bearer(token)?);
    let answer = registrar.register_robot(registration).await.map_err(rpc("RegisterRobot"))?.into_inner();
    let id = answer.robot.map_or(0, |r| r.id);
    let connection = connect.channel()?;
    let client = FleetClient::with_interceptor(connection.clone(), bearer(Some(&answer.token))?)
        .max_decoding_message_size(exploration_proto::MAX_MESSAGE_BYTES);
    let (tx, rx) = watch::channel(None);
    tokio::spawn(drive::follow(client.clone(), id, tx, stop.clone()));
    Ok(Robot {
        id,
        mission: mission_id,
        client,
        connection,
        assignment: rx,
        acked_seq: AtomicU64::new(0),
        acked: AtomicU64::new(0),
        next_seq: AtomicU64::new(1),
    })
}

/// Every robot at its rates until `until`, and beside them an empty call
/// open-loop at 20 Hz: what the machine and the transport alone add to
/// every call's latency in this run.
async fn real_rate_phase(
    config: &LoadConfig,
    world: &Arc<World>,
    connect: &Connector<'_>,
    robots: &[Placed],
    recorder: &Arc<Recorder>,
    triggers: &Arc<Mutex<Triggers>>,
    until: Instant,
) -> Result<(), SimError> {
    let mut drivers = JoinSet::new();
    for (robot, start) in robots {
        let (robot, world, recorder, triggers) =
            (Arc::clone(robot), Arc::clone(world), Arc::clone(recorder), Arc::clone(triggers));
        drivers.spawn(drive::drive(robot, *start, world, config.clone(), recorder, triggers, until));
    }
    let probe = tokio::spawn(probe_empty_calls(connect.channel()?, Arc::clone(recorder), until));
    while let Some(done) = drivers.join_next().await {
        done.map_err(|e| SimError::Fleet(format!("a robot task failed: {e}")))?;
    }
    let _ = probe.await;
    Ok(())
}

async fn probe_empty_calls(channel: Channel, recorder: Arc<Recorder>, until: Instant) {
    let mut health = tonic_health::pb::health_client::HealthClient::new(channel);
    let mut due = Instant::now();
    while due < until {
        tokio::time::sleep_until(due.into()).await;
        let request = tonic_health::pb::HealthCheckRequest { service: String::new() };
        let code = health.check(request).await.map_or_else(|s| s.code(), |_| Code::Ok);
        recorder.record("Health (empty)", due, code);
        due += Duration::from_millis(50);
    }
}

/// Whether every acknowledged update is in the store: each mission's count
/// of map updates and each robot's highest sequence number, read back;
/// with how many were acknowledged.
async fn acknowledged_in_store(
    missions: &mut Missions,
    mission_ids: &[u64],
    robots: &[Placed],
) -> Result<(u64, bool), SimError> {
    let mut in_store = true;
    let mut acknowledged = 0;
    for &mission_id in mission_ids {
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
    Ok((acknowledged, in_store))
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
}
