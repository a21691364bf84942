//! The fleet runner: one mission, N simulated robots, until the reachable
//! free space is known.
//!
//! Time is discrete. In each step every robot, in a fixed order, moves,
//! senses, and reports to the executive; the executive may replan within
//! that request. Because the robots take turns and every random draw comes
//! from the run's seed, the executive sees the same requests in the same
//! order on every run with the same seed, and the run is reproducible, while
//! each robot remains its own gRPC client.
//!
//! The models of the papers' simulators, each a setting with the paper's
//! value as its default: cells of 15 cm and interference (robots closer than
//! a set distance move with probability 0.7; Burgard et al. 2005, §IV-C),
//! 360° sensors, teams started close together, and limited communication
//! (§II-D). Robots take up space: one robot per cell, a robot waits when its
//! next cell is taken, and after waiting a few steps it goes around the
//! robot in its way. The embedded executive's clock is the simulation's: a
//! step lasts the time a robot of the reference speed needs for one cell,
//! so leases, stalls and replanning intervals are in simulated seconds and a
//! seed gives the same run on any machine at any load.

use std::collections::BTreeMap;
use std::sync::Arc;
use std::time::{Duration, Instant};

use serde::Serialize;
use tokio_util::sync::CancellationToken;
use tonic::Status;

use exploration::grid::Cell;
use exploration::rng::SplitMix64;
use exploration_proto::v1 as pb;
use exploration_proto::v1::missions_client::MissionsClient;

mod config;
mod embedded;
mod steps;

pub use config::*;
pub(crate) use embedded::EmbeddedExecutive;

use exploration_proto::replicas::Replicas;
use steps::{Exploration, tick};
use tonic::service::interceptor::InterceptedService;

use crate::robot::{Bidding, Occupancy, RobotError, SimRobot, TeamMap};
use crate::world::{World, WorldError};

/// What a run measured.
#[derive(Debug, Clone, Serialize)]
pub struct RunReport {
    /// The executive's mission.
    pub mission_id: u64,
    /// The world.
    pub map: String,
    /// The policy.
    pub policy: String,
    /// Team size.
    pub robots: usize,
    /// The seed.
    pub seed: u64,
    /// Whether every reachable free cell became known (by one robot, under
    /// limited communication, as Burgard et al. 2005 §IV-D count it).
    pub completed: bool,
    /// Why the run ended.
    pub ended: String,
    /// Time steps taken.
    pub steps: u64,
    /// Share of reachable free cells known at the end (0..1).
    pub coverage: f64,
    /// Steps to reach 50, 90, 95 and 100 % coverage (Simmons et al. 2000).
    pub t50: Option<u64>,
    /// See `t50`.
    pub t90: Option<u64>,
    /// See `t50`.
    pub t95: Option<u64>,
    /// See `t50`.
    pub t100: Option<u64>,
    /// Metres each robot travelled.
    pub distance_per_robot: Vec<f64>,
    /// Steps robots spent without a task, summed over the team.
    pub idle_steps: u64,
    /// Targets abandoned for another before being reached, summed over the team.
    pub target_switches: u64,
    /// Replannings of the executive.
    pub replans: u64,
    /// Map updates the executive applied.
    pub map_updates: u64,
    /// Map updates the robots saw acknowledged; equals `map_updates` when
    /// none was lost or applied twice.
    pub updates_acknowledged: u64,
    /// Reachable free cells of the world.
    pub reachable_cells: usize,
    /// Cell size, metres.
    pub cell_size: f64,
    /// Communication range, metres, when limited.
    pub comm_range_m: Option<f64>,
    /// Cells sensed by more than one robot, as a share of the cells sensed.
    pub overlap: f64,
    /// Steps at which the assignment stream lagged behind a response.
    pub stream_lags: u64,
    /// Wall-clock seconds.
    pub wall_time_s: f64,
    /// Each robot's cells, in order (not serialized).
    #[serde(skip)]
    pub trajectories: Vec<Vec<Cell>>,
    /// Coverage after each step (not serialized).
    #[serde(skip)]
    pub coverage_curve: Vec<f32>,
    /// The world explored (not serialized).
    #[serde(skip)]
    pub world: Option<World>,
    /// The executive's last segmentation labels, for `segmentation` (not serialized).
    #[serde(skip)]
    pub segments: Option<Vec<u32>>,
    /// With injected faults: the mission's tasks by how they ended, and the
    /// robots the executive holds lost at the end.
    pub fault_record: Option<FaultRecord>,
    /// With `return_home`: steps from the end of exploration until the
    /// executive had completed the mission and every live robot was home;
    /// `None` when not asked for or not reached within the step limit.
    pub home_steps: Option<u64>,
}

impl RunReport {
    /// Targets abandoned before being reached, per robot per 100 steps.
    pub fn switches_per_robot_per_100_steps(&self) -> f64 {
        100.0 * self.target_switches as f64 / (self.robots.max(1) as f64 * self.steps.max(1) as f64)
    }
}

/// How the executive dealt with injected faults.
#[derive(Debug, Clone, Default, Serialize)]
pub struct FaultRecord {
    /// Tasks by state ("reached", "failed", "released", ...).
    pub tasks_by_state: BTreeMap<String, usize>,
    /// Tasks failed by the executive for lack of progress.
    pub stalled_tasks: usize,
    /// Tasks the robots reported unreachable.
    pub unreachable_tasks: usize,
    /// Robots marked lost (lease expired) at the end.
    pub lost_robots: Vec<String>,
}

/// Why a run could not be carried out.
#[derive(Debug, thiserror::Error)]
pub enum SimError {
    /// The world could not be loaded.
    #[error(transparent)]
    World(#[from] WorldError),
    /// A robot gave up.
    #[error("robot failed: {0}")]
    Robot(#[from] RobotError),
    /// One of the fleet's own calls (creating the mission, reading its
    /// policy) failed for good.
    #[error("{0}")]
    Call(RobotError),
    /// The executive refused a request.
    #[error("executive refused {what}: {}", exploration_proto::client::status_line(.status))]
    Rpc {
        /// Which request.
        what: &'static str,
        /// Its answer.
        status: Status,
    },
    /// The embedded executive could not start.
    #[error("cannot start the embedded executive: {0}")]
    Executive(String),
    /// The fleet's own side cannot go on: the executive's address or the
    /// token it was given are unusable, or a robot's task failed.
    #[error("{0}")]
    Fleet(String),
    /// The configuration cannot run.
    #[error("{0}")]
    Config(String),
}

/// Runs one mission to the end.
pub async fn run(config: &RunConfig) -> Result<RunReport, SimError> {
    if config.robots == 0 || config.models.is_empty() {
        return Err(SimError::Config("a run needs at least one robot and one robot model".into()));
    }
    let world = config.world.build(config.cell_size, config.start, config.seed)?;
    let (embedded, url, token) = match &config.server {
        Some(url) => (None, url.clone(), config.token.clone()),
        None => {
            // Loopback is shared with every local user: the embedded executive
            // is not left open, only this fleet holds its operator token.
            let token = match &config.token {
                Some(token) => token.clone(),
                None => coordinator::auth::random_operator_token().map_err(|e| SimError::Executive(e.to_string()))?,
            };
            let executive = EmbeddedExecutive::start(config.db.clone(), token.clone(), config.view).await?;
            let url = executive.url.clone();
            (Some(executive), url, Some(token))
        }
    };
    let clock = embedded.as_ref().and_then(|e| e.clock.clone());
    let result = run_against(config, world, &url, token.as_deref(), clock).await;
    if let Some(executive) = embedded {
        if config.linger && config.view.is_some() {
            crate::errln!("the run is over; the live view stays up until Ctrl-C");
            let _ = tokio::signal::ctrl_c().await;
        }
        executive.stop().await?;
    }
    result
}

/// The cells the robots start on: all on the world's start, or spread over
/// random cells reachable from it.
pub(crate) fn start_cells(world: &World, config: &RunConfig) -> Vec<Cell> {
    match config.layout {
        Layout::Together => packed_around(world, world.start, config.robots),
        Layout::Spread => {
            let mut reachable: Vec<usize> = (0..world.frame.len()).filter(|&i| world.reachable[i]).collect();
            let mut rng = SplitMix64::new(config.seed ^ 0x5350_5245_4144);
            // Distinct cells: drawn without replacement.
            (0..config.robots.min(reachable.len()))
                .map(|_| world.frame.cell(reachable.swap_remove(rng.below(reachable.len() as u64) as usize)))
                .collect()
        }
    }
}

/// `n` distinct reachable cells closest to `start` (breadth first, 4-connected,
/// neighbours in a fixed order): a team standing close together, one robot
/// per cell, the first on the start itself.
fn packed_around(world: &World, start: Cell, n: usize) -> Vec<Cell> {
    let frame = world.frame;
    let mut seen = vec![false; frame.len()];
    let mut queue = std::collections::VecDeque::from([start]);
    seen[frame.index(start)] = true;
    let mut cells = Vec::with_capacity(n);
    while let Some(cell) = queue.pop_front() {
        if cells.len() == n {
            break;
        }
        cells.push(cell);
        for (dx, dy) in [(1, 0), (0, 1), (-1, 0), (0, -1)] {
            let next = Cell::new(cell.x + dx, cell.y + dy);
            if frame.contains(next) && world.reachable[frame.index(next)] && !seen[frame.index(next)] {
                seen[frame.index(next)] = true;
                queue.push_back(next);
            }
        }
    }
    cells
}

/// What the executive says of a policy: whether robots bid, whether it
/// keeps a segmentation, its parameters.
async fn policy_info(missions: &Missions, name: &str, budget: Duration) -> Result<pb::PolicyInfo, SimError> {
    let listed =
        ask(missions, "ListPolicies", budget, |mut m| async move { m.list_policies(pb::ListPoliciesRequest {}).await })
            .await?;
    listed
        .policies
        .into_iter()
        .find(|p| p.name == name)
        .ok_or_else(|| SimError::Fleet(format!("the executive offers no policy {name:?}")))
}

/// Calls the executive on a clone of the client, retrying through restarts
/// and shedding as the robots do: a run survives an executive killed at any
/// moment, before, during or after its steps.
async fn ask<T, Fut>(
    missions: &Missions,
    what: &'static str,
    budget: Duration,
    call: impl Fn(Missions) -> Fut,
) -> Result<T, SimError>
where
    Fut: std::future::Future<Output = Result<tonic::Response<T>, Status>>,
{
    crate::robot::retry(what, budget, || call(missions.clone())).await.map_err(SimError::Call)
}

/// The executive's mission API as the fleet holds it: a lazy channel with
/// the fleet's bearer token.
type Missions = MissionsClient<InterceptedService<Replicas, exploration_proto::Bearer>>;

/// One run against a running executive: create the mission, bring the team
/// up, step it until the map is known or the run cannot go on, and measure.
async fn run_against(
    config: &RunConfig,
    world: World,
    url: &str,
    token: Option<&str>,
    clock: Option<Arc<coordinator::ManualClock>>,
) -> Result<RunReport, SimError> {
    let started = Instant::now();
    let missions = missions_client(config, url, token)?;
    let mission = create_mission(&missions, config, &world).await?;
    if config.given_segmentation {
        give_rooms(&missions, config, &world, mission.id).await?;
    }
    if config.progress {
        let frame = world.frame;
        crate::errln!(
            "mission {} on {} ({}×{} cells of {} m, {} reachable), {} robots, policy {}",
            mission.id,
            world.name,
            frame.width,
            frame.height,
            frame.resolution,
            world.reachable_cells,
            config.robots,
            config.policy
        );
    }
    let policy = policy_info(&missions, &config.policy, config.retry_budget).await?;
    let stop = CancellationToken::new();
    let _stop_streams = stop.clone().drop_guard();
    let mut robots = launch_team(config, &world, url, token, mission.id, &policy, &stop).await?;
    inject_faults(&mut robots, config, &world)?;
    let mut exploration = Exploration::new(config, &world);
    let ended = exploration.run(&mut robots, &world, config, clock.as_deref()).await?;
    let home_steps = if config.return_home {
        return_home(&mut robots, &world, &mut exploration.team, config, clock.as_deref()).await?
    } else {
        None
    };
    let from_executive = ask_executive(&missions, mission.id, config, &policy, &world).await?;
    Ok(exploration.report(config, world, &robots, mission.id, ended, home_steps, from_executive, started))
}

fn missions_client(config: &RunConfig, url: &str, token: Option<&str>) -> Result<Missions, SimError> {
    for replica in url.split(',') {
        if let Some(warning) = exploration_proto::client::plaintext_token_warning(replica.trim(), token) {
            tracing::warn!("{warning}");
        }
    }
    let channel = Replicas::from_list(url, config.tls.as_ref())
        .map_err(|e| SimError::Fleet(format!("bad executive URL or TLS settings: {e}")))?;
    Ok(MissionsClient::with_interceptor(channel, bearer(token)?))
}

/// The interceptor that sends `token`, if it is valid metadata.
pub(crate) fn bearer(token: Option<&str>) -> Result<exploration_proto::Bearer, SimError> {
    exploration_proto::Bearer::new(token).map_err(|e| SimError::Fleet(format!("the token is not valid metadata: {e}")))
}

/// Creates the run's mission, in lockstep so that a seed gives the same run
/// at any speed.
async fn create_mission(missions: &Missions, config: &RunConfig, world: &World) -> Result<pb::Mission, SimError> {
    let frame = world.frame;
    let request = pb::CreateMissionRequest {
        name: format!("fleet-sim {} seed {}", world.name, config.seed),
        frame: Some(pb::MapFrame {
            resolution: frame.resolution,
            origin: Some(pb::Point { x: frame.origin.x, y: frame.origin.y }),
            width: frame.width,
            height: frame.height,
        }),
        policy: Some(pb::PolicySpec {
            name: config.policy.clone(),
            params: config.params.iter().map(|(k, v)| (k.clone(), *v)).collect(),
        }),
        replan: None,
        scoped_by_communication: config.comm_range.is_some(),
        lockstep: true,
        lifecycle: Some(pb::LifecycleSettings {
            lease_s: config.lease_s.unwrap_or(0.0),
            stall_s: config.stall_s.unwrap_or(0.0),
            rendezvous: None,
        }),
    };
    // An executive restarting (or busy) when the run begins is waited for, as
    // the robots wait for it later. A create that was committed but whose
    // answer was lost leaves an unused mission behind: harmless.
    ask(missions, "CreateMission", config.retry_budget, |mut m| {
        let request = request.clone();
        async move { m.create_mission(request).await }
    })
    .await
}

/// Gives the mission the world's rooms and corridors.
async fn give_rooms(missions: &Missions, config: &RunConfig, world: &World, mission_id: u64) -> Result<(), SimError> {
    let request = pb::SetGivenSegmentationRequest {
        mission_id,
        label_runs: exploration_proto::label_runs::encode(&world.given_rooms()),
        actor: "fleet-sim".to_owned(),
        reason: format!("the rooms of {}", world.name),
    };
    ask(missions, "SetGivenSegmentation", config.retry_budget, |mut m| {
        let request = request.clone();
        async move { m.set_given_segmentation(request).await }
    })
    .await?;
    Ok(())
}

/// Connects and registers every robot on its start cell.
async fn launch_team(
    config: &RunConfig,
    world: &World,
    url: &str,
    token: Option<&str>,
    mission_id: u64,
    policy: &pb::PolicyInfo,
    stop: &CancellationToken,
) -> Result<Vec<SimRobot>, SimError> {
    // Bidding robots space their bid cells as the policy's `spacing_m` says.
    let bidding =
        policy.uses_bids.then(|| Bidding {
            every: config.bid_every.max(1),
            spacing_m: config.params.get("spacing_m").copied().unwrap_or_else(|| {
                policy.params.iter().find(|p| p.name == "spacing_m").map_or(0.0, |p| p.default_value)
            }),
        });
    let mut robots = Vec::with_capacity(config.robots);
    for (i, start) in start_cells(world, config).into_iter().enumerate() {
        robots.push(
            SimRobot::connect(
                url,
                config.tls.as_ref(),
                token,
                mission_id,
                format!("robot-{i}"),
                start,
                world,
                config.models[i % config.models.len()],
                bidding,
                config.comm_range.is_some(),
                config.robots,
                config.retry_budget,
                stop.clone(),
            )
            .await?,
        );
    }
    Ok(robots)
}

/// Gives the robots the faults the run asks for.
fn inject_faults(robots: &mut [SimRobot], config: &RunConfig, world: &World) -> Result<(), SimError> {
    for fault in &config.faults {
        let Some(robot) = robots.get_mut(fault.robot) else {
            return Err(SimError::Config(format!(
                "a fault names robot {} but the team has {} robots",
                fault.robot, config.robots
            )));
        };
        let mut faults = robot.faults();
        match fault.kind {
            FaultKind::Dies(step) => faults.dies_at = Some(step),
            FaultKind::Freezes(step) => faults.freezes_at = Some(step),
            FaultKind::CannotReach(min, max) => {
                let frame = world.frame;
                let (low, high) = (frame.cell_from_world_unchecked(&min), frame.cell_from_world_unchecked(&max));
                faults.unreachable = Some(exploration::grid::CellRect::spanning(low, high));
            }
        }
        robot.inject(faults);
    }
    Ok(())
}

/// What the report takes from the executive at the end of a run.
struct FromExecutive {
    summary: pb::Mission,
    segments: Option<Vec<u32>>,
    fault_record: Option<FaultRecord>,
}

async fn ask_executive(
    missions: &Missions,
    mission_id: u64,
    config: &RunConfig,
    policy: &pb::PolicyInfo,
    world: &World,
) -> Result<FromExecutive, SimError> {
    let budget = config.retry_budget;
    let summary = ask(missions, "GetMission", budget, |mut m| async move {
        m.get_mission(pb::GetMissionRequest { mission_id }).await
    })
    .await?;
    let segments = if policy.keeps_segmentation {
        ask(missions, "GetSegmentation", budget, |mut m| async move {
            m.get_segmentation(pb::GetSegmentationRequest { mission_id, include_labels: true, label_runs: true }).await
        })
        .await
        .ok()
        .and_then(|r| r.labels_per_cell(world.frame.len()).ok().flatten())
    } else {
        None
    };
    let fault_record =
        if config.faults.is_empty() { None } else { Some(fault_record(missions, mission_id, budget).await?) };
    Ok(FromExecutive { summary, segments, fault_record })
}

/// Steps the team on after exploration: the executive completes the mission
/// (it may still send robots to frontier the team could not see was
/// useless) and then sends each robot home. The number of steps until the
/// mission is complete and no live robot has a task left.
async fn return_home(
    robots: &mut [SimRobot],
    world: &World,
    team: &mut TeamMap,
    config: &RunConfig,
    clock: Option<&coordinator::ManualClock>,
) -> Result<Option<u64>, SimError> {
    for step in 1..=config.max_steps {
        let (mut completed, mut busy) = (false, false);
        let mut occupied = Occupancy::of(robots.iter().map(|r| r.cell));
        for robot in robots.iter_mut() {
            let outcome = robot.step(world, team, false, &mut occupied).await?;
            completed |= outcome.mission_completed;
            busy |= outcome.has_task && !outcome.dead;
        }
        if completed && !busy {
            return Ok(Some(step));
        }
        tick(clock, &world.frame).await;
        if let Some(pace) = config.pace {
            tokio::time::sleep(pace).await;
        }
    }
    Ok(None)
}

async fn fault_record(missions: &Missions, mission_id: u64, budget: Duration) -> Result<FaultRecord, SimError> {
    let tasks = ask(missions, "ListTasks", budget, |mut m| async move {
        m.list_tasks(pb::ListTasksRequest { mission_id, limit: 100_000, ..Default::default() }).await
    })
    .await?
    .tasks;
    let robots = ask(missions, "ListRobots", budget, |mut m| async move {
        m.list_robots(pb::ListRobotsRequest { mission_id }).await
    })
    .await?
    .robots;
    let mut record = FaultRecord::default();
    for task in &tasks {
        let state = pb::TaskState::try_from(task.state)
            .map_or("unknown".to_owned(), |s| s.as_str_name().trim_start_matches("TASK_STATE_").to_lowercase());
        *record.tasks_by_state.entry(state).or_default() += 1;
        let last = task.transitions.last().map(|t| t.cause.as_str()).unwrap_or("");
        record.stalled_tasks += usize::from(last.starts_with("no progress"));
        record.unreachable_tasks += usize::from(last.contains("unreachable"));
    }
    record.lost_robots = robots.iter().filter(|r| r.lost).map(|r| r.name.clone()).collect();
    Ok(record)
}
