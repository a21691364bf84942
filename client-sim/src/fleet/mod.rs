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
use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::{Duration, Instant};

use serde::Serialize;
use tokio_util::sync::CancellationToken;
use tonic::Status;

use exploration::grid::Cell;
use exploration::rng::SplitMix64;
use exploration_proto::v1 as pb;
use exploration_proto::v1::missions_client::MissionsClient;

mod steps;

use exploration_proto::replicas::Replicas;
use steps::{Exploration, tick};
use tonic::service::interceptor::InterceptedService;

use crate::generate::{Generator, generate};
use crate::robot::{Bidding, Occupancy, RobotError, RobotModel, SimRobot, TeamMap};
use crate::world::{StartChoice, World, WorldError};

/// Which world to explore.
#[derive(Debug, Clone, PartialEq)]
pub enum WorldSpec {
    /// A ROS map_server map (YAML).
    Map(PathBuf),
    /// A generated world of the given size, metres.
    Generated {
        /// What kind.
        generator: Generator,
        /// Width, metres.
        width_m: f64,
        /// Height, metres.
        height_m: f64,
    },
}

impl WorldSpec {
    /// Builds the world for a run.
    pub fn build(&self, cell_size: Option<f64>, start: StartChoice, seed: u64) -> Result<World, WorldError> {
        match self {
            Self::Map(path) => World::load(path, cell_size, start, seed),
            Self::Generated { generator, width_m, height_m } => {
                generate(*generator, *width_m, *height_m, cell_size.unwrap_or(0.15), seed, start)
            }
        }
    }
}

/// Robots close to each other slow each other down (Burgard et al. 2005,
/// §IV-C: "whenever robots are close to each other, the system performs the
/// planned movement with a probability of 0.7").
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Interference {
    /// Closer than this (metres), robots interfere.
    pub radius_m: f64,
    /// Probability that a planned move happens when they do.
    pub success: f64,
}

/// How far robots can communicate (Burgard et al. 2005, §II-D).
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum CommRange {
    /// In metres.
    Metres(f64),
    /// As a share of the map's diameter (Fig. 12's axis).
    OfDiameter(f64),
}

impl CommRange {
    /// The range in metres on `world`.
    pub fn metres(&self, world: &World) -> f64 {
        match self {
            Self::Metres(m) => *m,
            Self::OfDiameter(f) => f * world.diameter_m(),
        }
    }
}

/// A failure injected into one robot of the team.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Fault {
    /// The robot, by index (robot-0 is 0).
    pub robot: usize,
    /// What goes wrong.
    pub kind: FaultKind,
}

/// What goes wrong with a robot.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum FaultKind {
    /// From this step on it is silent and still: the executive's lease runs out.
    Dies(u64),
    /// From this step on it cannot move but reports: the executive sees it stall.
    Freezes(u64),
    /// It reports targets inside this world rectangle (min, max corners) unreachable.
    CannotReach(exploration::math::Point2, exploration::math::Point2),
}

/// Where the team starts.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Layout {
    /// Packed around the start cell, one robot per cell (the papers' teams
    /// start close to each other).
    #[default]
    Together,
    /// Each robot at its own random cell of the main free area.
    Spread,
}

/// Everything a run is made of.
#[derive(Debug, Clone)]
pub struct RunConfig {
    /// The world.
    pub world: WorldSpec,
    /// Team size.
    pub robots: usize,
    /// Coordination policy.
    pub policy: String,
    /// Policy parameter overrides.
    pub params: BTreeMap<String, f64>,
    /// Seed of every random choice.
    pub seed: u64,
    /// An executive to use; `None` starts one on loopback.
    pub server: Option<String>,
    /// Operator token of the executive: the one `server` requires, or the
    /// one the embedded executive is started with (a random one if `None`).
    pub token: Option<String>,
    /// TLS settings for `server` (an `https://` URL).
    pub tls: Option<exploration_proto::client::ClientTls>,
    /// Database of the embedded executive; `None` uses a temporary file.
    pub db: Option<PathBuf>,
    /// Simulation cell size, metres; `None` keeps a map's own.
    pub cell_size: Option<f64>,
    /// The robots' models, robot i taking model i mod len (heterogeneous teams).
    pub models: Vec<RobotModel>,
    /// Where the team starts.
    pub start: StartChoice,
    /// Together or spread.
    pub layout: Layout,
    /// Interference between close robots; `None` for none.
    pub interference: Option<Interference>,
    /// Limited communication; `None` for unlimited.
    pub comm_range: Option<CommRange>,
    /// Give up after this many steps.
    pub max_steps: u64,
    /// Give up after this many steps in which no robot has a task, or 10×
    /// this many in which the team learns nothing new.
    pub stall_steps: u64,
    /// How long a robot keeps retrying an unreachable executive.
    pub retry_budget: Duration,
    /// Robots of a bidding policy (`simmons`) bid every this many steps.
    pub bid_every: u64,
    /// Print progress to stderr.
    pub progress: bool,
    /// Failures to inject.
    pub faults: Vec<Fault>,
    /// The mission's lease, seconds; `None` keeps the executive's default.
    pub lease_s: Option<f64>,
    /// The mission's stall timeout, seconds; `None` keeps the executive's default.
    pub stall_s: Option<f64>,
    /// Wall-clock time per step, to watch or steer a run as it happens;
    /// `None` runs as fast as the executive answers.
    pub pace: Option<Duration>,
    /// After exploration, keep stepping while the executive sends the robots
    /// home, until every live robot is there (or `max_steps` more steps).
    pub return_home: bool,
    /// Give the mission the world's rooms and corridors (Wurm et al. 2008,
    /// §VI; see [`World::given_rooms`]) instead of letting it segment the
    /// explored map online.
    pub given_segmentation: bool,
    /// Serve the embedded executive's live web view at this address (port 0:
    /// any free port); its URL and a read-only token are printed.
    pub view: Option<SocketAddr>,
    /// After the run, keep the embedded executive (and its view) serving
    /// until Ctrl-C, for a person still looking.
    pub linger: bool,
}

/// The robot of the papers' simulations: 360° sensor of 4 m, point-sized, 0.5 m/s.
pub const DEFAULT_MODEL: RobotModel = RobotModel {
    sensor_range_m: 4.0,
    field_of_view_rad: std::f64::consts::TAU,
    speed_mps: 0.5,
    footprint_radius_m: 0.0,
};

impl RunConfig {
    /// A run of `robots` robots with `policy` on the map at `map`, with the defaults.
    pub fn new(map: impl Into<PathBuf>, robots: usize, policy: &str) -> Self {
        Self::on(WorldSpec::Map(map.into()), robots, policy)
    }

    /// A run of `robots` robots with `policy` in `world`, with the defaults.
    pub fn on(world: WorldSpec, robots: usize, policy: &str) -> Self {
        Self {
            world,
            robots,
            policy: policy.to_owned(),
            params: BTreeMap::new(),
            seed: 1,
            server: None,
            token: None,
            tls: None,
            db: None,
            cell_size: Some(0.15),
            models: vec![DEFAULT_MODEL],
            start: StartChoice::Auto,
            layout: Layout::Together,
            interference: Some(Interference { radius_m: 1.0, success: 0.7 }),
            comm_range: None,
            max_steps: 50_000,
            view: None,
            linger: false,
            stall_steps: 200,
            retry_budget: Duration::from_secs(120),
            bid_every: 5,
            progress: false,
            faults: Vec::new(),
            lease_s: None,
            stall_s: None,
            pace: None,
            return_home: false,
            given_segmentation: false,
        }
    }
}

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
    /// The executive refused a request.
    #[error("executive refused {what}: {status}")]
    Rpc {
        /// Which request.
        what: &'static str,
        /// Its answer.
        status: Status,
    },
    /// The embedded executive could not start.
    #[error("cannot start the embedded executive: {0}")]
    Executive(String),
    /// The configuration cannot run.
    #[error("{0}")]
    Config(String),
}

/// An executive on loopback, owned by the run; stopped when dropped.
pub(crate) struct EmbeddedExecutive {
    pub(crate) url: String,
    /// Its operator token.
    pub(crate) token: String,
    /// Its clock, moved on with the simulation's steps; `None`: the wall clock.
    clock: Option<Arc<coordinator::ManualClock>>,
    stop: CancellationToken,
    task: Option<tokio::task::JoinHandle<Result<(), coordinator::ServeError>>>,
    /// Holds the database (unless one was given) and the view's tokens file.
    _dir: tempfile::TempDir,
}

impl Drop for EmbeddedExecutive {
    fn drop(&mut self) {
        // A run abandoned midway (a time limit) must not leave its executive serving.
        self.stop.cancel();
    }
}

impl EmbeddedExecutive {
    async fn start(db: Option<PathBuf>, operator_token: String, view: Option<SocketAddr>) -> Result<Self, SimError> {
        // The fleet waits for every acknowledgement: a crash of this process
        // takes the fleet with it, so power-cut durability buys nothing here.
        // Its time is the simulation's: leases, stalls and replanning
        // intervals in simulated seconds, the same on any machine.
        Self::start_with(db, operator_token, coordinator::Durability::Normal, true, view).await
    }

    /// An executive as a deployment runs one (every commit survives a power
    /// cut), for load tests; with a random operator token unless given one.
    pub(crate) async fn start_durable(token: Option<String>) -> Result<Self, SimError> {
        let token = match token {
            Some(token) => token,
            None => coordinator::auth::random_operator_token().map_err(|e| SimError::Executive(e.to_string()))?,
        };
        Self::start_with(None, token, coordinator::Durability::Full, false, None).await
    }

    async fn start_with(
        db: Option<PathBuf>,
        operator_token: String,
        durability: coordinator::Durability,
        simulated_time: bool,
        view: Option<SocketAddr>,
    ) -> Result<Self, SimError> {
        let failed = |e: &dyn std::fmt::Display| SimError::Executive(e.to_string());
        let dir = tempfile::tempdir().map_err(|e| failed(&e))?;
        let path = db.unwrap_or_else(|| dir.path().join("coordinator.db"));
        let listener =
            tokio::net::TcpListener::bind("127.0.0.1:0").await.map_err(|e| SimError::Executive(e.to_string()))?;
        let address = listener.local_addr().map_err(|e| SimError::Executive(e.to_string()))?;
        let stop = CancellationToken::new();
        let shutdown = stop.clone().cancelled_owned();
        let mut config = coordinator::Config::new(path);
        config.operator_token = Some(operator_token.clone());
        config.durability = durability;
        let clock = simulated_time.then(|| {
            let (clock, handle) = coordinator::Clock::manual();
            config.executive.clock = clock;
            handle
        });
        let http = match view {
            Some(address) => {
                let http = tokio::net::TcpListener::bind(address).await.map_err(|e| failed(&e))?;
                let viewer = coordinator::auth::random_operator_token().map_err(|e| failed(&e))?;
                let tokens = dir.path().join("tokens");
                let line = format!("viewer viewer {}\n", coordinator::auth::sha256_hex(&viewer));
                std::fs::write(&tokens, line).map_err(|e| failed(&e))?;
                config.operator_tokens_file = Some(tokens);
                let url = http.local_addr().map_err(|e| failed(&e))?;
                eprintln!("live view: http://{url}/  (read-only token: {viewer})");
                Some(http)
            }
            None => None,
        };
        let listeners = coordinator::Listeners { grpc: listener, http, health: None };
        let task = tokio::spawn(coordinator::run_with(listeners, shutdown, config));
        Ok(Self { url: format!("http://{address}"), token: operator_token, clock, stop, task: Some(task), _dir: dir })
    }

    pub(crate) async fn stop(mut self) -> Result<(), SimError> {
        self.stop.cancel();
        let Some(task) = self.task.take() else { return Ok(()) };
        match task.await {
            Ok(Ok(())) => Ok(()),
            Ok(Err(e)) => Err(SimError::Executive(e.to_string())),
            Err(e) => Err(SimError::Executive(e.to_string())),
        }
    }
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
            eprintln!("the run is over; the live view stays up until Ctrl-C");
            let _ = tokio::signal::ctrl_c().await;
        }
        executive.stop().await?;
    }
    result
}

/// The cells the robots start on: all on the world's start, or spread over
/// random cells reachable from it.
fn start_cells(world: &World, config: &RunConfig) -> Vec<Cell> {
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
        .ok_or_else(|| SimError::Executive(format!("the executive offers no policy {name:?}")))
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
    Ok(crate::robot::retry(what, budget, || call(missions.clone())).await?)
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
        eprintln!(
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
        .map_err(|e| SimError::Executive(format!("bad executive URL or TLS settings for {url}: {e}")))?;
    let bearer = exploration_proto::Bearer::new(token)
        .map_err(|e| SimError::Executive(format!("the token is not valid metadata: {e}")))?;
    Ok(MissionsClient::with_interceptor(channel, bearer))
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
            m.get_segmentation(pb::GetSegmentationRequest { mission_id, include_labels: true }).await
        })
        .await
        .ok()
        .map(|r| r.labels)
        .filter(|l| l.len() == world.frame.len() * 4)
        .map(|l| l.chunks_exact(4).map(|c| u32::from_le_bytes([c[0], c[1], c[2], c[3]])).collect())
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn communication_ranges_read_in_metres_or_of_the_diameter() {
        let world = generate(Generator::Empty, 30.0, 40.0, 0.5, 1, StartChoice::Auto).unwrap();
        assert_eq!(CommRange::Metres(7.0).metres(&world), 7.0);
        assert!((CommRange::OfDiameter(0.3).metres(&world) - 15.0).abs() < 1e-9);
    }
}
