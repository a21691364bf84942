//! The fleet runner: one mission, N simulated robots, until the reachable
//! free space is known.
//!
//! Time is discrete. In each step every robot, in a fixed order, moves one
//! cell, senses, and reports to the executive; the executive may replan
//! within that request. Because the robots take turns, the executive sees the
//! same requests in the same order on every run with the same seed, and the
//! run is reproducible, while each robot remains its own gRPC client.

use std::collections::BTreeMap;
use std::path::PathBuf;
use std::time::{Duration, Instant};

use serde::Serialize;
use tokio_util::sync::CancellationToken;
use tonic::Status;

use exploration_proto::v1 as pb;
use exploration_proto::v1::missions_client::MissionsClient;

use crate::robot::{Bidding, RobotError, RobotModel, SimRobot, TeamMap};
use crate::world::{StartChoice, World, WorldError};

/// Everything a run is made of.
#[derive(Debug, Clone)]
pub struct RunConfig {
    /// The map_server YAML of the world.
    pub map: PathBuf,
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
    /// Database of the embedded executive; `None` uses a temporary file.
    pub db: Option<PathBuf>,
    /// Simulation cell size, metres; `None` keeps the map's.
    pub cell_size: Option<f64>,
    /// The robots.
    pub model: RobotModel,
    /// Where the team starts.
    pub start: StartChoice,
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
}

impl RunConfig {
    /// A run of `robots` robots with `policy` on `map`, with default settings.
    pub fn new(map: impl Into<PathBuf>, robots: usize, policy: &str) -> Self {
        Self {
            map: map.into(),
            robots,
            policy: policy.to_owned(),
            params: BTreeMap::new(),
            seed: 1,
            server: None,
            db: None,
            cell_size: Some(0.1),
            model: RobotModel {
                sensor_range_m: 4.0,
                field_of_view_rad: std::f64::consts::TAU,
                speed_mps: 0.5,
                footprint_radius_m: 0.0,
            },
            start: StartChoice::Auto,
            max_steps: 50_000,
            stall_steps: 200,
            retry_budget: Duration::from_secs(120),
            bid_every: 5,
            progress: false,
        }
    }
}

/// What a run measured.
#[derive(Debug, Clone, Serialize, PartialEq)]
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
    /// Whether every reachable free cell became known.
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
    /// Cells sensed by more than one robot, as a share of the cells sensed.
    pub overlap: f64,
    /// Steps at which the assignment stream lagged behind a response.
    pub stream_lags: u64,
    /// Wall-clock seconds.
    pub wall_time_s: f64,
    /// Each robot's cells, in order (not serialized).
    #[serde(skip)]
    pub trajectories: Vec<Vec<exploration::grid::Cell>>,
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
}

/// An executive on loopback, owned by the run.
struct EmbeddedExecutive {
    url: String,
    stop: CancellationToken,
    task: tokio::task::JoinHandle<Result<(), coordinator::ServeError>>,
    _dir: Option<tempfile::TempDir>,
}

impl EmbeddedExecutive {
    async fn start(db: Option<PathBuf>) -> Result<Self, SimError> {
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
        // The fleet waits for every acknowledgement: a crash of this process
        // takes the fleet with it, so power-cut durability buys nothing here.
        config.durability = coordinator::Durability::Normal;
        let task = tokio::spawn(coordinator::run(listener, shutdown, config));
        Ok(Self { url: format!("http://{address}"), stop, task, _dir: dir })
    }

    async fn stop(self) -> Result<(), SimError> {
        self.stop.cancel();
        match self.task.await {
            Ok(Ok(())) => Ok(()),
            Ok(Err(e)) => Err(SimError::Executive(e.to_string())),
            Err(e) => Err(SimError::Executive(e.to_string())),
        }
    }
}

/// Runs one mission to the end.
pub async fn run(config: &RunConfig) -> Result<RunReport, SimError> {
    let world = World::load(&config.map, config.cell_size, config.start, config.seed)?;
    let embedded = match &config.server {
        Some(_) => None,
        None => Some(EmbeddedExecutive::start(config.db.clone()).await?),
    };
    let url = match (&config.server, &embedded) {
        (Some(url), _) => url.clone(),
        (None, Some(e)) => e.url.clone(),
        (None, None) => unreachable!("an executive was started"),
    };
    let result = run_against(config, &world, &url).await;
    if let Some(executive) = embedded {
        executive.stop().await?;
    }
    result
}

async fn run_against(config: &RunConfig, world: &World, url: &str) -> Result<RunReport, SimError> {
    let started = Instant::now();
    let channel = tonic::transport::Endpoint::from_shared(url.to_owned())
        .map_err(|e| SimError::Executive(format!("bad executive URL {url}: {e}")))?
        .connect_timeout(Duration::from_secs(5))
        .connect_lazy();
    let mut missions = MissionsClient::new(channel);
    let frame = world.frame;
    let mission = missions
        .create_mission(pb::CreateMissionRequest {
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
        })
        .await
        .map_err(|status| SimError::Rpc { what: "CreateMission", status })?
        .into_inner();
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
    let mut robots = Vec::with_capacity(config.robots);
    for i in 0..config.robots {
        robots.push(
            SimRobot::connect(
                url,
                mission.id,
                format!("robot-{i}"),
                world.start,
                world,
                config.model,
                bidding,
                config.retry_budget,
                stop.clone(),
            )
            .await?,
        );
    }
    let mut team = TeamMap::new(frame);
    let mut milestones: [Option<u64>; 4] = [None; 4];
    const LEVELS: [f64; 4] = [0.5, 0.9, 0.95, 1.0];
    let mut idle_steps = 0;
    let mut last_progress = (0, 0);
    let mut step = 0;
    let ended = loop {
        let mut any_task = false;
        let mut executive_done = false;
        for robot in &mut robots {
            let outcome = robot.step(world, &mut team).await?;
            any_task |= outcome.has_task;
            executive_done |= outcome.mission_completed;
        }
        let coverage = team.known_reachable as f64 / world.reachable_cells.max(1) as f64;
        for (slot, level) in milestones.iter_mut().zip(LEVELS) {
            if slot.is_none() && coverage >= level - 1e-12 {
                *slot = Some(step);
            }
        }
        if config.progress && step % 250 == 0 {
            eprintln!("step {step:>6}  coverage {:>5.1} %", 100.0 * coverage);
        }
        if team.known_reachable >= world.reachable_cells {
            break "every reachable free cell is known".to_owned();
        }
        if executive_done {
            break "the executive reports no frontier left".to_owned();
        }
        idle_steps = if any_task { 0 } else { idle_steps + 1 };
        if idle_steps >= config.stall_steps {
            break format!("no robot had a task for {idle_steps} steps");
        }
        if team.known_reachable > last_progress.0 {
            last_progress = (team.known_reachable, step);
        } else if step - last_progress.1 >= 10 * config.stall_steps {
            break format!("the team learnt nothing for {} steps", step - last_progress.1);
        }
        step += 1;
        if step >= config.max_steps {
            break format!("step limit {} reached", config.max_steps);
        }
    };
    let summary = missions
        .get_mission(pb::GetMissionRequest { mission_id: mission.id })
        .await
        .map_err(|status| SimError::Rpc { what: "GetMission", status })?
        .into_inner();
    let sensed = team.sensed_by.iter().filter(|&&n| n > 0).count();
    let overlapping = team.sensed_by.iter().filter(|&&n| n > 1).count();
    let coverage = team.known_reachable as f64 / world.reachable_cells.max(1) as f64;
    let report = RunReport {
        mission_id: mission.id,
        map: world.name.clone(),
        policy: config.policy.clone(),
        robots: config.robots,
        seed: config.seed,
        completed: team.known_reachable >= world.reachable_cells,
        ended,
        steps: step + 1,
        coverage,
        t50: milestones[0],
        t90: milestones[1],
        t95: milestones[2],
        t100: milestones[3],
        distance_per_robot: robots.iter().map(|r| r.distance_m).collect(),
        replans: summary.replans,
        map_updates: summary.map_updates,
        updates_acknowledged: robots.iter().map(|r| r.acknowledged_updates).sum(),
        reachable_cells: world.reachable_cells,
        cell_size: frame.resolution,
        overlap: if sensed == 0 { 0.0 } else { overlapping as f64 / sensed as f64 },
        stream_lags: robots.iter().map(|r| r.stream_lags).sum(),
        wall_time_s: started.elapsed().as_secs_f64(),
        trajectories: robots.iter().map(|r| r.trajectory.clone()).collect(),
    };
    Ok(report)
}
