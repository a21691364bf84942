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

use std::collections::{BTreeMap, HashSet};
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

use crate::generate::{Generator, generate};
use crate::robot::{Bidding, RobotError, RobotModel, SimRobot, TeamMap};
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
            stall_steps: 200,
            retry_budget: Duration::from_secs(120),
            bid_every: 5,
            progress: false,
            faults: Vec::new(),
            lease_s: None,
            stall_s: None,
            pace: None,
            return_home: false,
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
    _dir: Option<tempfile::TempDir>,
}

impl Drop for EmbeddedExecutive {
    fn drop(&mut self) {
        // A run abandoned midway (a time limit) must not leave its executive serving.
        self.stop.cancel();
    }
}

impl EmbeddedExecutive {
    async fn start(db: Option<PathBuf>, operator_token: String) -> Result<Self, SimError> {
        // The fleet waits for every acknowledgement: a crash of this process
        // takes the fleet with it, so power-cut durability buys nothing here.
        // Its time is the simulation's: leases, stalls and replanning
        // intervals in simulated seconds, the same on any machine.
        Self::start_with(db, operator_token, coordinator::Durability::Normal, true).await
    }

    /// An executive as a deployment runs one (every commit survives a power
    /// cut), for load tests; with a random operator token unless given one.
    pub(crate) async fn start_durable(token: Option<String>) -> Result<Self, SimError> {
        let token = match token {
            Some(token) => token,
            None => coordinator::auth::random_operator_token().map_err(|e| SimError::Executive(e.to_string()))?,
        };
        Self::start_with(None, token, coordinator::Durability::Full, false).await
    }

    async fn start_with(
        db: Option<PathBuf>,
        operator_token: String,
        durability: coordinator::Durability,
        simulated_time: bool,
    ) -> Result<Self, SimError> {
        let (path, dir) = match db {
            Some(path) => (path, None),
            None => {
                let dir = tempfile::tempdir().map_err(|e| SimError::Executive(e.to_string()))?;
                (dir.path().join("coordinator.db"), Some(dir))
            }
        };
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
        let task = tokio::spawn(coordinator::run(listener, shutdown, config));
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
            let executive = EmbeddedExecutive::start(config.db.clone(), token.clone()).await?;
            let url = executive.url.clone();
            (Some(executive), url, Some(token))
        }
    };
    let clock = embedded.as_ref().and_then(|e| e.clock.clone());
    let result = run_against(config, world, &url, token.as_deref(), clock).await;
    if let Some(executive) = embedded {
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

/// Gives robot `to` what the other robots of its cluster integrated and
/// have not sent it yet (Burgard et al. 2005 §III: each robot logs what it
/// sent each peer, so nothing is integrated twice).
fn gather(robots: &mut [SimRobot], cluster: &[usize], to: usize, world: &World) {
    for &from in cluster.iter().filter(|&&from| from != to) {
        let (sender, receiver) = if from < to {
            let (low, high) = robots.split_at_mut(to);
            (&mut low[from], &mut high[0])
        } else {
            let (low, high) = robots.split_at_mut(from);
            (&mut high[0], &mut low[to])
        };
        sender.share_with(receiver, to, world);
    }
}

/// Robot `from` passes what it knows to the rest of its cluster.
fn scatter(robots: &mut [SimRobot], cluster: &[usize], from: usize, world: &World) {
    for &to in cluster.iter().filter(|&&to| to != from) {
        gather(robots, &[from, to], to, world);
    }
}

/// Robots in range of each other, through any chain of robots in range
/// (the ad-hoc network forwards within a cluster, Burgard et al. §III).
fn communication_clusters(robots: &[SimRobot], range_cells: f64) -> Vec<Vec<usize>> {
    let n = robots.len();
    let mut cluster: Vec<usize> = (0..n).collect();
    fn root(c: &mut [usize], mut k: usize) -> usize {
        while c[k] != k {
            c[k] = c[c[k]];
            k = c[k];
        }
        k
    }
    for i in 0..n {
        for j in i + 1..n {
            if robots[i].cell.distance(robots[j].cell) <= range_cells {
                let (a, b) = (root(&mut cluster, i), root(&mut cluster, j));
                cluster[a.max(b)] = a.min(b);
            }
        }
    }
    let mut groups: BTreeMap<usize, Vec<usize>> = BTreeMap::new();
    for i in 0..n {
        let r = root(&mut cluster, i);
        groups.entry(r).or_default().push(i);
    }
    groups.into_values().collect()
}

/// Moves the executive's simulated clock on by one step (the time a robot of
/// the reference speed takes for one cell), when it has one.
async fn tick(clock: Option<&coordinator::ManualClock>, frame: &exploration::grid::GridFrame) {
    if let Some(clock) = clock {
        clock.step(Duration::from_secs_f64(frame.resolution / crate::robot::REFERENCE_SPEED_MPS)).await;
    }
}

async fn run_against(
    config: &RunConfig,
    world: World,
    url: &str,
    token: Option<&str>,
    clock: Option<Arc<coordinator::ManualClock>>,
) -> Result<RunReport, SimError> {
    let started = Instant::now();
    if let Some(warning) = exploration_proto::client::plaintext_token_warning(url, token) {
        tracing::warn!("{warning}");
    }
    let channel = exploration_proto::client::endpoint(url, config.tls.as_ref())
        .map_err(|e| SimError::Executive(format!("bad executive URL or TLS settings for {url}: {e}")))?
        .connect_lazy();
    let bearer = exploration_proto::Bearer::new(token)
        .map_err(|e| SimError::Executive(format!("the token is not valid metadata: {e}")))?;
    let mut missions = MissionsClient::with_interceptor(channel, bearer);
    let frame = world.frame;
    let limited = config.comm_range.is_some();
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
        scoped_by_communication: limited,
        // A run steps in lock-step with the executive's plans: a seed
        // gives the same run at any speed.
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
    let mission = crate::robot::retry("CreateMission", config.retry_budget, || {
        let mut missions = missions.clone();
        let request = request.clone();
        async move { missions.create_mission(request).await }
    })
    .await?;
    if config.progress {
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
    let stop = CancellationToken::new();
    let _stop_streams = stop.clone().drop_guard();
    let bidding = (config.policy == "simmons").then(|| Bidding {
        every: config.bid_every.max(1),
        spacing_m: config.params.get("spacing_m").copied().unwrap_or(0.3),
    });
    let starts = start_cells(&world, config);
    let mut robots = Vec::with_capacity(config.robots);
    for (i, &start) in starts.iter().enumerate() {
        robots.push(
            SimRobot::connect(
                url,
                config.tls.as_ref(),
                token,
                mission.id,
                format!("robot-{i}"),
                start,
                &world,
                config.models[i % config.models.len()],
                bidding,
                limited,
                config.robots,
                config.retry_budget,
                stop.clone(),
            )
            .await?,
        );
    }
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
                let (low, high) = (frame.cell_from_world_unchecked(&min), frame.cell_from_world_unchecked(&max));
                faults.unreachable = Some(exploration::grid::CellRect::spanning(low, high));
            }
        }
        robot.inject(faults);
    }
    let range_cells = config.comm_range.map(|r| r.metres(&world) / frame.resolution);
    let mut rng = SplitMix64::new(config.seed ^ 0x494E_5445_5246);
    let mut team = TeamMap::new(frame);
    let mut milestones: [Option<u64>; 4] = [None; 4];
    const LEVELS: [f64; 4] = [0.5, 0.9, 0.95, 1.0];
    let mut curve = Vec::new();
    let (mut idle_steps, mut idle_total) = (0, 0);
    let mut last_progress = (0, 0);
    let mut step = 0;
    let known = |team: &TeamMap, robots: &[SimRobot]| {
        if limited { robots.iter().map(|r| r.known_reachable).max().unwrap_or(0) } else { team.known_reachable }
    };
    let ended = loop {
        // Limited communication: who is in range, and what they pass on.
        let clusters = range_cells.map(|range| communication_clusters(&robots, range)).unwrap_or_default();
        let mut cluster_of = vec![None; robots.len()];
        for (c, cluster) in clusters.iter().enumerate() {
            for &k in cluster {
                cluster_of[k] = Some(c);
                gather(&mut robots, cluster, k, &world);
            }
        }
        for cluster in &clusters {
            let ids: Vec<u64> = cluster.iter().map(|&k| robots[k].id).collect();
            for &k in cluster {
                let peers = ids.iter().copied().filter(|id| *id != robots[k].id).collect();
                robots[k].hear_peers(peers, &world, &team).await?;
            }
        }
        let mut any_task = false;
        let mut executive_done = false;
        let cells: Vec<Cell> = robots.iter().map(|r| r.cell).collect();
        let mut occupied: HashSet<Cell> = cells.iter().copied().collect();
        for i in 0..robots.len() {
            let robot = &mut robots[i];
            // Interference: a move near another robot succeeds with probability p.
            let blocked = config.interference.is_some_and(|f| {
                let near = cells
                    .iter()
                    .enumerate()
                    .any(|(j, c)| j != i && c.distance(robot.cell) * frame.resolution <= f.radius_m);
                near && !rng.chance(f.success)
            });
            let outcome = robot.step(&world, &mut team, blocked, &mut occupied).await?;
            // Robots in range talk all the time: what one senses reaches its
            // sub-team at once, before any of them plans on its own map (the
            // executive plans the sub-team on the map they share), even one
            // that leaves the range before its next step.
            if let Some(c) = cluster_of[i] {
                scatter(&mut robots, &clusters[c], i, &world);
            }
            any_task |= outcome.has_task;
            if !outcome.has_task {
                idle_total += 1;
            }
            executive_done |= outcome.mission_completed;
        }
        let known_now = known(&team, &robots);
        let coverage = known_now as f64 / world.reachable_cells.max(1) as f64;
        curve.push(coverage as f32);
        for (slot, level) in milestones.iter_mut().zip(LEVELS) {
            // On the base of `steps`: the number of steps taken when reached.
            if slot.is_none() && coverage >= level - 1e-12 {
                *slot = Some(step + 1);
            }
        }
        if config.progress && step % 250 == 0 {
            eprintln!("step {step:>6}  coverage {:>5.1} %", 100.0 * coverage);
        }
        if known_now >= world.reachable_cells {
            break "every reachable free cell is known".to_owned();
        }
        if executive_done && !limited {
            break "the executive reports no frontier left".to_owned();
        }
        idle_steps = if any_task { 0 } else { idle_steps + 1 };
        if idle_steps >= config.stall_steps {
            break format!("no robot had a task for {idle_steps} steps");
        }
        if known_now > last_progress.0 {
            last_progress = (known_now, step);
        } else if step - last_progress.1 >= 10 * config.stall_steps {
            break format!("the team learnt nothing for {} steps", step - last_progress.1);
        }
        step += 1;
        tick(clock.as_deref(), &frame).await;
        if let Some(pace) = config.pace {
            tokio::time::sleep(pace).await;
        }
        if step >= config.max_steps {
            break format!("step limit {} reached", config.max_steps);
        }
    };
    let home_steps = if config.return_home {
        return_home(&mut robots, &world, &mut team, config, clock.as_deref()).await?
    } else {
        None
    };
    let summary = missions
        .get_mission(pb::GetMissionRequest { mission_id: mission.id })
        .await
        .map_err(|status| SimError::Rpc { what: "GetMission", status })?
        .into_inner();
    let segments = if config.policy == "segmentation" {
        missions
            .get_segmentation(pb::GetSegmentationRequest { mission_id: mission.id, include_labels: true })
            .await
            .ok()
            .map(|r| r.into_inner().labels)
            .filter(|l| l.len() == frame.len() * 4)
            .map(|l| l.chunks_exact(4).map(|c| u32::from_le_bytes([c[0], c[1], c[2], c[3]])).collect())
    } else {
        None
    };
    let fault_record =
        if config.faults.is_empty() { None } else { Some(fault_record(&mut missions, mission.id).await?) };
    let sensed = team.sensed_by.iter().filter(|&&n| n > 0).count();
    let overlapping = team.sensed_by.iter().filter(|&&n| n > 1).count();
    let known_now = known(&team, &robots);
    Ok(RunReport {
        mission_id: mission.id,
        map: world.name.clone(),
        policy: config.policy.clone(),
        robots: config.robots,
        seed: config.seed,
        completed: known_now >= world.reachable_cells,
        ended,
        steps: step + 1,
        coverage: known_now as f64 / world.reachable_cells.max(1) as f64,
        t50: milestones[0],
        t90: milestones[1],
        t95: milestones[2],
        t100: milestones[3],
        distance_per_robot: robots.iter().map(|r| r.distance_m).collect(),
        idle_steps: idle_total,
        replans: summary.replans,
        map_updates: summary.map_updates,
        updates_acknowledged: robots.iter().map(|r| r.acknowledged_updates).sum(),
        reachable_cells: world.reachable_cells,
        cell_size: frame.resolution,
        comm_range_m: range_cells.map(|r| r * frame.resolution),
        overlap: if sensed == 0 { 0.0 } else { overlapping as f64 / sensed as f64 },
        stream_lags: robots.iter().map(|r| r.stream_lags).sum(),
        wall_time_s: started.elapsed().as_secs_f64(),
        trajectories: robots.iter().map(|r| r.trajectory.clone()).collect(),
        coverage_curve: curve,
        world: Some(world),
        segments,
        fault_record,
        home_steps,
    })
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
        let mut occupied: HashSet<Cell> = robots.iter().map(|r| r.cell).collect();
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

async fn fault_record<T>(missions: &mut MissionsClient<T>, mission_id: u64) -> Result<FaultRecord, SimError>
where
    T: tonic::client::GrpcService<tonic::body::Body>,
    T::Error: Into<tonic::codegen::StdError>,
    T::ResponseBody: tonic::codegen::Body<Data = tonic::codegen::Bytes> + Send + 'static,
    <T::ResponseBody as tonic::codegen::Body>::Error: Into<tonic::codegen::StdError> + Send,
{
    let tasks = missions
        .list_tasks(pb::ListTasksRequest { mission_id, limit: 100_000, ..Default::default() })
        .await
        .map_err(|status| SimError::Rpc { what: "ListTasks", status })?
        .into_inner()
        .tasks;
    let robots = missions
        .list_robots(pb::ListRobotsRequest { mission_id })
        .await
        .map_err(|status| SimError::Rpc { what: "ListRobots", status })?
        .into_inner()
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
