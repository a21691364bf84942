//! The executive: every mission's live state, kept in step with the store.
//!
//! Requests for one mission are serialized by that mission's lock, which
//! makes the executive deterministic for a given order of requests (the
//! simulator relies on it) and lets each operation be prepared, committed and
//! applied without interference; a map update releases the lock while its
//! write is made durable ([`writer`]). Policies run on the planner's
//! threads, off the async workers.

use std::collections::{BTreeMap, HashMap};
use std::sync::atomic::AtomicU64;
use std::sync::{Arc, RwLock};

use crate::clock::Clock;
use crate::domain::{
    Assignment, Bid, Heartbeat, MapUpdate, MissionId, MissionSpec, MissionState, RobotId, RobotRecord, RobotSpec,
    Timestamp,
};
use crate::error::Error;
use crate::store::{Changeset, Store};

mod mission;
mod operator;
mod ownership;
mod planner;
mod upkeep;
mod views;
mod writer;

pub use ownership::{ReplicaSettings, keep_leases_until};
pub use views::{MapChanges, MapView, MissionSummary, RobotSummary};

use mission::Mission;
use planner::{MissionCell, Planner, PlannerSettings};
use writer::Writer;

use crate::metrics::Metrics;

/// Limits and knobs of an executive.
#[derive(Debug, Clone)]
pub struct ExecutiveSettings {
    /// Threads a replanning may use for cost maps.
    pub planner_threads: usize,
    /// Plans made off the request path at once, and the threads one of them
    /// may use when it is the only one (the others take one each). Fewer
    /// than the cores, so that requests keep a core while missions plan:
    /// the planning threads' low priority does not protect the requests on
    /// every host (it did not in this project's 2-core sandbox).
    pub background_planner_threads: usize,
    /// CPU the planning threads may use on average, in cores; `None`: as
    /// much as they can get. Under a CPU limit (a container's quota) a plan
    /// that spends a period's quota at once makes every request wait for
    /// the next period; a budget below the limit spreads the plans out.
    pub planner_cpu: Option<f64>,
    /// Most missions at once.
    pub max_missions: usize,
    /// Most robots in one mission.
    pub max_robots_per_mission: usize,
    /// Most grid cells over all missions (memory bound).
    pub max_total_cells: u64,
    /// What leases, stalls and replanning intervals are timed by.
    pub clock: Clock,
    /// Most robot requests waiting for one mission; more are refused with
    /// RESOURCE_EXHAUSTED.
    pub max_queued_per_mission: usize,
    /// Missions planned off the request path replan for map news (frontier
    /// change, distance travelled, time) at most this often; a demand (a
    /// robot arrived or failed, joined, ...) is planned at once.
    pub min_plan_interval: std::time::Duration,
    /// Replicas sharing the database: this one's name, address and leases;
    /// `None`: the only executive on its database, holding every mission.
    pub replica: Option<ReplicaSettings>,
}

impl Default for ExecutiveSettings {
    fn default() -> Self {
        Self {
            planner_threads: cores(),
            background_planner_threads: cores().saturating_sub(1).max(1),
            planner_cpu: None,
            max_missions: 1_000,
            max_robots_per_mission: 1_000,
            max_total_cells: 400_000_000,
            clock: Clock::default(),
            max_queued_per_mission: 64,
            min_plan_interval: std::time::Duration::from_secs(1),
            replica: None,
        }
    }
}

/// Cores this process may run on.
fn cores() -> usize {
    std::thread::available_parallelism().map_or(1, |n| n.get())
}

/// A backup copy of the store on disk; removed when dropped.
#[derive(Debug)]
pub struct BackupFile(std::path::PathBuf);

impl BackupFile {
    /// The copy.
    pub fn path(&self) -> &std::path::Path {
        &self.0
    }
}

impl Drop for BackupFile {
    fn drop(&mut self) {
        if let Err(e) = std::fs::remove_file(&self.0)
            && e.kind() != std::io::ErrorKind::NotFound
        {
            tracing::warn!(path = %self.0.display(), error = %e, "cannot remove a backup copy");
        }
    }
}

/// The missions and grid cells an executive holds, against its limits.
#[derive(Debug)]
struct Usage(std::sync::Mutex<(usize, u64)>);

impl Usage {
    fn new(missions: usize, cells: u64) -> Self {
        Self(std::sync::Mutex::new((missions, cells)))
    }

    /// Takes one mission of `cells` cells, or says which limit it would pass.
    fn reserve(&self, cells: u64, settings: &ExecutiveSettings) -> Result<(), Error> {
        let mut usage = self.0.lock().unwrap_or_else(|e| e.into_inner());
        let (missions, total) = *usage;
        if missions >= settings.max_missions {
            return Err(Error::ResourceExhausted(format!(
                "this executive already holds {missions} missions, its limit"
            )));
        }
        if total + cells > settings.max_total_cells {
            return Err(Error::ResourceExhausted(format!(
                "a {cells}-cell map would take this executive past its limit of {} cells over all missions \
                 ({total} in use)",
                settings.max_total_cells
            )));
        }
        *usage = (missions + 1, total + cells);
        Ok(())
    }

    /// Gives back a reservation whose mission was not made.
    /// A mission loaded from the store, whatever the limits.
    fn add(&self, cells: u64) {
        let mut usage = self.0.lock().unwrap_or_else(|e| e.into_inner());
        *usage = (usage.0 + 1, usage.1 + cells);
    }

    fn release(&self, cells: u64) {
        let mut usage = self.0.lock().unwrap_or_else(|e| e.into_inner());
        *usage = (usage.0.saturating_sub(1), usage.1.saturating_sub(cells));
    }
}

/// How often leases and stalls are checked.
pub const SWEEP_PERIOD: std::time::Duration = std::time::Duration::from_millis(500);

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

/// The exploration executive.
#[derive(Debug)]
pub struct Executive {
    store: Arc<dyn Store>,
    writer: Writer,
    settings: ExecutiveSettings,
    missions: RwLock<BTreeMap<MissionId, Arc<MissionCell>>>,
    robot_missions: RwLock<HashMap<RobotId, MissionId>>,
    next_task_id: Arc<AtomicU64>,
    planner: Arc<Planner>,
    metrics: Arc<Metrics>,
    next_region_id: AtomicU64,
    usage: Usage,
    /// Each robot's token hash.
    tokens: RwLock<HashMap<RobotId, String>>,
    /// The missions held, when replicas share the database.
    ownership: Option<ownership::Ownership>,
}

impl Executive {
    /// Loads every mission from the store, where it was; as one of several
    /// replicas ([`ExecutiveSettings::replica`]), only those it claims
    /// (the lease keeper claims the missions nobody holds).
    pub async fn open(
        store: Arc<dyn Store>,
        settings: ExecutiveSettings,
        metrics: Arc<Metrics>,
    ) -> Result<Self, Error> {
        let writer = Writer::new(Arc::clone(&store), settings.clock.clone(), Arc::clone(&metrics));
        let ownership = settings.replica.clone().map(ownership::Ownership::new);
        // Identities: after the largest given; a replica gives them from
        // blocks of its own, so that replicas never give the same one.
        let (next_task_id, next_region_id) = match &ownership {
            None => (store.max_task_id().await?, store.max_region_id().await?),
            Some(ownership) => {
                let block = store.reserve_id_block(&ownership.settings.claimant.id, Timestamp::now()).await?;
                let first = block
                    .checked_mul(1 << 32)
                    .ok_or_else(|| Error::Internal(format!("identity block {block} is past the last one (2^31)")))?;
                (first, first)
            }
        };
        let next_task_id = Arc::new(AtomicU64::new(next_task_id));
        let planner = Planner::new(
            writer.clone(),
            settings.clock.clone(),
            PlannerSettings::from(&settings),
            Arc::clone(&next_task_id),
            Arc::clone(&metrics),
        );
        let tokens = store.robot_tokens().await?.into_iter().collect();
        let executive = Self {
            store: Arc::clone(&store),
            writer,
            settings,
            missions: RwLock::default(),
            robot_missions: RwLock::default(),
            next_task_id,
            planner,
            metrics,
            next_region_id: AtomicU64::new(next_region_id),
            usage: Usage::new(0, 0),
            tokens: RwLock::new(tokens),
            ownership,
        };
        if executive.ownership.is_none() {
            for record in store.missions().await? {
                let cells = record.spec.frame.len() as u64;
                let mission = executive.writer.load(record).await?;
                executive.usage.add(cells);
                executive.start_holding(Arc::new(MissionCell::new(mission))).await;
            }
        }
        Ok(executive)
    }

    /// Starts acting for a mission: its robots are found through it, its
    /// planner runs, and a mission planned off the request path replans
    /// now, not at the next request.
    async fn start_holding(&self, cell: Arc<MissionCell>) {
        let mut mission = cell.lock().await;
        let id = mission.record().id;
        {
            let mut index = self.robot_missions.write().unwrap_or_else(|e| e.into_inner());
            for robot in mission.robots() {
                index.insert(robot.id, id);
            }
        }
        self.missions.write().unwrap_or_else(|e| e.into_inner()).insert(id, Arc::clone(&cell));
        self.planner.start(Arc::clone(&cell));
        if !mission.record().spec.lockstep {
            self.planner.after_change(&cell, &mut mission).await;
        }
    }

    /// Lets go of a mission: out of the maps, its planner stopped, its slot
    /// and cells given back. Its robots' streams close once the requests
    /// under way end.
    fn forget_mission(&self, id: MissionId) {
        let cell = self.missions.write().unwrap_or_else(|e| e.into_inner()).remove(&id);
        self.robot_missions.write().unwrap_or_else(|e| e.into_inner()).retain(|_, m| *m != id);
        if let Some(cell) = cell {
            cell.retire();
            self.usage.release(cell.cells());
        }
    }

    /// Whether this executive holds (acts for) the mission.
    pub fn holds(&self, id: MissionId) -> bool {
        self.held_mission(id).is_some()
    }

    /// A mission this executive holds.
    fn held_mission(&self, id: MissionId) -> Option<Arc<MissionCell>> {
        self.missions.read().unwrap_or_else(|e| e.into_inner()).get(&id).cloned()
    }

    /// A mission, claimed first (or pointed to) when another replica may hold it.
    async fn mission_handle(&self, id: MissionId) -> Result<Arc<MissionCell>, Error> {
        if let Some(cell) = self.held_mission(id) {
            return Ok(cell);
        }
        match &self.ownership {
            Some(ownership) => self.claim_or_point(ownership, id).await,
            None => Err(Error::NotFound(format!("mission {id} does not exist; ListMissions shows the missions"))),
        }
    }

    /// A robot's mission, claimed first (or pointed to) when another replica may hold it.
    async fn mission_of_robot(&self, robot: RobotId) -> Result<Arc<MissionCell>, Error> {
        let mission = {
            let index = self.robot_missions.read().unwrap_or_else(|e| e.into_inner());
            index.get(&robot).copied()
        };
        let mission = match (mission, &self.ownership) {
            (Some(m), _) => Some(m),
            (None, Some(_)) => self.store.robot_mission(robot).await?,
            (None, None) => None,
        };
        match mission {
            Some(m) => self.mission_handle(m).await,
            None => Err(Error::NotFound(format!("robot {robot} does not exist; register it with RegisterRobot first"))),
        }
    }

    /// A mission for a robot's request, unless too many already wait for it.
    async fn lock_for_request<'a>(&self, cell: &'a MissionCell) -> Result<tokio::sync::MutexGuard<'a, Mission>, Error> {
        let asked = std::time::Instant::now();
        let locked = cell.lock_for_request(self.settings.max_queued_per_mission).await.inspect_err(|_| {
            self.metrics.shed("mission queue full");
        })?;
        self.metrics.mission_wait.observe(asked.elapsed().as_secs_f64());
        Ok(locked)
    }

    /// The stored hash of a robot's token, if it has one.
    pub fn robot_token_hash(&self, robot: RobotId) -> Option<String> {
        self.tokens.read().unwrap_or_else(|e| e.into_inner()).get(&robot).cloned()
    }

    /// Creates a mission.
    pub async fn create_mission(&self, spec: MissionSpec) -> Result<MissionSummary, Error> {
        let cells = spec.frame.len() as u64;
        // Reserved before the store is asked, so that simultaneous calls
        // cannot all pass the check; given back if the mission is not made.
        self.usage.reserve(cells, &self.settings)?;
        let now = Timestamp::now();
        let (_claiming, created) = match &self.ownership {
            // A replica's mission is created with its lease, in one
            // transaction: no other replica ever sees it unclaimed. The
            // claim lock is held until the mission is in this executive's
            // map: the lease keeper must not hand it on before that.
            Some(ownership) => {
                let claiming = ownership.claiming().await;
                let ReplicaSettings { claimant, lease, .. } = &ownership.settings;
                let created = self.store.create_claimed_mission(&spec, now, claimant, *lease).await;
                (Some(claiming), created.map(|(m, l)| (m, Some(l))))
            }
            None => (None, self.store.create_mission(&spec, now).await.map(|m| (m, None))),
        };
        let (record, lease) = match created {
            Ok(created) => created,
            Err(e) => {
                self.usage.release(cells);
                return Err(e.into());
            }
        };
        tracing::info!(mission = record.id, policy = record.spec.policy.name(), cells, "mission created");
        let mut mission = Mission::new(record.clone(), self.settings.clock.now());
        if let (Some(ownership), Some(lease)) = (&self.ownership, lease) {
            ownership.hold_new(&mut mission, &lease);
        }
        let summary = Self::summary(&mission);
        let cell = Arc::new(MissionCell::new(mission));
        self.planner.start(Arc::clone(&cell));
        self.missions.write().unwrap_or_else(|e| e.into_inner()).insert(record.id, cell);
        Ok(summary)
    }

    /// The robot of that name in a mission, if there is one.
    pub async fn robot_named(&self, mission_id: MissionId, name: &str) -> Result<Option<RobotId>, Error> {
        let handle = self.mission_handle(mission_id).await?;
        let mission = handle.lock().await;
        Ok(mission.robot_by_name(name).map(|r| r.id))
    }

    /// Registers a robot, or resumes the robot of that name; returns it, a
    /// new token for it, and whether it was resumed.
    pub async fn register_robot(
        &self,
        mission_id: MissionId,
        spec: RobotSpec,
    ) -> Result<(RobotRecord, String, bool), Error> {
        let handle = self.mission_handle(mission_id).await?;
        let mut mission = handle.lock().await;
        if mission.is_deleted() {
            return Err(Error::NotFound(format!("mission {mission_id} was deleted")));
        }
        if let Some(existing) = mission.robot_by_name(&spec.name) {
            let mut resumed = existing.clone();
            resumed.capabilities = spec.capabilities;
            resumed.last_seen = Timestamp::now();
            resumed.lost = false;
            let secret = crate::auth::RobotSecret::new()?;
            let hash = secret.token_hash(resumed.id);
            // The new token and the record in one commit: a robot is never
            // left with a token it was not given.
            let changes = Changeset {
                robots: vec![resumed.clone()],
                robot_tokens: vec![(resumed.id, hash.clone())],
                ..Changeset::default()
            };
            let changes = self.writer.write(&mut mission, changes).await?;
            self.tokens.write().unwrap_or_else(|e| e.into_inner()).insert(resumed.id, hash);
            mission.apply(changes);
            let token = secret.token(resumed.id);
            mission.heard_from(resumed.id, self.settings.clock.now());
            tracing::info!(mission = mission_id, robot = resumed.id, name = %resumed.name, "robot resumed");
            return Ok((resumed, token, true));
        }
        if mission.robot_count() >= self.settings.max_robots_per_mission {
            return Err(Error::ResourceExhausted(format!(
                "mission {mission_id} already has {} robots, the limit",
                mission.robot_count()
            )));
        }
        if mission.record().spec.frame.cell_from_world(&spec.pose.position).is_none() {
            return Err(Error::InvalidArgument(format!(
                "pose {} lies outside the map of mission {mission_id}",
                crate::validate::Place(spec.pose.position)
            )));
        }
        // The token names the robot, whose identity the store gives inside
        // the transaction that stores the token's hash.
        let secret = crate::auth::RobotSecret::new()?;
        let record = self
            .store
            .create_robot(mission_id, &spec, &|id| secret.token_hash(id), Timestamp::now(), mission.fence())
            .await?;
        let token = secret.token(record.id);
        self.tokens.write().unwrap_or_else(|e| e.into_inner()).insert(record.id, secret.token_hash(record.id));
        tracing::info!(mission = mission_id, robot = record.id, name = %record.name, "robot registered");
        mission.insert_robot(record.clone(), self.settings.clock.now());
        self.robot_missions.write().unwrap_or_else(|e| e.into_inner()).insert(record.id, mission_id);
        Ok((record, token, false))
    }

    /// Applies a robot's report, then replans if it asked for it.
    pub async fn heartbeat(&self, robot_id: RobotId, heartbeat: Heartbeat) -> Result<Assignment, Error> {
        let handle = self.mission_of_robot(robot_id).await?;
        let mut mission = self.lock_for_request(&handle).await?;
        let peers = heartbeat.peers.clone();
        let changes = mission.prepare_heartbeat(robot_id, heartbeat, Timestamp::now())?;
        // A task's new state is applied once queued and answered once
        // durable, as map updates are: written under the mission's lock,
        // the transitions every new target sets off kept the mission's other
        // requests waiting for the disk (docs/benchmarks.md).
        let queued = if mission.only_liveness(&changes) {
            // Where the robot is and that it lives: written behind, with the
            // next sweep (see `Mission::apply_unsaved`).
            mission.apply_unsaved(changes);
            None
        } else {
            Some(self.writer.queue_and_apply(&mut mission, changes).await?)
        };
        mission.heard_from(robot_id, self.settings.clock.now());
        if let Some(peers) = peers {
            mission.set_peers(robot_id, peers);
        }
        self.planner.after_change(&handle, &mut mission).await;
        let Some(queued) = queued else { return mission.assignment_told(robot_id) };
        let assignment = mission.assignment(robot_id);
        drop(mission);
        self.writer.durable(queued, &handle).await?;
        assignment
    }

    /// Applies a robot's map update exactly once, then replans if due.
    pub async fn update_map(&self, robot_id: RobotId, update: MapUpdate) -> Result<MapUpdateOutcome, Error> {
        let handle = self.mission_of_robot(robot_id).await?;
        let mut mission = self.lock_for_request(&handle).await?;
        let seq = update.seq;
        let peers = update.peers.clone();
        let changes = mission.prepare_update(robot_id, update, Timestamp::now())?;
        // Applied once queued, acknowledged once durable (see `writer`).
        let queued = self.writer.queue_and_apply(&mut mission, changes).await?;
        mission.heard_from(robot_id, self.settings.clock.now());
        if let Some(peers) = peers {
            mission.set_peers(robot_id, peers);
        }
        self.planner.after_change(&handle, &mut mission).await;
        let assignment = mission.assignment(robot_id);
        let (frontier_cells, mission_state) = (mission.frontier_cells() as u64, mission.record().state);
        drop(mission);
        self.writer.durable(queued, &handle).await?;
        Ok(MapUpdateOutcome { applied_seq: seq, assignment: assignment?, frontier_cells, mission_state })
    }

    /// Replaces a robot's bids; the `simmons` policy replans on them.
    pub async fn submit_bids(&self, robot_id: RobotId, bids: Vec<Bid>) -> Result<(usize, Assignment), Error> {
        let handle = self.mission_of_robot(robot_id).await?;
        let mut mission = self.lock_for_request(&handle).await?;
        mission.check_bids(robot_id, &bids)?;
        let changes =
            Changeset { bids: Some((robot_id, bids.clone())), at: Some(Timestamp::now()), ..Changeset::default() };
        self.writer.write(&mut mission, changes).await?;
        mission.set_bids(robot_id, &bids);
        mission.mark_bids_fresh(robot_id);
        mission.heard_from(robot_id, self.settings.clock.now());
        self.planner.after_change(&handle, &mut mission).await;
        Ok((bids.len(), mission.assignment(robot_id)?))
    }

    /// Makes a changeset durable, then applies it to the mission in memory:
    /// the order every change follows, so that nothing acknowledged is lost.
    async fn commit(&self, mission: &mut Mission, changes: Changeset) -> Result<(), Error> {
        let changes = self.writer.write(mission, changes).await?;
        mission.apply(changes);
        Ok(())
    }
}
