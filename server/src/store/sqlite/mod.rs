//! The SQLite store: one file, WAL journal, migrations embedded at build time.

use std::collections::BTreeMap;
use std::path::Path;
use std::str::FromStr;
use std::time::Duration;

use async_trait::async_trait;
use sqlx::sqlite::{
    SqliteConnectOptions, SqliteJournalMode, SqlitePool, SqlitePoolOptions, SqliteRow, SqliteSynchronous,
};
use sqlx::{Row, Sqlite, Transaction};

use super::{Changeset, LoggedPatch, Store, StoreError, TaskFilter};
use crate::domain::{
    Actor, Bid, BlacklistEntry, Leftover, LeftoverReason, LifecycleSettings, MissionEvent, MissionId, MissionRecord,
    MissionSpec, MissionState, Pose, Region, ReplanSettings, RobotId, RobotRecord, RobotSpec, RobotState,
    StoredSegmentation, TaskId, TaskKind, TaskRecord, TaskState, Timestamp, Transition,
};
use exploration::fusion::Patch;
use exploration::grid::Cell;
use exploration::grid::{CellRect, GridFrame};
use exploration::math::Point2;
use exploration::policy::{Capabilities, PolicyConfig};
use exploration::segment::{CriticalPoint, Segment, Segmentation};

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
}

impl SqliteStore {
    /// Opens (creating if needed) the database at `path` and applies migrations.
    pub async fn open(path: &Path, durability: Durability) -> Result<Self, StoreError> {
        let options = SqliteConnectOptions::from_str("sqlite:")?
            .filename(path)
            .create_if_missing(true)
            .journal_mode(SqliteJournalMode::Wal)
            .synchronous(match durability {
                Durability::Full => SqliteSynchronous::Full,
                Durability::Normal => SqliteSynchronous::Normal,
            })
            .foreign_keys(true)
            .busy_timeout(Duration::from_secs(10));
        let pool = SqlitePoolOptions::new().max_connections(4).connect_with(options).await?;
        MIGRATOR.run(&pool).await?;
        Ok(Self { pool })
    }

    /// Closes every connection, checkpointing the WAL.
    pub async fn close(&self) {
        self.pool.close().await;
    }
}

fn corrupt(what: impl Into<String>) -> StoreError {
    StoreError::Corrupt(what.into())
}

fn leftovers_json(leftovers: &[Leftover]) -> String {
    let items: Vec<serde_json::Value> = leftovers
        .iter()
        .map(|l| {
            serde_json::json!({
                "reason": l.reason.as_str(), "cells": l.cells, "x": l.position.x, "y": l.position.y,
            })
        })
        .collect();
    serde_json::Value::Array(items).to_string()
}

fn leftovers_from_json(id: i64, json: &str) -> Result<Vec<Leftover>, StoreError> {
    let bad = |what: &str| corrupt(format!("mission {id}: leftovers: {what}"));
    let value: serde_json::Value = serde_json::from_str(json).map_err(|e| bad(&e.to_string()))?;
    value
        .as_array()
        .ok_or_else(|| bad("not an array"))?
        .iter()
        .map(|l| {
            let reason = l["reason"].as_str().and_then(LeftoverReason::parse).ok_or_else(|| bad("reason"))?;
            Ok(Leftover {
                reason,
                cells: l["cells"].as_u64().ok_or_else(|| bad("cells"))? as usize,
                position: Point2::new(
                    l["x"].as_f64().ok_or_else(|| bad("x"))?,
                    l["y"].as_f64().ok_or_else(|| bad("y"))?,
                ),
            })
        })
        .collect()
}

fn mission_from_row(row: &SqliteRow) -> Result<MissionRecord, StoreError> {
    let id: i64 = row.try_get("id")?;
    let policy: String = row.try_get("policy")?;
    let params_json: String = row.try_get("policy_params")?;
    let params: BTreeMap<String, f64> =
        serde_json::from_str(&params_json).map_err(|e| corrupt(format!("mission {id}: policy parameters: {e}")))?;
    let policy = PolicyConfig::new(&policy, &params).map_err(|e| corrupt(format!("mission {id}: {e}")))?;
    let state: String = row.try_get("state")?;
    Ok(MissionRecord {
        id: id as MissionId,
        spec: MissionSpec {
            name: row.try_get("name")?,
            frame: GridFrame::new(
                row.try_get("resolution")?,
                Point2::new(row.try_get("origin_x")?, row.try_get("origin_y")?),
                row.try_get::<i64, _>("width")? as u32,
                row.try_get::<i64, _>("height")? as u32,
            ),
            policy,
            replan: ReplanSettings {
                distance_m: row.try_get("replan_distance_m")?,
                interval: Duration::from_secs_f64(row.try_get("replan_interval_s")?),
                frontier_change: row.try_get("replan_frontier_change")?,
            },
            scoped_by_communication: row.try_get::<i64, _>("scoped_by_communication")? != 0,
            lifecycle: LifecycleSettings {
                lease: Duration::from_secs_f64(row.try_get("lease_s")?),
                stall: Duration::from_secs_f64(row.try_get("stall_s")?),
                rendezvous: match (
                    row.try_get::<Option<f64>, _>("rendezvous_x")?,
                    row.try_get::<Option<f64>, _>("rendezvous_y")?,
                ) {
                    (Some(x), Some(y)) => Some(Point2::new(x, y)),
                    _ => None,
                },
            },
        },
        state: MissionState::parse(&state).ok_or_else(|| corrupt(format!("mission {id}: state {state:?}")))?,
        replans: row.try_get::<i64, _>("replans")? as u64,
        map_updates: row.try_get::<i64, _>("map_updates")? as u64,
        paused: row.try_get::<i64, _>("paused")? != 0,
        leftovers: leftovers_from_json(id, &row.try_get::<String, _>("leftovers")?)?,
        created_at: Timestamp(row.try_get("created_at")?),
    })
}

fn robot_from_row(row: &SqliteRow) -> Result<RobotRecord, StoreError> {
    let id: i64 = row.try_get("id")?;
    let state: String = row.try_get("state")?;
    Ok(RobotRecord {
        id: id as RobotId,
        mission_id: row.try_get::<i64, _>("mission_id")? as MissionId,
        name: row.try_get("name")?,
        capabilities: Capabilities {
            sensor_range_m: row.try_get("sensor_range_m")?,
            field_of_view_rad: row.try_get("field_of_view_rad")?,
            speed_mps: row.try_get("speed_mps")?,
            footprint_radius_m: row.try_get("footprint_radius_m")?,
        },
        state: RobotState::parse(&state).ok_or_else(|| corrupt(format!("robot {id}: state {state:?}")))?,
        pose: Pose {
            position: Point2::new(row.try_get("pose_x")?, row.try_get("pose_y")?),
            heading: row.try_get("pose_theta")?,
        },
        last_map_seq: row.try_get::<i64, _>("last_map_seq")? as u64,
        distance_m: row.try_get("distance_m")?,
        assignment_version: row.try_get::<i64, _>("assignment_version")? as u64,
        assigned_distance_m: row.try_get("assigned_distance_m")?,
        current_task: row.try_get::<Option<i64>, _>("current_task_id")?.map(|t| t as TaskId),
        last_seen: Timestamp(row.try_get("last_seen")?),
        lost: row.try_get::<i64, _>("lost")? != 0,
        home: Point2::new(row.try_get("home_x")?, row.try_get("home_y")?),
    })
}

fn task_from_row(row: &SqliteRow) -> Result<TaskRecord, StoreError> {
    let id: i64 = row.try_get("id")?;
    let state: String = row.try_get("state")?;
    let kind: String = row.try_get("kind")?;
    Ok(TaskRecord {
        id: id as TaskId,
        mission_id: row.try_get::<i64, _>("mission_id")? as MissionId,
        robot_id: row.try_get::<i64, _>("robot_id")? as RobotId,
        kind: TaskKind::parse(&kind).ok_or_else(|| corrupt(format!("task {id}: kind {kind:?}")))?,
        target: Point2::new(row.try_get("target_x")?, row.try_get("target_y")?),
        state: TaskState::parse(&state).ok_or_else(|| corrupt(format!("task {id}: state {state:?}")))?,
        policy: row.try_get("policy")?,
        utility: row.try_get("utility")?,
        path_cost: row.try_get("path_cost")?,
        gain_region: match (
            row.try_get::<Option<i64>, _>("gain_x")?,
            row.try_get::<Option<i64>, _>("gain_y")?,
            row.try_get::<Option<i64>, _>("gain_width")?,
            row.try_get::<Option<i64>, _>("gain_height")?,
        ) {
            (Some(x), Some(y), Some(w), Some(h)) => Some(CellRect::new(x as i32, y as i32, w as u32, h as u32)),
            _ => None,
        },
        created_by: row.try_get("created_by")?,
        note: row.try_get("note")?,
        created_at: Timestamp(row.try_get("created_at")?),
        updated_at: Timestamp(row.try_get("updated_at")?),
        transitions: Vec::new(),
    })
}

/// Run-length encoding of labels: (label, run) pairs of little-endian u32.
fn encode_labels(labels: &[u32]) -> Vec<u8> {
    let mut out = Vec::new();
    let mut i = 0;
    while i < labels.len() {
        let label = labels[i];
        let run = labels[i..].iter().take_while(|&&l| l == label).count();
        out.extend_from_slice(&label.to_le_bytes());
        out.extend_from_slice(&(run as u32).to_le_bytes());
        i += run;
    }
    out
}

fn decode_labels(bytes: &[u8], len: usize) -> Result<Vec<u32>, StoreError> {
    let mut labels = Vec::with_capacity(len);
    for pair in bytes.chunks_exact(8) {
        let label = u32::from_le_bytes([pair[0], pair[1], pair[2], pair[3]]);
        let run = u32::from_le_bytes([pair[4], pair[5], pair[6], pair[7]]) as usize;
        labels.extend(std::iter::repeat_n(label, run));
    }
    if labels.len() == len {
        Ok(labels)
    } else {
        Err(corrupt(format!("segmentation labels hold {} cells, not {len}", labels.len())))
    }
}

fn segments_json(segmentation: &Segmentation) -> String {
    let segments: Vec<serde_json::Value> = segmentation
        .segments
        .iter()
        .map(|s| {
            serde_json::json!({
                "id": s.id,
                "cells": s.cells,
                "bounds": [s.bounds.x, s.bounds.y, s.bounds.width, s.bounds.height],
                "frontier": s.frontier.iter().map(|c| [c.x, c.y]).collect::<Vec<_>>(),
            })
        })
        .collect();
    serde_json::Value::Array(segments).to_string()
}

fn critical_points_json(segmentation: &Segmentation) -> String {
    let points: Vec<serde_json::Value> =
        segmentation.critical_points.iter().map(|p| serde_json::json!([p.cell.x, p.cell.y, p.clearance])).collect();
    serde_json::Value::Array(points).to_string()
}

fn segmentation_from_row(row: &SqliteRow, frame: GridFrame) -> Result<StoredSegmentation, StoreError> {
    let bad = |what: &str| corrupt(format!("segmentation: {what}"));
    let labels = decode_labels(&row.try_get::<Vec<u8>, _>("labels")?, frame.len())?;
    let segments: serde_json::Value =
        serde_json::from_str(&row.try_get::<String, _>("segments")?).map_err(|e| bad(&e.to_string()))?;
    let points: serde_json::Value =
        serde_json::from_str(&row.try_get::<String, _>("critical_points")?).map_err(|e| bad(&e.to_string()))?;
    let int = |v: &serde_json::Value| v.as_i64().ok_or_else(|| bad("not an integer"));
    let segments = segments
        .as_array()
        .ok_or_else(|| bad("segments"))?
        .iter()
        .map(|s| {
            let b = s["bounds"].as_array().ok_or_else(|| bad("bounds"))?;
            Ok(Segment {
                id: int(&s["id"])? as u32,
                cells: int(&s["cells"])? as usize,
                bounds: CellRect::new(int(&b[0])? as i32, int(&b[1])? as i32, int(&b[2])? as u32, int(&b[3])? as u32),
                frontier: s["frontier"]
                    .as_array()
                    .ok_or_else(|| bad("frontier"))?
                    .iter()
                    .map(|c| Ok(Cell::new(int(&c[0])? as i32, int(&c[1])? as i32)))
                    .collect::<Result<_, StoreError>>()?,
            })
        })
        .collect::<Result<Vec<_>, StoreError>>()?;
    let critical_points = points
        .as_array()
        .ok_or_else(|| bad("critical points"))?
        .iter()
        .map(|p| {
            Ok(CriticalPoint {
                cell: Cell::new(int(&p[0])? as i32, int(&p[1])? as i32),
                clearance: p[2].as_f64().ok_or_else(|| bad("clearance"))?,
            })
        })
        .collect::<Result<Vec<_>, StoreError>>()?;
    Ok(StoredSegmentation {
        computed_at: Timestamp(row.try_get("computed_at")?),
        segmentation: Segmentation { frame, labels, segments, critical_points },
    })
}

fn transition_from_row(row: &SqliteRow) -> Result<Transition, StoreError> {
    let from: Option<String> = row.try_get("from_state")?;
    let to: String = row.try_get("to_state")?;
    let actor: String = row.try_get("actor")?;
    Ok(Transition {
        from: match from {
            Some(s) => Some(TaskState::parse(&s).ok_or_else(|| corrupt(format!("transition from {s:?}")))?),
            None => None,
        },
        to: TaskState::parse(&to).ok_or_else(|| corrupt(format!("transition to {to:?}")))?,
        at: Timestamp(row.try_get("at")?),
        cause: row.try_get("cause")?,
        actor: Actor::parse(&actor).ok_or_else(|| corrupt(format!("transition actor {actor:?}")))?,
        by: row.try_get("by_name")?,
    })
}

/// Little-endian f32 per cell, NaN for unknown cells.
fn encode_cells(patch: &Patch) -> Vec<u8> {
    patch.log_odds().iter().flat_map(|v| v.to_le_bytes()).collect()
}

fn decode_cells(bytes: &[u8]) -> Vec<f32> {
    bytes.chunks_exact(4).map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]])).collect()
}

async fn write_robot(tx: &mut Transaction<'_, Sqlite>, robot: &RobotRecord) -> Result<(), StoreError> {
    sqlx::query(
        "UPDATE robots SET sensor_range_m = ?1, field_of_view_rad = ?2, speed_mps = ?3, footprint_radius_m = ?4,
                state = ?5, pose_x = ?6, pose_y = ?7, pose_theta = ?8, last_map_seq = ?9, distance_m = ?10,
                assignment_version = ?11, assigned_distance_m = ?12, current_task_id = ?13, last_seen = ?14,
                lost = ?15
         WHERE id = ?16",
    )
    .bind(robot.capabilities.sensor_range_m)
    .bind(robot.capabilities.field_of_view_rad)
    .bind(robot.capabilities.speed_mps)
    .bind(robot.capabilities.footprint_radius_m)
    .bind(robot.state.as_str())
    .bind(robot.pose.position.x)
    .bind(robot.pose.position.y)
    .bind(robot.pose.heading)
    .bind(robot.last_map_seq as i64)
    .bind(robot.distance_m)
    .bind(robot.assignment_version as i64)
    .bind(robot.assigned_distance_m)
    .bind(robot.current_task.map(|t| t as i64))
    .bind(robot.last_seen.millis())
    .bind(i64::from(robot.lost))
    .bind(robot.id as i64)
    .execute(&mut **tx)
    .await?;
    Ok(())
}

async fn write_transition(tx: &mut Transaction<'_, Sqlite>, task_id: TaskId, t: &Transition) -> Result<(), StoreError> {
    sqlx::query(
        "INSERT INTO task_transitions (task_id, from_state, to_state, cause, actor, at, by_name)
         VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7)",
    )
    .bind(task_id as i64)
    .bind(t.from.map(TaskState::as_str))
    .bind(t.to.as_str())
    .bind(&t.cause)
    .bind(t.actor.as_str())
    .bind(t.at.millis())
    .bind(&t.by)
    .execute(&mut **tx)
    .await?;
    Ok(())
}

#[async_trait]
impl Store for SqliteStore {
    async fn create_mission(&self, spec: &MissionSpec, now: Timestamp) -> Result<MissionRecord, StoreError> {
        let params: BTreeMap<&str, f64> = spec.policy.params().clone();
        let params = serde_json::to_string(&params).map_err(|e| corrupt(e.to_string()))?;
        let row = sqlx::query(
            "INSERT INTO missions (name, resolution, origin_x, origin_y, width, height, policy, policy_params,
                                   replan_distance_m, replan_interval_s, replan_frontier_change, state,
                                   created_at, updated_at, scoped_by_communication, lease_s, stall_s,
                                   rendezvous_x, rendezvous_y)
             VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7, ?8, ?9, ?10, ?11, 'active', ?12, ?12, ?13, ?14, ?15, ?16, ?17)
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
        .fetch_one(&self.pool)
        .await?;
        mission_from_row(&row)
    }

    async fn missions(&self) -> Result<Vec<MissionRecord>, StoreError> {
        sqlx::query("SELECT * FROM missions ORDER BY id")
            .fetch_all(&self.pool)
            .await?
            .iter()
            .map(mission_from_row)
            .collect()
    }

    async fn create_robot(
        &self,
        mission_id: MissionId,
        spec: &RobotSpec,
        token_sha256: &str,
        now: Timestamp,
    ) -> Result<RobotRecord, StoreError> {
        let row = sqlx::query(
            "INSERT INTO robots (mission_id, name, sensor_range_m, field_of_view_rad, speed_mps, footprint_radius_m,
                                 state, pose_x, pose_y, pose_theta, last_seen, created_at, home_x, home_y,
                                 token_sha256)
             VALUES (?1, ?2, ?3, ?4, ?5, ?6, 'idle', ?7, ?8, ?9, ?10, ?10, ?7, ?8, ?11)
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
        .bind(token_sha256)
        .fetch_one(&self.pool)
        .await?;
        robot_from_row(&row)
    }

    async fn set_robot_token(&self, robot_id: RobotId, token_sha256: &str) -> Result<(), StoreError> {
        sqlx::query("UPDATE robots SET token_sha256 = ?1 WHERE id = ?2")
            .bind(token_sha256)
            .bind(robot_id as i64)
            .execute(&self.pool)
            .await?;
        Ok(())
    }

    async fn robot_tokens(&self) -> Result<Vec<(RobotId, String)>, StoreError> {
        let rows = sqlx::query("SELECT id, token_sha256 FROM robots WHERE token_sha256 IS NOT NULL")
            .fetch_all(&self.pool)
            .await?;
        rows.iter().map(|row| Ok((row.try_get::<i64, _>("id")? as RobotId, row.try_get("token_sha256")?))).collect()
    }

    async fn blacklist(&self, mission_id: MissionId) -> Result<Vec<BlacklistEntry>, StoreError> {
        sqlx::query(
            "SELECT b.* FROM blacklist b JOIN robots r ON r.id = b.robot_id WHERE r.mission_id = ?1
             ORDER BY b.created_at, b.robot_id",
        )
        .bind(mission_id as i64)
        .fetch_all(&self.pool)
        .await?
        .iter()
        .map(|row| {
            Ok(BlacklistEntry {
                robot_id: row.try_get::<i64, _>("robot_id")? as RobotId,
                cell: Cell::new(row.try_get::<i64, _>("cell_x")? as i32, row.try_get::<i64, _>("cell_y")? as i32),
                cause: row.try_get("cause")?,
                created_at: Timestamp(row.try_get("created_at")?),
            })
        })
        .collect()
    }

    async fn forbidden_regions(&self, mission_id: MissionId) -> Result<Vec<Region>, StoreError> {
        sqlx::query("SELECT * FROM forbidden_regions WHERE mission_id = ?1 AND allowed_at IS NULL ORDER BY id")
            .bind(mission_id as i64)
            .fetch_all(&self.pool)
            .await?
            .iter()
            .map(|row| {
                Ok(Region {
                    id: row.try_get::<i64, _>("id")? as u64,
                    mission_id: row.try_get::<i64, _>("mission_id")? as MissionId,
                    min: Point2::new(row.try_get("min_x")?, row.try_get("min_y")?),
                    max: Point2::new(row.try_get("max_x")?, row.try_get("max_y")?),
                    actor: row.try_get("actor")?,
                    reason: row.try_get("reason")?,
                    created_at: Timestamp(row.try_get("created_at")?),
                })
            })
            .collect()
    }

    async fn max_region_id(&self) -> Result<u64, StoreError> {
        let max: Option<i64> =
            sqlx::query_scalar("SELECT MAX(id) FROM forbidden_regions").fetch_one(&self.pool).await?;
        Ok(max.unwrap_or(0) as u64)
    }

    async fn robots(&self, mission_id: MissionId) -> Result<Vec<RobotRecord>, StoreError> {
        sqlx::query("SELECT * FROM robots WHERE mission_id = ?1 ORDER BY id")
            .bind(mission_id as i64)
            .fetch_all(&self.pool)
            .await?
            .iter()
            .map(robot_from_row)
            .collect()
    }

    async fn patches(&self, mission_id: MissionId) -> Result<Vec<LoggedPatch>, StoreError> {
        sqlx::query(
            "SELECT robot_id, seq, x, y, width, height, cells FROM map_patches WHERE mission_id = ?1 ORDER BY id",
        )
        .bind(mission_id as i64)
        .fetch_all(&self.pool)
        .await?
        .iter()
        .map(|row| {
            let rect = CellRect::new(
                row.try_get::<i64, _>("x")? as i32,
                row.try_get::<i64, _>("y")? as i32,
                row.try_get::<i64, _>("width")? as u32,
                row.try_get::<i64, _>("height")? as u32,
            );
            let cells: Vec<u8> = row.try_get("cells")?;
            let patch = Patch::from_stored(rect, decode_cells(&cells)).map_err(|e| corrupt(e.to_string()))?;
            Ok(LoggedPatch {
                robot_id: row.try_get::<i64, _>("robot_id")? as RobotId,
                seq: row.try_get::<i64, _>("seq")? as u64,
                patch,
            })
        })
        .collect()
    }

    async fn open_tasks(&self, mission_id: MissionId) -> Result<Vec<TaskRecord>, StoreError> {
        sqlx::query("SELECT * FROM tasks WHERE mission_id = ?1 AND state IN ('assigned', 'active') ORDER BY id")
            .bind(mission_id as i64)
            .fetch_all(&self.pool)
            .await?
            .iter()
            .map(task_from_row)
            .collect()
    }

    async fn tasks(&self, filter: TaskFilter) -> Result<Vec<TaskRecord>, StoreError> {
        // The selected tasks, as a literal so that both queries stay static SQL.
        macro_rules! selected {
            () => {
                "SELECT id FROM tasks WHERE mission_id = ?1 AND (?2 IS NULL OR robot_id = ?2)
                 AND (?3 IS NULL OR kind = ?3) AND (?4 = 0 OR state IN ('assigned', 'active'))
                 ORDER BY id DESC LIMIT ?5"
            };
        }
        let rows = sqlx::query(concat!("SELECT * FROM tasks WHERE id IN (", selected!(), ") ORDER BY id DESC"))
            .bind(filter.mission_id as i64)
            .bind(filter.robot_id.map(|r| r as i64))
            .bind(filter.kind.map(TaskKind::as_str))
            .bind(i64::from(filter.open_only))
            .bind(i64::from(filter.limit))
            .fetch_all(&self.pool)
            .await?;
        let mut tasks = rows.iter().map(task_from_row).collect::<Result<Vec<_>, _>>()?;
        if !tasks.is_empty() {
            let transitions =
                sqlx::query(concat!("SELECT * FROM task_transitions WHERE task_id IN (", selected!(), ") ORDER BY id"))
                    .bind(filter.mission_id as i64)
                    .bind(filter.robot_id.map(|r| r as i64))
                    .bind(filter.kind.map(TaskKind::as_str))
                    .bind(i64::from(filter.open_only))
                    .bind(i64::from(filter.limit))
                    .fetch_all(&self.pool)
                    .await?;
            let mut by_task: BTreeMap<TaskId, Vec<Transition>> = BTreeMap::new();
            for row in &transitions {
                let task_id = row.try_get::<i64, _>("task_id")? as TaskId;
                by_task.entry(task_id).or_default().push(transition_from_row(row)?);
            }
            for task in &mut tasks {
                task.transitions = by_task.remove(&task.id).unwrap_or_default();
            }
        }
        Ok(tasks)
    }

    async fn max_task_id(&self) -> Result<TaskId, StoreError> {
        let max: Option<i64> = sqlx::query_scalar("SELECT MAX(id) FROM tasks").fetch_one(&self.pool).await?;
        Ok(max.unwrap_or(0) as TaskId)
    }

    async fn replace_bids(&self, robot_id: RobotId, bids: &[Bid], now: Timestamp) -> Result<(), StoreError> {
        let mut tx = self.pool.begin().await?;
        sqlx::query("DELETE FROM bids WHERE robot_id = ?1").bind(robot_id as i64).execute(&mut *tx).await?;
        for (ordinal, bid) in bids.iter().enumerate() {
            sqlx::query(
                "INSERT INTO bids (robot_id, ordinal, target_x, target_y, path_cost, information_gain,
                                   region_min_x, region_min_y, region_max_x, region_max_y, submitted_at)
                 VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7, ?8, ?9, ?10, ?11)",
            )
            .bind(robot_id as i64)
            .bind(ordinal as i64)
            .bind(bid.target.x)
            .bind(bid.target.y)
            .bind(bid.path_cost)
            .bind(bid.information_gain)
            .bind(bid.gain_region.0.x)
            .bind(bid.gain_region.0.y)
            .bind(bid.gain_region.1.x)
            .bind(bid.gain_region.1.y)
            .bind(now.millis())
            .execute(&mut *tx)
            .await?;
        }
        tx.commit().await?;
        Ok(())
    }

    async fn bids(&self, robot_id: RobotId) -> Result<Vec<Bid>, StoreError> {
        sqlx::query("SELECT * FROM bids WHERE robot_id = ?1 ORDER BY ordinal")
            .bind(robot_id as i64)
            .fetch_all(&self.pool)
            .await?
            .iter()
            .map(|row| {
                Ok(Bid {
                    target: Point2::new(row.try_get("target_x")?, row.try_get("target_y")?),
                    path_cost: row.try_get("path_cost")?,
                    information_gain: row.try_get("information_gain")?,
                    gain_region: (
                        Point2::new(row.try_get("region_min_x")?, row.try_get("region_min_y")?),
                        Point2::new(row.try_get("region_max_x")?, row.try_get("region_max_y")?),
                    ),
                })
            })
            .collect()
    }

    async fn events(&self, mission_id: MissionId) -> Result<Vec<MissionEvent>, StoreError> {
        sqlx::query("SELECT * FROM mission_events WHERE mission_id = ?1 ORDER BY id")
            .bind(mission_id as i64)
            .fetch_all(&self.pool)
            .await?
            .iter()
            .map(|row| {
                Ok(MissionEvent {
                    id: row.try_get::<i64, _>("id")? as u64,
                    mission_id: row.try_get::<i64, _>("mission_id")? as MissionId,
                    at: Timestamp(row.try_get("at")?),
                    kind: row.try_get("kind")?,
                    detail: row.try_get("detail")?,
                    actor: row.try_get("actor")?,
                })
            })
            .collect()
    }

    async fn segmentation(&self, mission_id: MissionId) -> Result<Option<StoredSegmentation>, StoreError> {
        let frame = sqlx::query("SELECT resolution, origin_x, origin_y, width, height FROM missions WHERE id = ?1")
            .bind(mission_id as i64)
            .fetch_optional(&self.pool)
            .await?;
        let Some(frame) = frame else { return Ok(None) };
        let frame = GridFrame::new(
            frame.try_get("resolution")?,
            Point2::new(frame.try_get("origin_x")?, frame.try_get("origin_y")?),
            frame.try_get::<i64, _>("width")? as u32,
            frame.try_get::<i64, _>("height")? as u32,
        );
        let row = sqlx::query("SELECT * FROM segmentations WHERE mission_id = ?1")
            .bind(mission_id as i64)
            .fetch_optional(&self.pool)
            .await?;
        row.map(|row| segmentation_from_row(&row, frame)).transpose()
    }

    async fn commit(&self, changes: &Changeset) -> Result<(), StoreError> {
        if changes.is_empty() {
            return Ok(());
        }
        let now = changes.at.unwrap_or_else(Timestamp::now);
        let mut tx = self.pool.begin().await?;
        // Tasks first: robots refer to them.
        for task in &changes.new_tasks {
            sqlx::query(
                "INSERT INTO tasks (id, mission_id, robot_id, target_x, target_y, state, policy, utility, path_cost,
                                    created_at, updated_at, gain_x, gain_y, gain_width, gain_height, kind,
                                    created_by, note)
                 VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7, ?8, ?9, ?10, ?11, ?12, ?13, ?14, ?15, ?16, ?17, ?18)",
            )
            .bind(task.id as i64)
            .bind(task.mission_id as i64)
            .bind(task.robot_id as i64)
            .bind(task.target.x)
            .bind(task.target.y)
            .bind(task.state.as_str())
            .bind(&task.policy)
            .bind(task.utility)
            .bind(task.path_cost)
            .bind(task.created_at.millis())
            .bind(task.updated_at.millis())
            .bind(task.gain_region.map(|r| i64::from(r.x)))
            .bind(task.gain_region.map(|r| i64::from(r.y)))
            .bind(task.gain_region.map(|r| i64::from(r.width)))
            .bind(task.gain_region.map(|r| i64::from(r.height)))
            .bind(task.kind.as_str())
            .bind(&task.created_by)
            .bind(&task.note)
            .execute(&mut *tx)
            .await?;
            for t in &task.transitions {
                write_transition(&mut tx, task.id, t).await?;
            }
        }
        for change in &changes.task_changes {
            sqlx::query("UPDATE tasks SET state = ?1, updated_at = ?2 WHERE id = ?3")
                .bind(change.state.as_str())
                .bind(change.transition.at.millis())
                .bind(change.task_id as i64)
                .execute(&mut *tx)
                .await?;
            write_transition(&mut tx, change.task_id, &change.transition).await?;
        }
        for robot in &changes.robots {
            write_robot(&mut tx, robot).await?;
        }
        for logged in &changes.patches {
            let rect = logged.patch.rect();
            sqlx::query(
                "INSERT INTO map_patches (mission_id, robot_id, seq, x, y, width, height, cells, received_at)
                 SELECT mission_id, ?1, ?2, ?3, ?4, ?5, ?6, ?7, ?8 FROM robots WHERE id = ?1",
            )
            .bind(logged.robot_id as i64)
            .bind(logged.seq as i64)
            .bind(i64::from(rect.x))
            .bind(i64::from(rect.y))
            .bind(i64::from(rect.width))
            .bind(i64::from(rect.height))
            .bind(encode_cells(&logged.patch))
            .bind(now.millis())
            .execute(&mut *tx)
            .await?;
        }
        if let Some((mission_id, policy)) = &changes.policy {
            let params: BTreeMap<&str, f64> = policy.params().clone();
            sqlx::query("UPDATE missions SET policy = ?1, policy_params = ?2 WHERE id = ?3")
                .bind(policy.name())
                .bind(serde_json::to_string(&params).map_err(|e| corrupt(e.to_string()))?)
                .bind(*mission_id as i64)
                .execute(&mut *tx)
                .await?;
        }
        for event in &changes.events {
            sqlx::query("INSERT INTO mission_events (mission_id, at, kind, detail, actor) VALUES (?1, ?2, ?3, ?4, ?5)")
                .bind(event.mission_id as i64)
                .bind(event.at.millis())
                .bind(&event.kind)
                .bind(&event.detail)
                .bind(&event.actor)
                .execute(&mut *tx)
                .await?;
        }
        if let Some((mission_id, stored)) = &changes.segmentation {
            sqlx::query(
                "INSERT INTO segmentations (mission_id, computed_at, labels, segments, critical_points)
                 VALUES (?1, ?2, ?3, ?4, ?5)
                 ON CONFLICT (mission_id) DO UPDATE SET computed_at = excluded.computed_at, labels = excluded.labels,
                     segments = excluded.segments, critical_points = excluded.critical_points",
            )
            .bind(*mission_id as i64)
            .bind(stored.computed_at.millis())
            .bind(encode_labels(&stored.segmentation.labels))
            .bind(segments_json(&stored.segmentation))
            .bind(critical_points_json(&stored.segmentation))
            .execute(&mut *tx)
            .await?;
        }
        for entry in &changes.blacklisted {
            sqlx::query(
                "INSERT INTO blacklist (robot_id, cell_x, cell_y, cause, created_at) VALUES (?1, ?2, ?3, ?4, ?5)
                 ON CONFLICT (robot_id, cell_x, cell_y) DO UPDATE SET cause = excluded.cause,
                     created_at = excluded.created_at",
            )
            .bind(entry.robot_id as i64)
            .bind(i64::from(entry.cell.x))
            .bind(i64::from(entry.cell.y))
            .bind(&entry.cause)
            .bind(entry.created_at.millis())
            .execute(&mut *tx)
            .await?;
        }
        for (robot, cell) in &changes.unblacklisted {
            sqlx::query("DELETE FROM blacklist WHERE robot_id = ?1 AND cell_x = ?2 AND cell_y = ?3")
                .bind(*robot as i64)
                .bind(i64::from(cell.x))
                .bind(i64::from(cell.y))
                .execute(&mut *tx)
                .await?;
        }
        for region in &changes.forbidden {
            sqlx::query(
                "INSERT INTO forbidden_regions (id, mission_id, min_x, min_y, max_x, max_y, actor, reason, created_at)
                 VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7, ?8, ?9)",
            )
            .bind(region.id as i64)
            .bind(region.mission_id as i64)
            .bind(region.min.x)
            .bind(region.min.y)
            .bind(region.max.x)
            .bind(region.max.y)
            .bind(&region.actor)
            .bind(&region.reason)
            .bind(region.created_at.millis())
            .execute(&mut *tx)
            .await?;
        }
        for region in &changes.allowed {
            sqlx::query("UPDATE forbidden_regions SET allowed_at = ?1 WHERE id = ?2")
                .bind(now.millis())
                .bind(*region as i64)
                .execute(&mut *tx)
                .await?;
        }
        if let Some(m) = &changes.mission {
            sqlx::query(
                "UPDATE missions SET state = ?1, replans = ?2, map_updates = ?3, updated_at = ?4, paused = ?5,
                        leftovers = ?6
                 WHERE id = ?7",
            )
            .bind(m.state.as_str())
            .bind(m.replans as i64)
            .bind(m.map_updates as i64)
            .bind(now.millis())
            .bind(i64::from(m.paused))
            .bind(leftovers_json(&m.leftovers))
            .bind(m.id as i64)
            .execute(&mut *tx)
            .await?;
        }
        tx.commit().await?;
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::store::{MissionCounters, TaskChange};

    fn spec() -> MissionSpec {
        MissionSpec {
            name: "lab".into(),
            frame: GridFrame::new(0.1, Point2::new(-1.0, -2.0), 40, 30),
            policy: PolicyConfig::default_for("burgard").unwrap(),
            replan: ReplanSettings::default(),
            scoped_by_communication: true,
            lifecycle: LifecycleSettings {
                lease: Duration::from_secs(7),
                stall: Duration::from_secs(11),
                rendezvous: Some(Point2::new(0.5, -1.5)),
            },
        }
    }

    fn robot_spec(name: &str) -> RobotSpec {
        RobotSpec {
            name: name.into(),
            capabilities: Capabilities {
                sensor_range_m: 4.0,
                field_of_view_rad: 6.0,
                speed_mps: 0.5,
                footprint_radius_m: 0.2,
            },
            pose: Pose { position: Point2::new(0.5, 0.5), heading: 0.1 },
        }
    }

    #[tokio::test]
    async fn a_changeset_round_trips_through_a_real_file() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("store.db");
        let store = SqliteStore::open(&path, Durability::Full).await.unwrap();
        let mission = store.create_mission(&spec(), Timestamp(1_000)).await.unwrap();
        assert_eq!(mission.spec, spec());
        let mut robot = store.create_robot(mission.id, &robot_spec("r1"), "", Timestamp(2_000)).await.unwrap();
        assert_eq!(robot.state, RobotState::Idle);
        assert_eq!(robot.home, Point2::new(0.5, 0.5));
        store.set_robot_token(robot.id, "abc123").await.unwrap();

        let rect = CellRect::new(3, 4, 2, 1);
        let patch = Patch::from_probabilities(rect, &[0.2, 0.9], &[false, true]).unwrap();
        let task = TaskRecord {
            id: 7,
            mission_id: mission.id,
            robot_id: robot.id,
            kind: TaskKind::Goto,
            target: Point2::new(1.0, 2.0),
            state: TaskState::Assigned,
            policy: "operator".into(),
            utility: 0.5,
            path_cost: 1.5,
            gain_region: Some(CellRect::new(1, 2, 3, 4)),
            created_by: "operator:ana".into(),
            note: "check the lab".into(),
            created_at: Timestamp(3_000),
            updated_at: Timestamp(3_000),
            transitions: vec![Transition {
                from: None,
                to: TaskState::Assigned,
                at: Timestamp(3_000),
                cause: "operator ana".into(),
                actor: Actor::Operator,
                by: "ana".into(),
            }],
        };
        let frame = spec().frame;
        let mut labels = vec![0u32; frame.len()];
        labels[5..40].fill(1);
        labels[100..130].fill(2);
        let segmentation = StoredSegmentation {
            computed_at: Timestamp(3_000),
            segmentation: Segmentation {
                frame,
                labels,
                segments: vec![
                    Segment { id: 1, cells: 35, bounds: CellRect::new(5, 0, 35, 1), frontier: vec![Cell::new(7, 0)] },
                    Segment { id: 2, cells: 30, bounds: CellRect::new(20, 2, 30, 2), frontier: vec![] },
                ],
                critical_points: vec![CriticalPoint { cell: Cell::new(19, 1), clearance: 2.5 }],
            },
        };
        robot.current_task = Some(7);
        robot.last_map_seq = 5;
        robot.assignment_version = 1;
        robot.lost = true;
        let leftovers =
            vec![Leftover { reason: LeftoverReason::TooNarrow, cells: 12, position: Point2::new(1.5, 2.5) }];
        let region = Region {
            id: 3,
            mission_id: mission.id,
            min: Point2::new(0.0, 0.0),
            max: Point2::new(1.0, 1.0),
            actor: "ana".into(),
            reason: "wet floor".into(),
            created_at: Timestamp(3_000),
        };
        let blacklisted = BlacklistEntry {
            robot_id: robot.id,
            cell: Cell::new(4, 5),
            cause: "unreachable".into(),
            created_at: Timestamp(3_000),
        };
        store
            .commit(&Changeset {
                mission: Some(MissionCounters {
                    id: mission.id,
                    state: MissionState::Completed,
                    replans: 1,
                    map_updates: 1,
                    paused: true,
                    leftovers: leftovers.clone(),
                }),
                robots: vec![robot.clone()],
                new_tasks: vec![task.clone()],
                task_changes: vec![],
                patches: vec![LoggedPatch { robot_id: robot.id, seq: 5, patch: patch.clone() }],
                policy: Some((mission.id, PolicyConfig::default_for("minpos").unwrap())),
                events: vec![MissionEvent {
                    id: 0,
                    mission_id: mission.id,
                    at: Timestamp(3_000),
                    kind: "policy_changed".into(),
                    detail: "burgard -> minpos".into(),
                    actor: "ops".into(),
                }],
                segmentation: Some((mission.id, segmentation.clone())),
                blacklisted: vec![blacklisted.clone(), BlacklistEntry { cell: Cell::new(9, 9), ..blacklisted.clone() }],
                unblacklisted: vec![],
                forbidden: vec![region.clone(), Region { id: 4, ..region.clone() }],
                allowed: vec![],
                at: Some(Timestamp(3_000)),
            })
            .await
            .unwrap();
        store
            .commit(&Changeset {
                task_changes: vec![TaskChange {
                    task_id: 7,
                    state: TaskState::Reached,
                    transition: Transition {
                        from: Some(TaskState::Assigned),
                        to: TaskState::Reached,
                        at: Timestamp(4_000),
                        cause: "robot arrived".into(),
                        actor: Actor::Robot,
                        by: String::new(),
                    },
                }],
                unblacklisted: vec![(robot.id, Cell::new(9, 9))],
                allowed: vec![4],
                ..Changeset::default()
            })
            .await
            .unwrap();
        store.close().await;

        // Reopen the file: everything is there.
        let store = SqliteStore::open(&path, Durability::Normal).await.unwrap();
        let missions = store.missions().await.unwrap();
        assert_eq!(missions.len(), 1);
        assert_eq!(missions[0].replans, 1);
        assert_eq!(missions[0].spec.lifecycle, spec().lifecycle);
        assert!(missions[0].paused);
        assert_eq!(missions[0].state, MissionState::Completed);
        assert_eq!(missions[0].leftovers, leftovers);
        assert_eq!(store.blacklist(mission.id).await.unwrap(), vec![blacklisted]);
        assert_eq!(store.forbidden_regions(mission.id).await.unwrap(), vec![region]);
        assert_eq!(store.max_region_id().await.unwrap(), 4);
        assert_eq!(store.robot_tokens().await.unwrap(), vec![(robot.id, "abc123".to_owned())]);
        assert_eq!(store.robots(mission.id).await.unwrap(), vec![robot.clone()]);
        let patches = store.patches(mission.id).await.unwrap();
        assert_eq!(patches.len(), 1);
        assert_eq!(patches[0].seq, 5);
        assert_eq!(patches[0].patch.rect(), rect);
        assert_eq!(patches[0].patch.log_odds()[0], patch.log_odds()[0]);
        assert!(patches[0].patch.log_odds()[1].is_nan());
        assert!(store.open_tasks(mission.id).await.unwrap().is_empty());
        let tasks =
            store.tasks(TaskFilter { robot_id: Some(robot.id), ..TaskFilter::mission(mission.id, 10) }).await.unwrap();
        assert_eq!(tasks.len(), 1);
        assert_eq!(tasks[0].state, TaskState::Reached);
        assert_eq!(
            (tasks[0].kind, tasks[0].created_by.as_str(), tasks[0].note.as_str()),
            (TaskKind::Goto, "operator:ana", "check the lab")
        );
        assert_eq!(tasks[0].transitions.len(), 2);
        assert_eq!(tasks[0].transitions[0].by, "ana");
        assert_eq!(tasks[0].transitions[1].actor, Actor::Robot);
        let filter = TaskFilter { kind: Some(TaskKind::Explore), ..TaskFilter::mission(mission.id, 10) };
        assert!(store.tasks(filter).await.unwrap().is_empty());
        let filter = TaskFilter { open_only: true, ..TaskFilter::mission(mission.id, 10) };
        assert!(store.tasks(filter).await.unwrap().is_empty());
        assert_eq!(tasks[0].gain_region, Some(CellRect::new(1, 2, 3, 4)));
        assert_eq!(missions[0].spec.policy.name(), "minpos");
        let events = store.events(mission.id).await.unwrap();
        assert_eq!(events.len(), 1);
        assert_eq!((events[0].kind.as_str(), events[0].actor.as_str()), ("policy_changed", "ops"));
        assert_eq!(store.segmentation(mission.id).await.unwrap(), Some(segmentation));
        assert_eq!(store.max_task_id().await.unwrap(), 7);
    }

    #[tokio::test]
    async fn a_failed_changeset_writes_nothing() {
        let dir = tempfile::tempdir().unwrap();
        let store = SqliteStore::open(&dir.path().join("s.db"), Durability::Full).await.unwrap();
        let mission = store.create_mission(&spec(), Timestamp(1)).await.unwrap();
        let robot = store.create_robot(mission.id, &robot_spec("r1"), "", Timestamp(1)).await.unwrap();
        let mut moved = robot.clone();
        moved.last_map_seq = 9;
        // A task for a robot that does not exist violates a foreign key.
        let bad_task = TaskRecord {
            id: 1,
            mission_id: mission.id,
            robot_id: 999,
            kind: TaskKind::Explore,
            target: Point2::origin(),
            state: TaskState::Assigned,
            policy: "burgard".into(),
            utility: 0.0,
            path_cost: 0.0,
            gain_region: None,
            created_by: "policy".into(),
            note: String::new(),
            created_at: Timestamp(1),
            updated_at: Timestamp(1),
            transitions: vec![],
        };
        let result =
            store.commit(&Changeset { robots: vec![moved], new_tasks: vec![bad_task], ..Changeset::default() }).await;
        assert!(result.is_err());
        assert_eq!(store.robots(mission.id).await.unwrap(), vec![robot]);
    }
}
