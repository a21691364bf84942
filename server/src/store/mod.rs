//! Persistence of missions, robots, the map update log, tasks and bids.
//!
//! The executive talks to a [`Store`] only; SQL lives behind it, in
//! [`sqlite`]. Every write is a [`Changeset`] committed in one transaction,
//! so a crash leaves either all of an operation or none of it. A PostgreSQL
//! backend implements the same trait.

use async_trait::async_trait;

use crate::domain::{
    Bid, BlacklistEntry, Leftover, MissionEvent, MissionId, MissionRecord, MissionSpec, MissionState, Region, RobotId,
    RobotRecord, RobotSpec, StoredSegmentation, TaskId, TaskKind, TaskRecord, TaskState, Timestamp, Transition,
};
use exploration::fusion::Patch;
use exploration::grid::Cell;
use exploration::policy::PolicyConfig;

pub mod sqlite;

pub use sqlite::SqliteStore;

/// Why the store failed. Never shown to clients; logged once by the service.
#[derive(Debug, thiserror::Error)]
pub enum StoreError {
    /// The database refused or failed.
    #[error("database error: {0}")]
    Database(#[from] sqlx::Error),
    /// Migrations could not be applied.
    #[error("migration error: {0}")]
    Migrate(#[from] sqlx::migrate::MigrateError),
    /// A stored value does not parse.
    #[error("corrupt record: {0}")]
    Corrupt(String),
}

/// A mission's counters and state, as the executive last set them.
#[derive(Debug, Clone, PartialEq)]
pub struct MissionCounters {
    /// The mission.
    pub id: MissionId,
    /// Its state.
    pub state: MissionState,
    /// Replannings so far.
    pub replans: u64,
    /// Map updates applied so far.
    pub map_updates: u64,
    /// Paused by an operator.
    pub paused: bool,
    /// The frontier left at completion.
    pub leftovers: Vec<Leftover>,
}

/// A task's change of state.
#[derive(Debug, Clone, PartialEq)]
pub struct TaskChange {
    /// The task.
    pub task_id: TaskId,
    /// Its new state.
    pub state: TaskState,
    /// The transition to record.
    pub transition: Transition,
}

/// A patch of one robot's map, as logged.
#[derive(Debug, Clone, PartialEq)]
pub struct LoggedPatch {
    /// Whose map.
    pub robot_id: RobotId,
    /// The update it came with.
    pub seq: u64,
    /// The cells.
    pub patch: Patch,
}

/// Everything one operation writes, committed atomically.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Changeset {
    /// The mission's counters, when they changed.
    pub mission: Option<MissionCounters>,
    /// Robots whose records changed, written whole.
    pub robots: Vec<RobotRecord>,
    /// Tasks created, with their first transition in `transitions`.
    pub new_tasks: Vec<TaskRecord>,
    /// Task state changes.
    pub task_changes: Vec<TaskChange>,
    /// Map patches to append to the log.
    pub patches: Vec<LoggedPatch>,
    /// The mission's new policy, when it changed.
    pub policy: Option<(MissionId, PolicyConfig)>,
    /// Mission events to record.
    pub events: Vec<MissionEvent>,
    /// The mission's new segmentation.
    pub segmentation: Option<(MissionId, StoredSegmentation)>,
    /// Targets blacklisted for robots.
    pub blacklisted: Vec<BlacklistEntry>,
    /// Blacklist entries that expired: (robot, cell).
    pub unblacklisted: Vec<(RobotId, Cell)>,
    /// Regions forbidden.
    pub forbidden: Vec<Region>,
    /// Forbidden regions allowed again (at the changeset's time).
    pub allowed: Vec<u64>,
    /// When.
    pub at: Option<Timestamp>,
}

impl Changeset {
    /// Whether there is nothing to write.
    pub fn is_empty(&self) -> bool {
        self.mission.is_none()
            && self.robots.is_empty()
            && self.new_tasks.is_empty()
            && self.task_changes.is_empty()
            && self.patches.is_empty()
            && self.policy.is_none()
            && self.events.is_empty()
            && self.segmentation.is_none()
            && self.blacklisted.is_empty()
            && self.unblacklisted.is_empty()
            && self.forbidden.is_empty()
            && self.allowed.is_empty()
    }
}

/// Which tasks to list.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct TaskFilter {
    /// The mission.
    pub mission_id: MissionId,
    /// Only this robot's, when set.
    pub robot_id: Option<RobotId>,
    /// Only this kind, when set.
    pub kind: Option<TaskKind>,
    /// Only tasks that have not ended.
    pub open_only: bool,
    /// At most this many, newest first.
    pub limit: u32,
}

impl TaskFilter {
    /// A mission's latest `limit` tasks.
    pub fn mission(mission_id: MissionId, limit: u32) -> Self {
        Self { mission_id, robot_id: None, kind: None, open_only: false, limit }
    }
}

/// The executive's persistence.
#[async_trait]
pub trait Store: Send + Sync + std::fmt::Debug {
    /// Creates a mission and returns it with its new identity.
    async fn create_mission(&self, spec: &MissionSpec, now: Timestamp) -> Result<MissionRecord, StoreError>;

    /// Every mission, oldest first.
    async fn missions(&self) -> Result<Vec<MissionRecord>, StoreError>;

    /// Registers a robot with the hash of its token and returns it with its new identity.
    async fn create_robot(
        &self,
        mission_id: MissionId,
        spec: &RobotSpec,
        token_sha256: &str,
        now: Timestamp,
    ) -> Result<RobotRecord, StoreError>;

    /// Replaces the hash of a robot's token.
    async fn set_robot_token(&self, robot_id: RobotId, token_sha256: &str) -> Result<(), StoreError>;

    /// Every robot's token hash (robots registered before tokens have none).
    async fn robot_tokens(&self) -> Result<Vec<(RobotId, String)>, StoreError>;

    /// A mission's blacklisted targets.
    async fn blacklist(&self, mission_id: MissionId) -> Result<Vec<BlacklistEntry>, StoreError>;

    /// A mission's forbidden regions that are still forbidden, oldest first.
    async fn forbidden_regions(&self, mission_id: MissionId) -> Result<Vec<Region>, StoreError>;

    /// The highest region identity ever given (0 when none).
    async fn max_region_id(&self) -> Result<u64, StoreError>;

    /// A mission's robots, in registration order.
    async fn robots(&self, mission_id: MissionId) -> Result<Vec<RobotRecord>, StoreError>;

    /// A mission's map log, in the order it was applied.
    async fn patches(&self, mission_id: MissionId) -> Result<Vec<LoggedPatch>, StoreError>;

    /// A mission's tasks that have not ended.
    async fn open_tasks(&self, mission_id: MissionId) -> Result<Vec<TaskRecord>, StoreError>;

    /// Tasks with their transitions, newest first.
    async fn tasks(&self, filter: TaskFilter) -> Result<Vec<TaskRecord>, StoreError>;

    /// The highest task identity ever given (0 when none).
    async fn max_task_id(&self) -> Result<TaskId, StoreError>;

    /// Replaces a robot's bids.
    async fn replace_bids(&self, robot_id: RobotId, bids: &[Bid], now: Timestamp) -> Result<(), StoreError>;

    /// A robot's latest bids.
    async fn bids(&self, robot_id: RobotId) -> Result<Vec<Bid>, StoreError>;

    /// A mission's events, oldest first.
    async fn events(&self, mission_id: MissionId) -> Result<Vec<MissionEvent>, StoreError>;

    /// A mission's latest segmentation, if one was computed.
    async fn segmentation(&self, mission_id: MissionId) -> Result<Option<StoredSegmentation>, StoreError>;

    /// Writes a changeset in one transaction.
    async fn commit(&self, changes: &Changeset) -> Result<(), StoreError>;
}
