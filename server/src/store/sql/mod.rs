//! The store over a SQL database, written once for every engine.
//!
//! [`SqlStore`] holds the queries and the group committer; a [`Backend`]
//! runs them on one engine (SQLite in [`crate::store::sqlite`], PostgreSQL
//! in [`crate::store::postgres`]), both through sqlx's pools ([`pooled`]).
//! [`rows`] reads records back and checks them; [`write`] writes
//! changesets; [`group`] writes them in groups; [`leases`] keeps the
//! replicas' mission leases.

mod group;
mod leases;
pub mod pooled;
pub(super) mod rows;
pub mod statement;
mod write;

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Duration;

use async_trait::async_trait;

use super::{Changeset, Claimant, CommitId, Fence, Lease, Share, Store, StoreError, StoredMap, Submitted, TaskFilter};
use crate::domain::{
    Bid, BlacklistEntry, MissionEvent, MissionId, MissionRecord, MissionSpec, Region, RobotId, RobotRecord, RobotSpec,
    Rooms, StoredSegmentation, TaskId, TaskKind, TaskRecord, Timestamp, Transition,
};
use rows::At;
pub use statement::{Backend, Statement, Transaction};

/// Missions, robots, tasks and the map log in a SQL database.
#[derive(Debug)]
pub struct SqlStore<B> {
    backend: Arc<B>,
    /// The group committer's queue (see [`group`]); taken at close.
    commits: Arc<std::sync::Mutex<Option<tokio::sync::mpsc::Sender<group::Pending>>>>,
    committer: Arc<std::sync::Mutex<Option<tokio::task::JoinHandle<()>>>>,
    /// The name of the next changeset submitted.
    next_commit: Arc<AtomicU64>,
}

impl<B> Clone for SqlStore<B> {
    fn clone(&self) -> Self {
        Self {
            backend: Arc::clone(&self.backend),
            commits: Arc::clone(&self.commits),
            committer: Arc::clone(&self.committer),
            next_commit: Arc::clone(&self.next_commit),
        }
    }
}

impl<B: Backend> SqlStore<B> {
    /// The store on `backend`, whose schema is up to date, with commit
    /// latency and group sizes counted in `metrics`.
    pub(super) fn new(backend: B, metrics: Option<Arc<crate::metrics::Metrics>>) -> Self {
        let backend = Arc::new(backend);
        let (commits, committer) = group::start(Arc::clone(&backend), metrics);
        Self {
            backend,
            commits: Arc::new(std::sync::Mutex::new(Some(commits))),
            committer: Arc::new(std::sync::Mutex::new(Some(committer))),
            next_commit: Arc::new(AtomicU64::new(1)),
        }
    }

    /// The engine.
    pub(super) fn backend(&self) -> &B {
        &self.backend
    }

    /// Writes what is queued, closes every connection and lets go of the
    /// database for the next executive.
    pub async fn close(&self) {
        // The committer writes what is queued, then ends.
        self.commits.lock().unwrap_or_else(|e| e.into_inner()).take();
        let committer = self.committer.lock().unwrap_or_else(|e| e.into_inner()).take();
        if let Some(committer) = committer {
            let _ = committer.await;
        }
        self.backend.close().await;
    }

    /// Every row `sql` selects for `key` (its one parameter), read by `read`.
    async fn all<T>(
        &self,
        sql: &'static str,
        key: u64,
        read: impl Fn(&B::Row) -> Result<T, StoreError>,
    ) -> Result<Vec<T>, StoreError> {
        self.backend.fetch_all(Statement::new(sql).int(key as i64)).await?.iter().map(read).collect()
    }

    /// The count (or largest identity, 0 for none) `statement` selects, as column `n`.
    async fn number(&self, statement: Statement, what: &str) -> Result<u64, StoreError> {
        let row = self.backend.fetch_optional(statement).await?;
        let value = match row {
            Some(row) => statement::Columns::value::<Option<i64>>(&row, "n")?,
            None => None,
        };
        crate::validate::count(value.unwrap_or(0), what).map_err(|e| StoreError::Corrupt(e.to_string()))
    }

    /// The grid frame of a mission, checked.
    async fn frame(&self, mission_id: MissionId) -> Result<Option<exploration::grid::GridFrame>, StoreError> {
        let select =
            Statement::new("SELECT id, resolution, origin_x, origin_y, width, height FROM missions WHERE id = $1");
        let row = self.backend.fetch_optional(select.int(mission_id as i64)).await?;
        row.map(|row| rows::frame_from_row(At::row("missions", &row, "id")?, &row)).transpose()
    }

    /// The one row of a table keyed by mission that `read` reads, if there is one.
    async fn by_mission<T>(
        &self,
        sql: &'static str,
        mission_id: MissionId,
        read: impl Fn(&B::Row, exploration::grid::GridFrame) -> Result<T, StoreError>,
    ) -> Result<Option<T>, StoreError> {
        let Some(frame) = self.frame(mission_id).await? else { return Ok(None) };
        let row = self.backend.fetch_optional(Statement::new(sql).int(mission_id as i64)).await?;
        row.map(|row| read(&row, frame)).transpose()
    }
}

/// The tasks [`Store::tasks`] selects, newest first: its two queries
/// share it as a literal, so that both stay static SQL.
macro_rules! selected_tasks {
    () => {
        "SELECT id FROM tasks WHERE mission_id = $1 AND ($2 IS NULL OR robot_id = $2)
         AND ($3 IS NULL OR kind = $3) AND ($4 = 0 OR state IN ('assigned', 'active'))
         ORDER BY id DESC LIMIT $5"
    };
}

/// `sql` bound to a task filter's five parameters.
fn filtered(sql: &'static str, filter: &TaskFilter) -> Statement {
    Statement::new(sql)
        .int(filter.mission_id as i64)
        .int(filter.robot_id.map(|r| r as i64))
        .maybe_text(filter.kind.map(TaskKind::as_str))
        .int(i64::from(filter.open_only))
        .int(i64::from(filter.limit))
}

/// The statement that stores a new mission from `spec` and returns its row.
fn insert_mission(spec: &MissionSpec, now: Timestamp) -> Result<Statement, StoreError> {
    let params: BTreeMap<&str, f64> = spec.policy.params().clone();
    let params = serde_json::to_string(&params).map_err(|e| StoreError::Corrupt(e.to_string()))?;
    let insert = Statement::new(
        "INSERT INTO missions (name, resolution, origin_x, origin_y, width, height, policy, policy_params,
                               replan_distance_m, replan_interval_s, replan_frontier_change, state,
                               created_at, updated_at, scoped_by_communication, lease_s, stall_s,
                               rendezvous_x, rendezvous_y, lockstep)
         VALUES ($1, $2, $3, $4, $5, $6, $7, $8, $9, $10, $11, 'active', $12, $12, $13, $14, $15, $16, $17,
                 $18)
         RETURNING *",
    )
    .text(&spec.name)
    .real(spec.frame.resolution)
    .real(spec.frame.origin.x)
    .real(spec.frame.origin.y)
    .int(i64::from(spec.frame.width))
    .int(i64::from(spec.frame.height))
    .text(spec.policy.name())
    .text(&params)
    .real(spec.replan.distance_m)
    .real(spec.replan.interval.as_secs_f64())
    .real(spec.replan.frontier_change)
    .int(now.millis())
    .int(i64::from(spec.scoped_by_communication))
    .real(spec.lifecycle.lease.as_secs_f64())
    .real(spec.lifecycle.stall.as_secs_f64())
    .real(spec.lifecycle.rendezvous.map(|p| p.x))
    .real(spec.lifecycle.rendezvous.map(|p| p.y))
    .int(i64::from(spec.lockstep));
    Ok(insert)
}

#[async_trait]
impl<B: Backend> Store for SqlStore<B> {
    async fn create_mission(&self, spec: &MissionSpec, now: Timestamp) -> Result<MissionRecord, StoreError> {
        let mut tx = self.backend.begin_write().await?;
        let row = tx.fetch_one(insert_mission(spec, now)?).await?;
        tx.commit().await?;
        rows::mission_from_row(&row)
    }

    async fn create_claimed_mission(
        &self,
        spec: &MissionSpec,
        now: Timestamp,
        claimant: &Claimant,
        period: Duration,
    ) -> Result<(MissionRecord, Lease), StoreError> {
        let mut tx = self.backend.begin_write().await?;
        let mission = rows::mission_from_row(&tx.fetch_one(insert_mission(spec, now)?).await?)?;
        let lease = rows::lease_from_row(&tx.fetch_one(leases::first_lease(mission.id, claimant, now, period)).await?)?;
        tx.commit().await?;
        Ok((mission, lease))
    }

    async fn missions(&self) -> Result<Vec<MissionRecord>, StoreError> {
        let select = Statement::new("SELECT * FROM missions WHERE deleted_at IS NULL ORDER BY id");
        let rows = self.backend.fetch_all(select).await?;
        rows.iter().map(rows::mission_from_row).collect()
    }

    async fn mission(&self, id: MissionId) -> Result<Option<MissionRecord>, StoreError> {
        let select = Statement::new("SELECT * FROM missions WHERE id = $1 AND deleted_at IS NULL").int(id as i64);
        self.backend.fetch_optional(select).await?.as_ref().map(rows::mission_from_row).transpose()
    }

    async fn create_robot(
        &self,
        mission_id: MissionId,
        spec: &RobotSpec,
        token_hash: &(dyn Fn(RobotId) -> String + Send + Sync),
        now: Timestamp,
        fence: Option<Fence>,
    ) -> Result<RobotRecord, StoreError> {
        let frame = self.frame(mission_id).await?.ok_or_else(|| {
            StoreError::Corrupt(format!("robots: a robot of mission {mission_id}, which is not stored"))
        })?;
        let insert = Statement::new(
            "INSERT INTO robots (mission_id, name, sensor_range_m, field_of_view_rad, speed_mps,
                                 footprint_radius_m, state, pose_x, pose_y, pose_theta, last_seen, created_at,
                                 home_x, home_y)
             VALUES ($1, $2, $3, $4, $5, $6, 'idle', $7, $8, $9, $10, $10, $7, $8)
             RETURNING *",
        )
        .int(mission_id as i64)
        .text(&spec.name)
        .real(spec.capabilities.sensor_range_m)
        .real(spec.capabilities.field_of_view_rad)
        .real(spec.capabilities.speed_mps)
        .real(spec.capabilities.footprint_radius_m)
        .real(spec.pose.position.x)
        .real(spec.pose.position.y)
        .real(spec.pose.heading)
        .int(now.millis());
        let mut tx = self.backend.begin_write().await?;
        if let Some(fence) = fence {
            write::check_fence(&mut tx, fence).await?;
        }
        let robot = rows::robot_from_row(&tx.fetch_one(insert).await?, &frame)?;
        let token = Statement::new("UPDATE robots SET token_sha256 = $1 WHERE id = $2");
        tx.execute(token.text(&token_hash(robot.id)).int(robot.id as i64)).await?;
        tx.commit().await?;
        Ok(robot)
    }

    async fn robot_mission(&self, robot_id: RobotId) -> Result<Option<MissionId>, StoreError> {
        let select = Statement::new("SELECT mission_id FROM robots WHERE id = $1").int(robot_id as i64);
        let row = self.backend.fetch_optional(select).await?;
        row.map(|row| rows::identity(&row, "robots", "mission_id")).transpose()
    }

    async fn lease(&self, mission_id: MissionId) -> Result<Option<Lease>, StoreError> {
        self.read_lease(mission_id).await
    }

    async fn claim(
        &self,
        mission_id: MissionId,
        claimant: &Claimant,
        now: Timestamp,
        period: Duration,
        grace: Duration,
    ) -> Result<Option<Lease>, StoreError> {
        self.claim_lease(mission_id, claimant, now, period, grace).await
    }

    async fn renew(&self, held: &[Fence], now: Timestamp, period: Duration) -> Result<Vec<MissionId>, StoreError> {
        self.renew_leases(held, now, period).await
    }

    async fn release(&self, fence: Fence) -> Result<(), StoreError> {
        self.release_lease(fence).await
    }

    async fn unclaimed(&self, now: Timestamp, grace: Duration) -> Result<Vec<MissionId>, StoreError> {
        self.unclaimed_missions(now, grace).await
    }

    async fn announce(&self, claimant: &Claimant, now: Timestamp, period: Duration) -> Result<Share, StoreError> {
        self.announce_replica(claimant, now, period).await
    }

    async fn reserve_id_block(&self, owner: &str, now: Timestamp) -> Result<u64, StoreError> {
        self.new_id_block(owner, now).await
    }

    async fn purge_deleted(&self, limit: u32) -> Result<bool, StoreError> {
        let select = Statement::new("SELECT MIN(id) AS n FROM missions WHERE deleted_at IS NOT NULL AND purged = 0");
        let mission_id = self.number(select, "missions: a deleted mission's id").await?;
        if mission_id == 0 {
            return Ok(false);
        }
        let mut tx = self.backend.begin_write().await?;
        write::purge_step(&mut tx, mission_id, limit).await?;
        tx.commit().await?;
        Ok(true)
    }

    async fn robot_tokens(&self) -> Result<Vec<(RobotId, String)>, StoreError> {
        let select =
            Statement::new("SELECT id, token_sha256 FROM robots WHERE token_sha256 IS NOT NULL AND token_sha256 <> ''");
        self.backend.fetch_all(select).await?.iter().map(rows::token_from_row).collect()
    }

    async fn blacklist(&self, mission_id: MissionId) -> Result<Vec<BlacklistEntry>, StoreError> {
        self.all(
            "SELECT b.* FROM blacklist b JOIN robots r ON r.id = b.robot_id WHERE r.mission_id = $1
             ORDER BY b.created_at, b.robot_id",
            mission_id,
            rows::blacklist_from_row,
        )
        .await
    }

    async fn forbidden_regions(&self, mission_id: MissionId) -> Result<Vec<Region>, StoreError> {
        self.all(
            "SELECT * FROM forbidden_regions WHERE mission_id = $1 AND allowed_at IS NULL ORDER BY id",
            mission_id,
            rows::region_from_row,
        )
        .await
    }

    async fn max_region_id(&self) -> Result<u64, StoreError> {
        // With those of purged missions, which are never given again.
        let select = Statement::new(
            "SELECT MAX(n) AS n FROM
                 (SELECT MAX(id) AS n FROM forbidden_regions UNION ALL SELECT MAX(last_region_id) FROM missions) ids",
        );
        self.number(select, "MAX(forbidden_regions.id)").await
    }

    async fn robots(&self, mission: &MissionRecord) -> Result<Vec<RobotRecord>, StoreError> {
        self.all("SELECT * FROM robots WHERE mission_id = $1 ORDER BY id", mission.id, |row| {
            rows::robot_from_row(row, &mission.spec.frame)
        })
        .await
    }

    async fn stored_map(&self, mission: &MissionRecord, limit: Option<u32>) -> Result<StoredMap, StoreError> {
        // One read transaction: a compaction between reading the snapshot
        // and the patches would otherwise lose the patches it folded.
        let mut tx = self.backend.begin_read().await?;
        let select = Statement::new("SELECT * FROM map_snapshots WHERE mission_id = $1");
        let snapshot = tx.fetch_all(select.int(mission.id as i64)).await?;
        let snapshot = snapshot.first().map(rows::snapshot_from_row).transpose()?;
        let through = snapshot.as_ref().map_or(0, |s| s.through_patch_id);
        let select = Statement::new(
            "SELECT id, robot_id, seq, x, y, width, height, cells, cells_format FROM map_patches
             WHERE mission_id = $1 AND id > $2 ORDER BY id LIMIT $3",
        );
        let limit = limit.map_or(i64::MAX, i64::from);
        let rows = tx.fetch_all(select.int(mission.id as i64).int(through as i64).int(limit)).await?;
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
        let count = Statement::new(
            "SELECT COUNT(*) AS n FROM map_patches WHERE mission_id = $1
                 AND id > COALESCE((SELECT through_patch_id FROM map_snapshots WHERE mission_id = $1), 0)",
        );
        self.number(count.int(mission_id as i64), "COUNT(map_patches)").await
    }

    async fn folded_patches(&self, mission_id: MissionId) -> Result<u64, StoreError> {
        let count = Statement::new(
            "SELECT COUNT(*) AS n FROM map_patches WHERE mission_id = $1
                 AND id <= COALESCE((SELECT through_patch_id FROM map_snapshots WHERE mission_id = $1), 0)",
        );
        self.number(count.int(mission_id as i64), "COUNT(map_patches)").await
    }

    async fn open_tasks(&self, mission_id: MissionId) -> Result<Vec<TaskRecord>, StoreError> {
        self.all(
            "SELECT * FROM tasks WHERE mission_id = $1 AND state IN ('assigned', 'active') ORDER BY id",
            mission_id,
            rows::task_from_row,
        )
        .await
    }

    async fn tasks(&self, filter: TaskFilter) -> Result<Vec<TaskRecord>, StoreError> {
        let select = concat!("SELECT * FROM tasks WHERE id IN (", selected_tasks!(), ") ORDER BY id DESC");
        let rows = self.backend.fetch_all(filtered(select, &filter)).await?;
        let mut tasks = rows.iter().map(rows::task_from_row).collect::<Result<Vec<_>, _>>()?;
        if !tasks.is_empty() {
            let select =
                concat!("SELECT * FROM task_transitions WHERE task_id IN (", selected_tasks!(), ") ORDER BY id");
            let transitions = self.backend.fetch_all(filtered(select, &filter)).await?;
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
        // With those of purged missions, which are never given again.
        let select = Statement::new(
            "SELECT MAX(n) AS n FROM (SELECT MAX(id) AS n FROM tasks UNION ALL SELECT MAX(last_task_id) FROM missions) ids",
        );
        self.number(select, "MAX(tasks.id)").await
    }

    async fn bids(&self, robot_id: RobotId) -> Result<Vec<Bid>, StoreError> {
        self.all("SELECT * FROM bids WHERE robot_id = $1 ORDER BY ordinal", robot_id, rows::bid_from_row).await
    }

    async fn events(&self, mission_id: MissionId, after_id: u64, limit: u32) -> Result<Vec<MissionEvent>, StoreError> {
        // Identities are at most i64::MAX: a larger cursor is past them all.
        let Ok(after_id) = i64::try_from(after_id) else { return Ok(Vec::new()) };
        let select =
            Statement::new("SELECT * FROM mission_events WHERE mission_id = $1 AND id > $2 ORDER BY id LIMIT $3");
        let rows = self.backend.fetch_all(select.int(mission_id as i64).int(after_id).int(i64::from(limit))).await?;
        rows.iter().map(rows::event_from_row).collect()
    }

    async fn latest_events(&self, mission_id: MissionId, limit: u32) -> Result<Vec<MissionEvent>, StoreError> {
        let select = Statement::new("SELECT * FROM mission_events WHERE mission_id = $1 ORDER BY id DESC LIMIT $2");
        let rows = self.backend.fetch_all(select.int(mission_id as i64).int(i64::from(limit))).await?;
        rows.iter().map(rows::event_from_row).collect()
    }

    async fn segmentation(&self, mission_id: MissionId) -> Result<Option<StoredSegmentation>, StoreError> {
        self.by_mission("SELECT * FROM segmentations WHERE mission_id = $1", mission_id, rows::segmentation_from_row)
            .await
    }

    async fn given_segmentation(&self, mission_id: MissionId) -> Result<Option<Rooms>, StoreError> {
        self.by_mission("SELECT * FROM given_segmentations WHERE mission_id = $1", mission_id, rows::rooms_from_row)
            .await
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
        self.backend.backup(path).await
    }

    fn backup_dir(&self) -> PathBuf {
        self.backend.backup_dir()
    }

    async fn close(&self) {
        SqlStore::close(self).await;
    }
}
