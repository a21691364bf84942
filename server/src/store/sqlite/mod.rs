//! The SQLite store: one file, WAL journal, migrations embedded at build
//! time, held by one executive at a time ([`StoreLock`]).
//!
//! [`rows`] reads records back and checks them; [`write`] writes changesets.

mod checkpoint;
mod group;
mod rows;
mod write;

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::str::FromStr;
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Duration;

use async_trait::async_trait;
use sqlx::Connection;
use sqlx::sqlite::{SqliteConnectOptions, SqliteJournalMode, SqlitePool, SqlitePoolOptions, SqliteSynchronous};

use super::lock::StoreLock;
use super::{Changeset, CommitId, Store, StoreError, StoredMap, Submitted, TaskFilter};
use crate::domain::{
    Bid, BlacklistEntry, MissionEvent, MissionId, MissionRecord, MissionSpec, Region, RobotId, RobotRecord, RobotSpec,
    Rooms, StoredSegmentation, TaskId, TaskKind, TaskRecord, Timestamp, Transition,
};
use rows::At;

static MIGRATOR: sqlx::migrate::Migrator = sqlx::migrate!("../migrations");

/// How hard SQLite works to keep a commit across failures.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Durability {
    /// Every commit survives a power cut (`synchronous = FULL`).
    #[default]
    Full,
    /// Every commit survives a crash of the process, the last ones may not
    /// survive a power cut (`synchronous = NORMAL`, safe in WAL mode).
    Normal,
}

/// Missions, robots, tasks and the map log in one SQLite file.
#[derive(Debug, Clone)]
pub struct SqliteStore {
    pool: SqlitePool,
    path: PathBuf,
    /// The group committer's queue (see [`group`]); taken at close.
    commits: Arc<std::sync::Mutex<Option<tokio::sync::mpsc::Sender<group::Pending>>>>,
    committer: Arc<std::sync::Mutex<Option<tokio::task::JoinHandle<()>>>>,
    /// Held by every writer (the committer for each group) and by the
    /// checkpointer to rewind the log.
    turn: checkpoint::WriterTurn,
    /// The checkpointer (see [`checkpoint`]) and how to stop it; taken at close.
    checkpointer: Arc<std::sync::Mutex<Option<checkpoint::Checkpointer>>>,
    /// The name of the next changeset submitted.
    next_commit: Arc<AtomicU64>,
    /// Held until the store is closed or every clone of it is dropped.
    lock: Arc<std::sync::Mutex<Option<StoreLock>>>,
}

impl SqliteStore {
    /// Opens (creating if needed) the database at `path` and applies
    /// migrations; refused while another executive holds it.
    pub async fn open(path: &Path, durability: Durability) -> Result<Self, StoreError> {
        Self::open_measured(path, durability, None).await
    }

    /// [`SqliteStore::open`], with commit latency and group sizes counted in `metrics`.
    pub async fn open_measured(
        path: &Path,
        durability: Durability,
        metrics: Option<Arc<crate::metrics::Metrics>>,
    ) -> Result<Self, StoreError> {
        check_path(path)?;
        let lock = StoreLock::acquire(path)?;
        let options = SqliteConnectOptions::from_str("sqlite:")?
            .filename(path)
            .create_if_missing(true)
            .journal_mode(SqliteJournalMode::Wal)
            .synchronous(match durability {
                Durability::Full => SqliteSynchronous::Full,
                Durability::Normal => SqliteSynchronous::Normal,
            })
            .foreign_keys(true)
            // Checkpoints run beside the writes, not inside them (see `checkpoint`).
            .pragma("wal_autocheckpoint", "0")
            .pragma("journal_size_limit", checkpoint::LOG_LIMIT_BYTES.to_string())
            .busy_timeout(Duration::from_secs(5));
        let pool = SqlitePoolOptions::new().max_connections(4).connect_with(options).await?;
        MIGRATOR.run(&pool).await?;
        let turn = checkpoint::WriterTurn::default();
        let (commits, committer) = group::start(pool.clone(), turn.clone(), metrics);
        let checkpointer = checkpoint::Checkpointer::start(pool.clone(), turn.clone());
        Ok(Self {
            pool,
            path: path.to_owned(),
            commits: Arc::new(std::sync::Mutex::new(Some(commits))),
            committer: Arc::new(std::sync::Mutex::new(Some(committer))),
            turn,
            checkpointer: Arc::new(std::sync::Mutex::new(Some(checkpointer))),
            next_commit: Arc::new(AtomicU64::new(1)),
            lock: Arc::new(std::sync::Mutex::new(Some(lock))),
        })
    }

    /// Closes every connection, checkpointing the WAL, and lets go of the
    /// database for the next executive.
    pub async fn close(&self) {
        // The committer writes what is queued, then ends.
        self.commits.lock().unwrap_or_else(|e| e.into_inner()).take();
        let committer = self.committer.lock().unwrap_or_else(|e| e.into_inner()).take();
        if let Some(committer) = committer {
            let _ = committer.await;
        }
        let checkpointer = self.checkpointer.lock().unwrap_or_else(|e| e.into_inner()).take();
        if let Some(checkpointer) = checkpointer {
            checkpointer.stop().await;
        }
        self.pool.close().await;
        self.lock.lock().unwrap_or_else(|e| e.into_inner()).take();
    }

    /// The database file.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Every row `sql` selects for `key` (its one parameter), read by `read`.
    async fn all<T>(
        &self,
        sql: &'static str,
        key: u64,
        read: impl Fn(&sqlx::sqlite::SqliteRow) -> Result<T, StoreError>,
    ) -> Result<Vec<T>, StoreError> {
        sqlx::query(sql).bind(key as i64).fetch_all(&self.pool).await?.iter().map(read).collect()
    }

    /// The count `sql` selects for `key` (its one parameter).
    async fn count(&self, sql: &'static str, key: u64) -> Result<u64, StoreError> {
        let count: i64 = sqlx::query_scalar(sql).bind(key as i64).fetch_one(&self.pool).await?;
        Ok(count.max(0) as u64)
    }

    /// The events a query over `mission_events` selects, checked.
    async fn events_of(
        &self,
        query: sqlx::query::Query<'_, sqlx::Sqlite, sqlx::sqlite::SqliteArguments>,
    ) -> Result<Vec<MissionEvent>, StoreError> {
        query.fetch_all(&self.pool).await?.iter().map(rows::event_from_row).collect()
    }

    /// The grid frame of a mission, checked.
    async fn frame(&self, mission_id: MissionId) -> Result<Option<exploration::grid::GridFrame>, StoreError> {
        let row = sqlx::query("SELECT id, resolution, origin_x, origin_y, width, height FROM missions WHERE id = ?1")
            .bind(mission_id as i64)
            .fetch_optional(&self.pool)
            .await?;
        row.map(|row| rows::frame_from_row(At::row("missions", &row, "id")?, &row)).transpose()
    }
}

/// Refuses what is not a database file SQLite can keep across restarts: an
/// in-memory database (each pooled connection would get its own, and all of
/// it would be lost), a folder, or a file in a folder that does not exist.
fn check_path(path: &Path) -> Result<(), StoreError> {
    let text = path.to_string_lossy();
    let bad = |why: String| Err(StoreError::Path(format!("--db {}: {why}", path.display())));
    if text.is_empty() || text == ":memory:" || text.starts_with("file:") || text.contains("mode=memory") {
        return bad("the executive keeps everything it acknowledges in a database file: give a file path".to_owned());
    }
    if path.is_dir() {
        return bad("is a folder; give a file in it (created if missing)".to_owned());
    }
    match path.parent().filter(|p| !p.as_os_str().is_empty()) {
        Some(dir) if !dir.is_dir() => bad(format!("the folder {} does not exist", dir.display())),
        _ => Ok(()),
    }
}

/// SQL that orders and pages a mission's tasks, shared by the two queries of
/// [`Store::tasks`] as a literal so that both stay static SQL.
macro_rules! selected_tasks {
    () => {
        "SELECT id FROM tasks WHERE mission_id = ?1 AND (?2 IS NULL OR robot_id = ?2)
         AND (?3 IS NULL OR kind = ?3) AND (?4 = 0 OR state IN ('assigned', 'active'))
         ORDER BY id DESC LIMIT ?5"
    };
}

#[async_trait]
impl Store for SqliteStore {
    async fn create_mission(&self, spec: &MissionSpec, now: Timestamp) -> Result<MissionRecord, StoreError> {
        let params: BTreeMap<&str, f64> = spec.policy.params().clone();
        let params = serde_json::to_string(&params).map_err(|e| StoreError::Corrupt(e.to_string()))?;
        let row = sqlx::query(
            "INSERT INTO missions (name, resolution, origin_x, origin_y, width, height, policy, policy_params,
                                   replan_distance_m, replan_interval_s, replan_frontier_change, state,
                                   created_at, updated_at, scoped_by_communication, lease_s, stall_s,
                                   rendezvous_x, rendezvous_y, lockstep)
             VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7, ?8, ?9, ?10, ?11, 'active', ?12, ?12, ?13, ?14, ?15, ?16, ?17,
                     ?18)
             RETURNING *",
        )
        .bind(&spec.name)
        .bind(spec.frame.resolution)
        .bind(spec.frame.origin.x)
        .bind(spec.frame.origin.y)
        .bind(i64::from(spec.frame.width))
        .bind(i64::from(spec.frame.height))
        .bind(spec.policy.name())
        .bind(params)
        .bind(spec.replan.distance_m)
        .bind(spec.replan.interval.as_secs_f64())
        .bind(spec.replan.frontier_change)
        .bind(now.millis())
        .bind(i64::from(spec.scoped_by_communication))
        .bind(spec.lifecycle.lease.as_secs_f64())
        .bind(spec.lifecycle.stall.as_secs_f64())
        .bind(spec.lifecycle.rendezvous.map(|p| p.x))
        .bind(spec.lifecycle.rendezvous.map(|p| p.y))
        .bind(i64::from(spec.lockstep))
        .fetch_one(&self.pool)
        .await?;
        rows::mission_from_row(&row)
    }

    async fn missions(&self) -> Result<Vec<MissionRecord>, StoreError> {
        sqlx::query("SELECT * FROM missions ORDER BY id")
            .fetch_all(&self.pool)
            .await?
            .iter()
            .map(rows::mission_from_row)
            .collect()
    }

    async fn create_robot(
        &self,
        mission_id: MissionId,
        spec: &RobotSpec,
        token_hash: &(dyn Fn(RobotId) -> String + Send + Sync),
        now: Timestamp,
    ) -> Result<RobotRecord, StoreError> {
        let frame = self.frame(mission_id).await?.ok_or_else(|| {
            StoreError::Corrupt(format!("robots: a robot of mission {mission_id}, which is not stored"))
        })?;
        let _writer = self.turn.lock().await;
        let mut conn = self.pool.acquire().await?;
        let created = async {
            let mut tx = conn.begin_with("BEGIN IMMEDIATE").await?;
            let row = sqlx::query(
                "INSERT INTO robots (mission_id, name, sensor_range_m, field_of_view_rad, speed_mps,
                                     footprint_radius_m, state, pose_x, pose_y, pose_theta, last_seen, created_at,
                                     home_x, home_y)
                 VALUES (?1, ?2, ?3, ?4, ?5, ?6, 'idle', ?7, ?8, ?9, ?10, ?10, ?7, ?8)
                 RETURNING *",
            )
            .bind(mission_id as i64)
            .bind(&spec.name)
            .bind(spec.capabilities.sensor_range_m)
            .bind(spec.capabilities.field_of_view_rad)
            .bind(spec.capabilities.speed_mps)
            .bind(spec.capabilities.footprint_radius_m)
            .bind(spec.pose.position.x)
            .bind(spec.pose.position.y)
            .bind(spec.pose.heading)
            .bind(now.millis())
            .fetch_one(&mut *tx)
            .await?;
            let robot = rows::robot_from_row(&row, &frame)?;
            sqlx::query("UPDATE robots SET token_sha256 = ?1 WHERE id = ?2")
                .bind(token_hash(robot.id))
                .bind(robot.id as i64)
                .execute(&mut *tx)
                .await?;
            tx.commit().await?;
            Ok::<_, StoreError>(robot)
        }
        .await;
        if created.is_err() {
            // Never back to the pool in a state nobody can vouch for (see `write`).
            conn.close_on_drop();
        }
        created
    }

    async fn robot_tokens(&self) -> Result<Vec<(RobotId, String)>, StoreError> {
        sqlx::query("SELECT id, token_sha256 FROM robots WHERE token_sha256 IS NOT NULL AND token_sha256 <> ''")
            .fetch_all(&self.pool)
            .await?
            .iter()
            .map(rows::token_from_row)
            .collect()
    }

    async fn blacklist(&self, mission_id: MissionId) -> Result<Vec<BlacklistEntry>, StoreError> {
        self.all(
            "SELECT b.* FROM blacklist b JOIN robots r ON r.id = b.robot_id WHERE r.mission_id = ?1
             ORDER BY b.created_at, b.robot_id",
            mission_id,
            rows::blacklist_from_row,
        )
        .await
    }

    async fn forbidden_regions(&self, mission_id: MissionId) -> Result<Vec<Region>, StoreError> {
        self.all(
            "SELECT * FROM forbidden_regions WHERE mission_id = ?1 AND allowed_at IS NULL ORDER BY id",
            mission_id,
            rows::region_from_row,
        )
        .await
    }

    async fn max_region_id(&self) -> Result<u64, StoreError> {
        let max: Option<i64> =
            sqlx::query_scalar("SELECT MAX(id) FROM forbidden_regions").fetch_one(&self.pool).await?;
        crate::validate::count(max.unwrap_or(0), "MAX(forbidden_regions.id)")
            .map_err(|e| StoreError::Corrupt(e.to_string()))
    }

    async fn robots(&self, mission: &MissionRecord) -> Result<Vec<RobotRecord>, StoreError> {
        self.all("SELECT * FROM robots WHERE mission_id = ?1 ORDER BY id", mission.id, |row| {
            rows::robot_from_row(row, &mission.spec.frame)
        })
        .await
    }

    async fn stored_map(&self, mission: &MissionRecord, limit: Option<u32>) -> Result<StoredMap, StoreError> {
        // One read transaction: a compaction between reading the snapshot
        // and the patches would otherwise lose the patches it folded.
        let mut tx = self.pool.begin().await?;
        let snapshot = sqlx::query("SELECT * FROM map_snapshots WHERE mission_id = ?1")
            .bind(mission.id as i64)
            .fetch_optional(&mut *tx)
            .await?
            .map(|row| rows::snapshot_from_row(&row))
            .transpose()?;
        let through = snapshot.as_ref().map_or(0, |s| s.through_patch_id);
        let rows = sqlx::query(
            "SELECT id, robot_id, seq, x, y, width, height, cells, cells_format FROM map_patches
             WHERE mission_id = ?1 AND id > ?2 ORDER BY id LIMIT ?3",
        )
        .bind(mission.id as i64)
        .bind(through as i64)
        .bind(limit.map_or(-1, i64::from))
        .fetch_all(&mut *tx)
        .await?;
        tx.commit().await?;
        let mut patches = Vec::with_capacity(rows.len());
        let mut last_patch_id = through;
        for row in &rows {
            let (id, patch) = rows::patch_from_row(row, &mission.spec.frame)?;
            patches.push(patch);
            last_patch_id = id;
        }
        Ok(StoredMap { snapshot, patches, last_patch_id })
    }

    async fn unfolded_patches(&self, mission_id: MissionId) -> Result<u64, StoreError> {
        self.count(
            "SELECT COUNT(*) FROM map_patches WHERE mission_id = ?1
                 AND id > COALESCE((SELECT through_patch_id FROM map_snapshots WHERE mission_id = ?1), 0)",
            mission_id,
        )
        .await
    }

    async fn folded_patches(&self, mission_id: MissionId) -> Result<u64, StoreError> {
        self.count(
            "SELECT COUNT(*) FROM map_patches WHERE mission_id = ?1
                 AND id <= COALESCE((SELECT through_patch_id FROM map_snapshots WHERE mission_id = ?1), 0)",
            mission_id,
        )
        .await
    }

    async fn open_tasks(&self, mission_id: MissionId) -> Result<Vec<TaskRecord>, StoreError> {
        self.all(
            "SELECT * FROM tasks WHERE mission_id = ?1 AND state IN ('assigned', 'active') ORDER BY id",
            mission_id,
            rows::task_from_row,
        )
        .await
    }

    async fn tasks(&self, filter: TaskFilter) -> Result<Vec<TaskRecord>, StoreError> {
        let rows = sqlx::query(concat!("SELECT * FROM tasks WHERE id IN (", selected_tasks!(), ") ORDER BY id DESC"))
            .bind(filter.mission_id as i64)
            .bind(filter.robot_id.map(|r| r as i64))
            .bind(filter.kind.map(TaskKind::as_str))
            .bind(i64::from(filter.open_only))
            .bind(i64::from(filter.limit))
            .fetch_all(&self.pool)
            .await?;
        let mut tasks = rows.iter().map(rows::task_from_row).collect::<Result<Vec<_>, _>>()?;
        if !tasks.is_empty() {
            let transitions = sqlx::query(concat!(
                "SELECT * FROM task_transitions WHERE task_id IN (",
                selected_tasks!(),
                ") ORDER BY id"
            ))
            .bind(filter.mission_id as i64)
            .bind(filter.robot_id.map(|r| r as i64))
            .bind(filter.kind.map(TaskKind::as_str))
            .bind(i64::from(filter.open_only))
            .bind(i64::from(filter.limit))
            .fetch_all(&self.pool)
            .await?;
            let mut by_task: BTreeMap<TaskId, Vec<Transition>> = BTreeMap::new();
            for row in &transitions {
                let (task_id, transition) = rows::transition_from_row(row)?;
                by_task.entry(task_id).or_default().push(transition);
            }
            for task in &mut tasks {
                task.transitions = by_task.remove(&task.id).unwrap_or_default();
            }
        }
        Ok(tasks)
    }

    async fn max_task_id(&self) -> Result<TaskId, StoreError> {
        let max: Option<i64> = sqlx::query_scalar("SELECT MAX(id) FROM tasks").fetch_one(&self.pool).await?;
        crate::validate::count(max.unwrap_or(0), "MAX(tasks.id)").map_err(|e| StoreError::Corrupt(e.to_string()))
    }

    async fn bids(&self, robot_id: RobotId) -> Result<Vec<Bid>, StoreError> {
        self.all("SELECT * FROM bids WHERE robot_id = ?1 ORDER BY ordinal", robot_id, rows::bid_from_row).await
    }

    async fn events(&self, mission_id: MissionId, after_id: u64, limit: u32) -> Result<Vec<MissionEvent>, StoreError> {
        // Identities are SQLite rowids (at most i64::MAX): a larger cursor is past them all.
        let Ok(after_id) = i64::try_from(after_id) else { return Ok(Vec::new()) };
        let sql = "SELECT * FROM mission_events WHERE mission_id = ?1 AND id > ?2 ORDER BY id LIMIT ?3";
        self.events_of(sqlx::query(sql).bind(mission_id as i64).bind(after_id).bind(i64::from(limit))).await
    }

    async fn latest_events(&self, mission_id: MissionId, limit: u32) -> Result<Vec<MissionEvent>, StoreError> {
        let sql = "SELECT * FROM mission_events WHERE mission_id = ?1 ORDER BY id DESC LIMIT ?2";
        self.events_of(sqlx::query(sql).bind(mission_id as i64).bind(i64::from(limit))).await
    }

    async fn segmentation(&self, mission_id: MissionId) -> Result<Option<StoredSegmentation>, StoreError> {
        let Some(frame) = self.frame(mission_id).await? else { return Ok(None) };
        let row = sqlx::query("SELECT * FROM segmentations WHERE mission_id = ?1")
            .bind(mission_id as i64)
            .fetch_optional(&self.pool)
            .await?;
        row.map(|row| rows::segmentation_from_row(&row, frame)).transpose()
    }

    async fn given_segmentation(&self, mission_id: MissionId) -> Result<Option<Rooms>, StoreError> {
        let Some(frame) = self.frame(mission_id).await? else { return Ok(None) };
        let row = sqlx::query("SELECT * FROM given_segmentations WHERE mission_id = ?1")
            .bind(mission_id as i64)
            .fetch_optional(&self.pool)
            .await?;
        row.map(|row| rows::rooms_from_row(&row, frame)).transpose()
    }

    async fn submit(&self, changes: Changeset, after: Option<CommitId>) -> Result<Submitted, StoreError> {
        if changes.is_empty() {
            // Writes nothing: whatever follows it follows what it follows.
            let id = after.unwrap_or_else(|| self.next_commit.fetch_add(1, Ordering::Relaxed));
            return Ok(Submitted::ready(id, Ok(changes)));
        }
        let queue = self.commits.lock().unwrap_or_else(|e| e.into_inner()).clone();
        let closed = || StoreError::Corrupt("the store is closed".to_owned());
        let queue = queue.ok_or_else(closed)?;
        let id = self.next_commit.fetch_add(1, Ordering::Relaxed);
        let (reply, answer) = tokio::sync::oneshot::channel();
        let queued_at = std::time::Instant::now();
        queue.send(group::Pending { id, after, changes, reply, queued_at }).await.map_err(|_| closed())?;
        Ok(Submitted::queued(id, answer))
    }

    async fn backup(&self, path: &Path) -> Result<(), StoreError> {
        // VACUUM INTO copies a consistent snapshot (one read transaction)
        // while writers go on, and refuses to overwrite an existing file.
        let target = path.to_str().ok_or_else(|| StoreError::LockFile {
            path: path.to_owned(),
            source: std::io::Error::new(std::io::ErrorKind::InvalidInput, "the path is not UTF-8"),
        })?;
        sqlx::query("VACUUM INTO ?1").bind(target).execute(&self.pool).await?;
        Ok(())
    }

    fn backup_dir(&self) -> PathBuf {
        match self.path.parent() {
            Some(dir) if !dir.as_os_str().is_empty() => dir.to_owned(),
            _ => PathBuf::from("."),
        }
    }
}

#[cfg(test)]
mod tests;
