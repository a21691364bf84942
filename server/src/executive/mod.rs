//! The executive: every mission's live state, kept in step with the store.
//!
//! Requests for one mission are serialized by that mission's lock, which
//! makes the executive deterministic for a given order of requests (the
//! simulator relies on it) and lets each operation be prepared, committed and
//! applied without interference. Policies run on the blocking pool, off the
//! async workers.

use std::collections::{BTreeMap, HashMap};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, RwLock};

use tokio::sync::{Mutex, watch};

use exploration::grid::OccupancyGrid;
use exploration::math::Point2;

use crate::domain::{
    Assignment, Bid, Heartbeat, MapUpdate, MissionEvent, MissionId, MissionRecord, MissionSpec, MissionState, RobotId,
    RobotRecord, RobotSpec, StoredSegmentation, TaskRecord, Timestamp,
};
use crate::error::Error;
use crate::store::{Changeset, Store, TaskFilter};
use exploration::policy::PolicyConfig;

mod mission;

use mission::Mission;

/// Limits and knobs of an executive.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ExecutiveSettings {
    /// Threads a replanning may use for cost maps.
    pub planner_threads: usize,
    /// Most missions at once.
    pub max_missions: usize,
    /// Most robots in one mission.
    pub max_robots_per_mission: usize,
    /// Most grid cells over all missions (memory bound).
    pub max_total_cells: u64,
}

impl Default for ExecutiveSettings {
    fn default() -> Self {
        Self {
            planner_threads: std::thread::available_parallelism().map_or(1, |n| n.get()),
            max_missions: 1_000,
            max_robots_per_mission: 1_000,
            max_total_cells: 400_000_000,
        }
    }
}

/// A mission with its live counters.
#[derive(Debug, Clone, PartialEq)]
pub struct MissionSummary {
    /// The stored record.
    pub record: MissionRecord,
    /// Registered robots.
    pub robots: usize,
    /// Known cells of the fused grid.
    pub known_cells: u64,
    /// Frontier cells of the fused grid.
    pub frontier_cells: u64,
}

/// A robot with its current target.
#[derive(Debug, Clone, PartialEq)]
pub struct RobotSummary {
    /// The stored record.
    pub record: RobotRecord,
    /// Where its current task leads.
    pub target: Option<Point2>,
}

/// What a map update led to.
#[derive(Debug, Clone, PartialEq)]
pub struct MapUpdateOutcome {
    /// The sequence number now applied.
    pub applied_seq: u64,
    /// The robot's assignment afterwards.
    pub assignment: Assignment,
    /// Frontier cells afterwards.
    pub frontier_cells: u64,
    /// The mission's state afterwards.
    pub mission_state: MissionState,
}

/// A copy of a mission's fused map.
#[derive(Debug, Clone)]
pub struct MapView {
    /// The fused grid.
    pub grid: OccupancyGrid,
    /// Frontier cell centres.
    pub frontier: Vec<Point2>,
    /// Robots and their targets.
    pub robots: Vec<RobotSummary>,
}

/// The exploration executive.
#[derive(Debug)]
pub struct Executive {
    store: Arc<dyn Store>,
    settings: ExecutiveSettings,
    missions: RwLock<BTreeMap<MissionId, Arc<Mutex<Mission>>>>,
    robot_missions: RwLock<HashMap<RobotId, MissionId>>,
    next_task_id: AtomicU64,
    total_cells: AtomicU64,
}

impl Executive {
    /// Loads every mission from the store, where it was.
    pub async fn open(store: Arc<dyn Store>, settings: ExecutiveSettings) -> Result<Self, Error> {
        let mut missions = BTreeMap::new();
        let mut robot_missions = HashMap::new();
        let mut total_cells = 0u64;
        for record in store.missions().await? {
            let id = record.id;
            let robots = store.robots(id).await?;
            let patches = store.patches(id).await?;
            let open_tasks = store.open_tasks(id).await?;
            tracing::info!(
                mission = id,
                robots = robots.len(),
                patches = patches.len(),
                open_tasks = open_tasks.len(),
                "restoring mission"
            );
            for robot in &robots {
                robot_missions.insert(robot.id, id);
            }
            let mut bids = Vec::new();
            for robot in &robots {
                bids.push((robot.id, store.bids(robot.id).await?));
            }
            total_cells += record.spec.frame.len() as u64;
            let mut mission = Mission::restore(record, robots, patches, open_tasks)?;
            for (robot, robot_bids) in bids {
                mission.set_bids(robot, &robot_bids);
            }
            missions.insert(id, Arc::new(Mutex::new(mission)));
        }
        let next_task_id = store.max_task_id().await?;
        Ok(Self {
            store,
            settings,
            missions: RwLock::new(missions),
            robot_missions: RwLock::new(robot_missions),
            next_task_id: AtomicU64::new(next_task_id),
            total_cells: AtomicU64::new(total_cells),
        })
    }

    fn mission_handle(&self, id: MissionId) -> Result<Arc<Mutex<Mission>>, Error> {
        let missions = self.missions.read().unwrap_or_else(|e| e.into_inner());
        missions
            .get(&id)
            .cloned()
            .ok_or_else(|| Error::NotFound(format!("mission {id} does not exist; ListMissions shows the missions")))
    }

    fn mission_of_robot(&self, robot: RobotId) -> Result<Arc<Mutex<Mission>>, Error> {
        let mission = {
            let index = self.robot_missions.read().unwrap_or_else(|e| e.into_inner());
            index.get(&robot).copied()
        };
        match mission {
            Some(m) => self.mission_handle(m),
            None => Err(Error::NotFound(format!("robot {robot} does not exist; register it with RegisterRobot first"))),
        }
    }

    fn summary(mission: &Mission) -> MissionSummary {
        MissionSummary {
            record: mission.record().clone(),
            robots: mission.robot_count(),
            known_cells: mission.known_cells(),
            frontier_cells: mission.frontier_cells() as u64,
        }
    }

    /// Creates a mission.
    pub async fn create_mission(&self, spec: MissionSpec) -> Result<MissionSummary, Error> {
        let cells = spec.frame.len() as u64;
        {
            let missions = self.missions.read().unwrap_or_else(|e| e.into_inner());
            if missions.len() >= self.settings.max_missions {
                return Err(Error::ResourceExhausted(format!(
                    "this executive already holds {} missions, its limit",
                    missions.len()
                )));
            }
        }
        let total = self.total_cells.load(Ordering::Relaxed);
        if total + cells > self.settings.max_total_cells {
            return Err(Error::ResourceExhausted(format!(
                "a {cells}-cell map would take this executive past its limit of {} cells over all missions ({} in use)",
                self.settings.max_total_cells, total
            )));
        }
        let record = self.store.create_mission(&spec, Timestamp::now()).await?;
        tracing::info!(mission = record.id, policy = record.spec.policy.name(), cells, "mission created");
        let mission = Mission::new(record.clone());
        let summary = Self::summary(&mission);
        self.total_cells.fetch_add(cells, Ordering::Relaxed);
        self.missions.write().unwrap_or_else(|e| e.into_inner()).insert(record.id, Arc::new(Mutex::new(mission)));
        Ok(summary)
    }

    /// One mission.
    pub async fn mission(&self, id: MissionId) -> Result<MissionSummary, Error> {
        let handle = self.mission_handle(id)?;
        let mission = handle.lock().await;
        Ok(Self::summary(&mission))
    }

    /// Every mission, oldest first.
    pub async fn missions(&self) -> Vec<MissionSummary> {
        let handles: Vec<_> = self.missions.read().unwrap_or_else(|e| e.into_inner()).values().cloned().collect();
        let mut out = Vec::with_capacity(handles.len());
        for handle in handles {
            out.push(Self::summary(&*handle.lock().await));
        }
        out
    }

    /// Registers a robot, or resumes the robot of that name.
    pub async fn register_robot(&self, mission_id: MissionId, spec: RobotSpec) -> Result<(RobotRecord, bool), Error> {
        let handle = self.mission_handle(mission_id)?;
        let mut mission = handle.lock().await;
        if let Some(existing) = mission.robot_by_name(&spec.name) {
            let mut resumed = existing.clone();
            resumed.capabilities = spec.capabilities;
            resumed.last_seen = Timestamp::now();
            let changes = Changeset { robots: vec![resumed.clone()], ..Changeset::default() };
            self.store.commit(&changes).await?;
            mission.apply(changes);
            tracing::info!(mission = mission_id, robot = resumed.id, name = %resumed.name, "robot resumed");
            return Ok((resumed, true));
        }
        if mission.robot_count() >= self.settings.max_robots_per_mission {
            return Err(Error::ResourceExhausted(format!(
                "mission {mission_id} already has {} robots, the limit",
                mission.robot_count()
            )));
        }
        if mission.record().spec.frame.cell_from_world(&spec.pose.position).is_none() {
            return Err(Error::InvalidArgument(format!(
                "pose ({:.3}, {:.3}) lies outside the map of mission {mission_id}",
                spec.pose.position.x, spec.pose.position.y
            )));
        }
        let record = self.store.create_robot(mission_id, &spec, Timestamp::now()).await?;
        tracing::info!(mission = mission_id, robot = record.id, name = %record.name, "robot registered");
        mission.insert_robot(record.clone());
        self.robot_missions.write().unwrap_or_else(|e| e.into_inner()).insert(record.id, mission_id);
        Ok((record, false))
    }

    /// Applies a robot's report, then replans if it asked for it.
    pub async fn heartbeat(&self, robot_id: RobotId, heartbeat: Heartbeat) -> Result<Assignment, Error> {
        let handle = self.mission_of_robot(robot_id)?;
        let mut mission = handle.lock().await;
        let peers = heartbeat.peers.clone();
        let changes = mission.prepare_heartbeat(robot_id, heartbeat, Timestamp::now())?;
        self.store.commit(&changes).await?;
        mission.apply(changes);
        if let Some(peers) = peers {
            mission.set_peers(robot_id, peers);
        }
        self.replan_if_due(&mut mission).await?;
        mission.assignment(robot_id)
    }

    /// Applies a robot's map update exactly once, then replans if due.
    pub async fn update_map(&self, robot_id: RobotId, update: MapUpdate) -> Result<MapUpdateOutcome, Error> {
        let handle = self.mission_of_robot(robot_id)?;
        let mut mission = handle.lock().await;
        let seq = update.seq;
        let peers = update.peers.clone();
        let changes = mission.prepare_update(robot_id, update, Timestamp::now())?;
        // Durable before it is applied or acknowledged.
        self.store.commit(&changes).await?;
        mission.apply(changes);
        if let Some(peers) = peers {
            mission.set_peers(robot_id, peers);
        }
        self.replan_if_due(&mut mission).await?;
        Ok(MapUpdateOutcome {
            applied_seq: seq,
            assignment: mission.assignment(robot_id)?,
            frontier_cells: mission.frontier_cells() as u64,
            mission_state: mission.record().state,
        })
    }

    /// Replaces a robot's bids; the `simmons` policy replans on them.
    pub async fn submit_bids(&self, robot_id: RobotId, bids: Vec<Bid>) -> Result<(usize, Assignment), Error> {
        let handle = self.mission_of_robot(robot_id)?;
        let mut mission = handle.lock().await;
        mission.robot(robot_id)?;
        self.store.replace_bids(robot_id, &bids, Timestamp::now()).await?;
        mission.set_bids(robot_id, &bids);
        self.replan_if_due(&mut mission).await?;
        Ok((bids.len(), mission.assignment(robot_id)?))
    }

    /// Changes a running mission's policy; the next replanning uses it.
    pub async fn set_policy(
        &self,
        mission_id: MissionId,
        policy: PolicyConfig,
        actor: &str,
        reason: &str,
    ) -> Result<MissionSummary, Error> {
        let handle = self.mission_handle(mission_id)?;
        let mut mission = handle.lock().await;
        let changes = mission.prepare_policy(policy, actor, reason, Timestamp::now());
        self.store.commit(&changes).await?;
        mission.apply(changes);
        tracing::info!(mission = mission_id, policy = mission.record().spec.policy.name(), actor, "policy changed");
        self.replan_if_due(&mut mission).await?;
        Ok(Self::summary(&mission))
    }

    /// A mission's events, oldest first.
    pub async fn events(&self, mission_id: MissionId) -> Result<Vec<MissionEvent>, Error> {
        self.mission_handle(mission_id)?;
        Ok(self.store.events(mission_id).await?)
    }

    /// A mission's latest segmentation, if one was computed.
    pub async fn segmentation(&self, mission_id: MissionId) -> Result<Option<StoredSegmentation>, Error> {
        self.mission_handle(mission_id)?;
        Ok(self.store.segmentation(mission_id).await?)
    }

    /// A robot's current assignment.
    pub async fn assignment(&self, robot_id: RobotId) -> Result<Assignment, Error> {
        let handle = self.mission_of_robot(robot_id)?;
        let mission = handle.lock().await;
        mission.assignment(robot_id)
    }

    /// A receiver of a robot's assignments: holds the current one, then sees every change.
    pub async fn watch(&self, robot_id: RobotId) -> Result<watch::Receiver<Assignment>, Error> {
        let handle = self.mission_of_robot(robot_id)?;
        let mission = handle.lock().await;
        mission.watch(robot_id)
    }

    /// A mission's robots with their targets.
    pub async fn robots(&self, mission_id: MissionId) -> Result<Vec<RobotSummary>, Error> {
        let handle = self.mission_handle(mission_id)?;
        let mission = handle.lock().await;
        Ok(Self::robot_summaries(&mission))
    }

    fn robot_summaries(mission: &Mission) -> Vec<RobotSummary> {
        mission.robots().map(|r| RobotSummary { record: r.clone(), target: mission.target_of(r) }).collect()
    }

    /// Tasks with their transitions, newest first.
    pub async fn tasks(&self, filter: TaskFilter) -> Result<Vec<TaskRecord>, Error> {
        let handle = self.mission_handle(filter.mission_id)?;
        if let Some(robot) = filter.robot_id {
            let mission = handle.lock().await;
            mission.robot(robot).map_err(|_| {
                Error::NotFound(format!("robot {robot} does not exist in mission {}", filter.mission_id))
            })?;
        }
        Ok(self.store.tasks(filter).await?)
    }

    /// A copy of a mission's fused map.
    pub async fn map(&self, mission_id: MissionId) -> Result<MapView, Error> {
        let handle = self.mission_handle(mission_id)?;
        let mission = handle.lock().await;
        let frame = mission.record().spec.frame;
        Ok(MapView {
            grid: mission.grid().clone(),
            frontier: mission.frontier().cells().into_iter().map(|c| frame.world_from_cell(c)).collect(),
            robots: Self::robot_summaries(&mission),
        })
    }

    /// Replans the mission if a trigger fired, and commits the outcome.
    async fn replan_if_due(&self, mission: &mut Mission) -> Result<(), Error> {
        let now = tokio::time::Instant::now();
        let Some(reason) = mission.replan_reason(now) else {
            return Ok(());
        };
        let job = mission.planning_job(self.settings.planner_threads);
        let started = std::time::Instant::now();
        let outcome = tokio::task::spawn_blocking(move || job.run())
            .await
            .map_err(|e| Error::Internal(format!("planner task failed: {e}")))?;
        let planning_ms = started.elapsed().as_secs_f64() * 1e3;
        let changes = mission.prepare_plan(&outcome, &reason, Timestamp::now(), &self.next_task_id);
        self.store.commit(&changes).await?;
        let reassigned = changes.new_tasks.len();
        mission.apply(changes);
        mission.mark_replanned(now);
        tracing::debug!(
            mission = mission.record().id,
            %reason,
            planning_ms,
            reassigned,
            replans = mission.record().replans,
            "replanned"
        );
        Ok(())
    }
}
