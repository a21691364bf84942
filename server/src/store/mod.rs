//! Persistence of missions, robots, the map update log, tasks and bids.
//!
//! The executive talks to a [`Store`] only; SQL lives behind it, in
//! [`sql`], written once for the two engines it runs on: [`sqlite`] (the
//! default, one file) and [`postgres`] (a server). Every write is a [`Changeset`] committed in one transaction,
//! so a crash leaves either all of an operation or none of it, and a commit
//! that fails leaves the store as it was and usable. A store belongs to one
//! executive at a time ([`lock`]).

use std::sync::Arc;

use async_trait::async_trait;

use crate::domain::{
    Bid, BlacklistEntry, Leftovers, MissionEvent, MissionId, MissionRecord, MissionSpec, MissionState, Region, RobotId,
    RobotRecord, RobotSpec, Rooms, StoredSegmentation, TaskId, TaskKind, TaskRecord, TaskState, Timestamp, Transition,
};
use exploration::fusion::{MapFusion, Patch};
use exploration::grid::{Cell, GridFrame};
use exploration::policy::PolicyConfig;
pub use lease::{Claimant, Fence, Lease, Share};

pub mod compact;
pub mod lease;
pub mod lock;
pub mod postgres;
pub mod snapshot;
pub mod sql;
pub mod sqlite;
#[cfg(test)]
pub(crate) mod suite;
#[cfg(test)]
mod tests;

pub use postgres::PostgresStore;
pub use sqlite::SqliteStore;

/// Where the store is: a database file, or a PostgreSQL server.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Location {
    /// A SQLite file, created if missing.
    Sqlite(std::path::PathBuf),
    /// A `postgres://` URL.
    Postgres(String),
    /// The URL of a database this executive has no store for (`mysql://…`):
    /// refused when opened, and shown without its password.
    Unsupported(String),
}

impl Location {
    /// `text` as `--db` reads it: a `postgres://` or `postgresql://` URL is
    /// PostgreSQL; `sqlite:PATH`, `sqlite://PATH` or any text that is not a
    /// URL is a SQLite file; another scheme's URL is [`Self::Unsupported`].
    pub fn parse(text: &str) -> Self {
        if text.starts_with("postgres://") || text.starts_with("postgresql://") {
            return Self::Postgres(text.to_owned());
        }
        if let Some(path) = text.strip_prefix("sqlite://").or_else(|| text.strip_prefix("sqlite:")) {
            return Self::Sqlite(path.into());
        }
        match text.split_once("://") {
            Some((scheme, _)) if is_url_scheme(scheme) => Self::Unsupported(text.to_owned()),
            _ => Self::Sqlite(text.into()),
        }
    }

    /// Opens the store, with its commit latency counted in `metrics`: for
    /// this executive alone, or `shared` with other replicas (PostgreSQL;
    /// see [`lease`]).
    pub async fn open(
        &self,
        durability: sqlite::Durability,
        shared: bool,
        metrics: Option<std::sync::Arc<crate::metrics::Metrics>>,
    ) -> Result<std::sync::Arc<dyn Store>, StoreError> {
        Ok(match self {
            Self::Sqlite(path) => std::sync::Arc::new(SqliteStore::open_measured(path, durability, metrics).await?),
            Self::Postgres(url) => std::sync::Arc::new(PostgresStore::open(url, shared, metrics).await?),
            Self::Unsupported(url) => {
                let scheme = url.split_once("://").map_or("", |(scheme, _)| scheme);
                return Err(StoreError::Path(format!(
                    "{scheme}:// is not a store this executive has: give a SQLite file or a postgres:// URL"
                )));
            }
        })
    }
}

/// Whether `text` could be a URL's scheme (RFC 3986: a letter, then letters,
/// digits, `+`, `-` or `.`), as in `mysql://`.
fn is_url_scheme(text: &str) -> bool {
    let mut chars = text.chars();
    chars.next().is_some_and(|c| c.is_ascii_alphabetic())
        && chars.all(|c| c.is_ascii_alphanumeric() || matches!(c, '+' | '-' | '.'))
}

impl std::str::FromStr for Location {
    type Err = std::convert::Infallible;

    fn from_str(text: &str) -> Result<Self, Self::Err> {
        Ok(Self::parse(text))
    }
}

impl std::fmt::Display for Location {
    /// The file, or the URL without its password.
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::Sqlite(path) => write!(f, "{}", path.display()),
            Self::Postgres(url) | Self::Unsupported(url) => f.write_str(&postgres::without_password(url)),
        }
    }
}

impl From<std::path::PathBuf> for Location {
    fn from(path: std::path::PathBuf) -> Self {
        Self::Sqlite(path)
    }
}

impl From<&str> for Location {
    fn from(text: &str) -> Self {
        Self::parse(text)
    }
}

impl From<String> for Location {
    fn from(text: String) -> Self {
        Self::parse(&text)
    }
}

impl From<&std::path::PathBuf> for Location {
    fn from(path: &std::path::PathBuf) -> Self {
        Self::Sqlite(path.clone())
    }
}

impl From<&std::path::Path> for Location {
    fn from(path: &std::path::Path) -> Self {
        Self::Sqlite(path.to_owned())
    }
}

/// Why the store failed. Never shown to clients in detail; logged once by the service.
#[derive(Debug, thiserror::Error)]
pub enum StoreError {
    /// The database refused or failed.
    #[error("database error: {0}")]
    Database(#[from] sqlx::Error),
    /// Migrations could not be applied.
    #[error("migration error: {0}")]
    Migrate(#[from] sqlx::migrate::MigrateError),
    /// A stored value does not parse or breaks a limit.
    #[error("corrupt record: {0}")]
    Corrupt(String),
    /// Another executive holds the store.
    #[error("{0}")]
    Locked(String),
    /// The path cannot hold a durable store.
    #[error("{0}")]
    Path(String),
    /// The lock file could not be made or read.
    #[error("lock file {path}: {cause}")]
    LockFile {
        /// The lock file.
        path: std::path::PathBuf,
        /// Why.
        cause: std::io::Error,
    },
    /// The store cannot do this; the message says what to use instead.
    #[error("{0}")]
    Unsupported(String),
    /// Not written: another replica has claimed the mission since this one
    /// did (see [`lease`]).
    #[error("mission {mission_id} is no longer this replica's: another one claimed it")]
    Fenced {
        /// The mission.
        mission_id: MissionId,
    },
    /// Not written: the transaction it was grouped in failed as a whole
    /// (the database busy past its timeout, an I/O error), and retrying it
    /// alone at once would meet the same.
    #[error("not written: {cause}")]
    Unwritten {
        /// What the failure means for the caller.
        kind: FailureKind,
        /// The failure of the transaction.
        cause: String,
    },
    /// Not written because a changeset it follows was not (see [`Store::submit`]).
    #[error("not written: a changeset it follows failed ({cause})")]
    Abandoned {
        /// What the first failure of the chain means for the caller.
        kind: FailureKind,
        /// The first failure of the chain.
        cause: String,
    },
}

/// What a failure means for the caller.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FailureKind {
    /// The disk (or the database's size limit) is full: nothing was written;
    /// reads still work, and writes will once space is freed.
    Full,
    /// A passing condition (the file is busy, an I/O error): nothing was
    /// written; retrying later may succeed.
    Transient,
    /// Another replica acts for the mission now: nothing was written, and
    /// this replica must give the mission up.
    Fenced,
    /// Anything else: a bug, a corrupt file.
    Internal,
}

impl StoreError {
    /// What this failure means for the caller.
    pub fn kind(&self) -> FailureKind {
        if let Self::Abandoned { kind, .. } | Self::Unwritten { kind, .. } = self {
            return *kind;
        }
        if let Self::Fenced { .. } = self {
            return FailureKind::Fenced;
        }
        let Self::Database(sqlx::Error::Database(e)) = self else {
            return match self {
                Self::Database(sqlx::Error::Io(_) | sqlx::Error::PoolTimedOut) => FailureKind::Transient,
                _ => FailureKind::Internal,
            };
        };
        if let Some(e) = e.try_downcast_ref::<sqlx::postgres::PgDatabaseError>() {
            return postgres_failure(e.code());
        }
        // SQLite's primary result codes (https://www.sqlite.org/rescode.html)
        // are the low byte of the extended ones sqlx reports.
        let primary = e.code().and_then(|c| c.parse::<i32>().ok()).map(|c| c & 0xff);
        match primary {
            Some(13) => FailureKind::Full,                            // SQLITE_FULL
            Some(5 | 6 | 8 | 10 | 14 | 15) => FailureKind::Transient, // BUSY, LOCKED, READONLY, IOERR, CANTOPEN, PROTOCOL
            _ => FailureKind::Internal,
        }
    }
}

/// What a PostgreSQL error (its SQLSTATE,
/// https://www.postgresql.org/docs/current/errcodes-appendix.html) means.
fn postgres_failure(sqlstate: &str) -> FailureKind {
    match sqlstate {
        "53100" | "53200" | "54000" => FailureKind::Full, // disk full, out of memory, a limit of the server
        // Connection lost, serialization or deadlock, a lock or statement
        // timeout, the server shutting down or starting.
        _ if sqlstate.starts_with("08") || sqlstate.starts_with("40") => FailureKind::Transient,
        "55P03" | "57014" | "57P01" | "57P02" | "57P03" | "53300" => FailureKind::Transient,
        _ => FailureKind::Internal,
    }
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
    pub leftovers: Leftovers,
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
    /// The cells, shared: the store writes them while the mission applies
    /// them, and a copy of a sensor footprint's cells per map update was
    /// 2 % of the executive's CPU at full map-update load.
    pub patch: Arc<Patch>,
}

/// A mission's map as stored: the fused map of the patches folded so far
/// (see [`compact`]), and the patches logged after them.
#[derive(Debug, Clone, Default)]
pub struct StoredMap {
    /// The folded part, if any was folded.
    pub snapshot: Option<MapSnapshot>,
    /// The patches after it, in the order they were applied.
    pub patches: Vec<LoggedPatch>,
    /// The log position of the last of `patches` (of the snapshot's last
    /// patch when there are none; 0 for an empty log).
    pub last_patch_id: u64,
}

impl StoredMap {
    /// The fused map the log makes, on the mission's `frame` with `robots`
    /// robots: the snapshot, then every patch after it. The same map,
    /// bit for bit, as the one the executive had applied them to.
    pub fn fuse(&self, frame: &GridFrame, robots: usize) -> Result<MapFusion, StoreError> {
        let mut fusion = match &self.snapshot {
            Some(s) => snapshot::decode(&s.bytes, s.raw_bytes, frame, robots)
                .map_err(|e| StoreError::Corrupt(format!("map_snapshots: the snapshot {e}")))?,
            None => MapFusion::new(*frame),
        };
        for logged in &self.patches {
            fusion.apply(logged.robot_id, &logged.patch).map_err(|e| {
                StoreError::Corrupt(format!(
                    "map_patches: robot {}'s patch {} does not apply: {e}",
                    logged.robot_id, logged.seq
                ))
            })?;
        }
        Ok(fusion)
    }
}

/// The fused map of a mission's oldest patches, kept in their place.
#[derive(Debug, Clone, PartialEq)]
pub struct MapSnapshot {
    /// The mission.
    pub mission_id: MissionId,
    /// The log position of the last patch folded into it: patches up to
    /// here are in the snapshot, never read again, and removed.
    pub through_patch_id: u64,
    /// How many patches it folds, in all.
    pub folded: u64,
    /// The fused map, as [`snapshot::encode`] writes it.
    pub bytes: Vec<u8>,
    /// Their size decompressed.
    pub raw_bytes: u64,
}

/// Names a submitted changeset, for the ones that follow it (see [`Store::submit`]).
pub type CommitId = u64;

/// A changeset queued for writing.
#[derive(Debug)]
pub struct Submitted {
    /// Its name, for the changesets that follow it.
    pub id: CommitId,
    answer: Answer,
}

#[derive(Debug)]
enum Answer {
    Queued(tokio::sync::oneshot::Receiver<Result<Changeset, StoreError>>),
    Ready(Box<Result<Changeset, StoreError>>),
}

impl Submitted {
    /// A changeset the writer will answer for on `answer`.
    pub fn queued(id: CommitId, answer: tokio::sync::oneshot::Receiver<Result<Changeset, StoreError>>) -> Self {
        Self { id, answer: Answer::Queued(answer) }
    }

    /// A changeset answered already (an empty one, which writes nothing).
    pub fn ready(id: CommitId, outcome: Result<Changeset, StoreError>) -> Self {
        Self { id, answer: Answer::Ready(Box::new(outcome)) }
    }

    /// The changeset back once it is durable, or why it was not written.
    pub async fn durable(self) -> Result<Changeset, StoreError> {
        match self.answer {
            Answer::Ready(outcome) => *outcome,
            Answer::Queued(answer) => {
                answer.await.map_err(|_| StoreError::Corrupt("the store closed before the write".to_owned()))?
            }
        }
    }
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
    /// The rooms given with the mission, when they were set (`Some`) or
    /// cleared (`None`).
    pub given_segmentation: Option<(MissionId, Option<Rooms>)>,
    /// Targets blacklisted for robots.
    pub blacklisted: Vec<BlacklistEntry>,
    /// Blacklist entries that expired: (robot, cell).
    pub unblacklisted: Vec<(RobotId, Cell)>,
    /// Regions forbidden.
    pub forbidden: Vec<Region>,
    /// Forbidden regions allowed again (at the changeset's time).
    pub allowed: Vec<u64>,
    /// Robots' new token hashes.
    pub robot_tokens: Vec<(RobotId, String)>,
    /// A robot's bids, replacing its earlier ones.
    pub bids: Option<(RobotId, Vec<Bid>)>,
    /// The lease the writer holds the mission by, when replicas share the
    /// database: the changeset is written only if the lease still carries
    /// its token (see [`lease`]).
    pub fence: Option<Fence>,
    /// A mission's map folded further: replaces its snapshot, whose
    /// patches are then no longer read (see `forget_folded`).
    pub snapshot: Option<MapSnapshot>,
    /// Removes at most this many of a mission's patches that its snapshot
    /// folds, oldest first: the log shrinks a little at a time, never in
    /// one long write that every other changeset would wait behind.
    pub forget_folded: Option<(MissionId, u32)>,
    /// A mission an operator deleted: hidden from every read at once, its
    /// robots' tokens void; its rows are removed later, a few at a time
    /// ([`Store::purge_deleted`]).
    pub deleted: Option<MissionId>,
    /// When.
    pub at: Option<Timestamp>,
}

impl Changeset {
    /// Whether there is nothing to write (a `fence` alone writes nothing:
    /// it is a condition on the rest).
    pub fn is_empty(&self) -> bool {
        self.mission.is_none()
            && self.robots.is_empty()
            && self.new_tasks.is_empty()
            && self.task_changes.is_empty()
            && self.patches.is_empty()
            && self.policy.is_none()
            && self.events.is_empty()
            && self.segmentation.is_none()
            && self.given_segmentation.is_none()
            && self.blacklisted.is_empty()
            && self.unblacklisted.is_empty()
            && self.forbidden.is_empty()
            && self.allowed.is_empty()
            && self.robot_tokens.is_empty()
            && self.bids.is_none()
            && self.snapshot.is_none()
            && self.forget_folded.is_none()
            && self.deleted.is_none()
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

    /// Creates a mission already claimed by `claimant` until `now + period`
    /// (fencing token 1), in one transaction: no replica ever sees it
    /// unclaimed, and a mission whose lease cannot be written is not made
    /// either.
    async fn create_claimed_mission(
        &self,
        spec: &MissionSpec,
        now: Timestamp,
        claimant: &Claimant,
        period: std::time::Duration,
    ) -> Result<(MissionRecord, Lease), StoreError>;

    /// Every mission, oldest first.
    async fn missions(&self) -> Result<Vec<MissionRecord>, StoreError>;

    /// One mission, if it exists.
    async fn mission(&self, id: MissionId) -> Result<Option<MissionRecord>, StoreError>;

    /// Registers a robot, with the hash of a token that names its new
    /// identity (`token_hash` is given that identity), in one transaction;
    /// with `fence`, only while the writer still holds the mission.
    async fn create_robot(
        &self,
        mission_id: MissionId,
        spec: &RobotSpec,
        token_hash: &(dyn Fn(RobotId) -> String + Send + Sync),
        now: Timestamp,
        fence: Option<Fence>,
    ) -> Result<RobotRecord, StoreError>;

    /// The mission a robot belongs to, if the robot exists.
    async fn robot_mission(&self, robot_id: RobotId) -> Result<Option<MissionId>, StoreError>;

    /// A mission's lease, if it was ever claimed.
    async fn lease(&self, mission_id: MissionId) -> Result<Option<Lease>, StoreError>;

    /// Claims a mission for `claimant` until `now + period`, with the next
    /// fencing token: if nobody ever claimed it, if its lease ran out more
    /// than `grace` before `now`, or if `claimant` held it (a replica that
    /// restarted). `None` when another replica holds it, or it was deleted.
    async fn claim(
        &self,
        mission_id: MissionId,
        claimant: &Claimant,
        now: Timestamp,
        period: std::time::Duration,
        grace: std::time::Duration,
    ) -> Result<Option<Lease>, StoreError>;

    /// Renews the leases `held` (each still carrying its token) until
    /// `now + period`; returns the missions whose lease was renewed: the
    /// others are lost.
    async fn renew(
        &self,
        held: &[Fence],
        now: Timestamp,
        period: std::time::Duration,
    ) -> Result<Vec<MissionId>, StoreError>;

    /// Ends a lease at once, if it still carries its token (a replica that
    /// stops hands its missions on without making anyone wait).
    async fn release(&self, fence: Fence) -> Result<(), StoreError>;

    /// Missions nobody holds: never claimed, or whose lease ran out more
    /// than `grace` before `now`.
    async fn unclaimed(&self, now: Timestamp, grace: std::time::Duration) -> Result<Vec<MissionId>, StoreError>;

    /// Announces `claimant` alive until `now + period` (a zero period
    /// withdraws it) and tells how many replicas are alive at `now` and how
    /// many missions they share.
    async fn announce(
        &self,
        claimant: &Claimant,
        now: Timestamp,
        period: std::time::Duration,
    ) -> Result<Share, StoreError>;

    /// A new block of identities for `owner` (see `id_blocks`): its number,
    /// 1 and up.
    async fn reserve_id_block(&self, owner: &str, now: Timestamp) -> Result<u64, StoreError>;

    /// Every robot's token hash (robots registered before tokens have none).
    async fn robot_tokens(&self) -> Result<Vec<(RobotId, String)>, StoreError>;

    /// A mission's blacklisted targets.
    async fn blacklist(&self, mission_id: MissionId) -> Result<Vec<BlacklistEntry>, StoreError>;

    /// A mission's forbidden regions that are still forbidden, oldest first.
    async fn forbidden_regions(&self, mission_id: MissionId) -> Result<Vec<Region>, StoreError>;

    /// The highest region identity ever given (0 when none).
    async fn max_region_id(&self) -> Result<u64, StoreError>;

    /// A mission's robots, in registration order.
    async fn robots(&self, mission: &MissionRecord) -> Result<Vec<RobotRecord>, StoreError>;

    /// A mission's map log, read at one moment: its snapshot and the
    /// patches after it, all of them or the first `limit`.
    async fn stored_map(&self, mission: &MissionRecord, limit: Option<u32>) -> Result<StoredMap, StoreError>;

    /// How many patches a mission's log holds after its snapshot.
    async fn unfolded_patches(&self, mission_id: MissionId) -> Result<u64, StoreError>;

    /// How many patches its snapshot folds a mission's log still holds.
    async fn folded_patches(&self, mission_id: MissionId) -> Result<u64, StoreError>;

    /// A mission's tasks that have not ended.
    async fn open_tasks(&self, mission_id: MissionId) -> Result<Vec<TaskRecord>, StoreError>;

    /// Tasks with their transitions, newest first.
    async fn tasks(&self, filter: TaskFilter) -> Result<Vec<TaskRecord>, StoreError>;

    /// The highest task identity ever given (0 when none).
    async fn max_task_id(&self) -> Result<TaskId, StoreError>;

    /// A robot's latest bids.
    async fn bids(&self, robot_id: RobotId) -> Result<Vec<Bid>, StoreError>;

    /// A mission's first `limit` events after the one with identity
    /// `after_id` (0: from the start), oldest first.
    async fn events(&self, mission_id: MissionId, after_id: u64, limit: u32) -> Result<Vec<MissionEvent>, StoreError>;

    /// A mission's latest `limit` events, newest first.
    async fn latest_events(&self, mission_id: MissionId, limit: u32) -> Result<Vec<MissionEvent>, StoreError>;

    /// A mission's latest segmentation, if one was computed.
    async fn segmentation(&self, mission_id: MissionId) -> Result<Option<StoredSegmentation>, StoreError>;

    /// The rooms given with a mission, if it has them.
    async fn given_segmentation(&self, mission_id: MissionId) -> Result<Option<Rooms>, StoreError>;

    /// Queues a changeset to be written after every changeset queued before
    /// it, and returns once it is queued; [`Submitted::durable`] then waits
    /// for the write. With `after`, the changeset is written only if the
    /// changeset `after` was: one prepared on a state that included another
    /// must not outlive it. Otherwise it fails with [`StoreError::Abandoned`],
    /// and so does the next one that follows it.
    async fn submit(&self, changes: Changeset, after: Option<CommitId>) -> Result<Submitted, StoreError>;

    /// Writes a changeset in one transaction (possibly with others): all of
    /// it is durable when this returns it back, none of it when it returns
    /// an error.
    async fn commit(&self, changes: Changeset) -> Result<Changeset, StoreError> {
        self.submit(changes, None).await?.durable().await
    }

    /// Removes at most about `limit` rows of one deleted mission (see
    /// [`Changeset::deleted`]), in one short transaction so that other
    /// writes do not wait behind a large mission's removal. Returns whether
    /// it removed anything: `false` once no deleted mission has rows left.
    async fn purge_deleted(&self, limit: u32) -> Result<bool, StoreError>;

    /// Writes a consistent copy of the whole store, taken while it is in
    /// use, to a new file at `path`.
    async fn backup(&self, path: &std::path::Path) -> Result<(), StoreError>;

    /// Where a backup may be written for a while (the same disk as the store,
    /// which must have room for it).
    fn backup_dir(&self) -> std::path::PathBuf;

    /// Writes what is queued, closes every connection and lets go of the
    /// database for the next executive.
    async fn close(&self);
}
