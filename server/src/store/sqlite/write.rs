//! One changeset, written in one transaction.
//!
//! A commit either writes all of a changeset or none of it, and a failure
//! never leaves a connection inside a transaction: whatever state SQLite and
//! sqlx were left in (after a full disk SQLite may or may not have rolled
//! back by itself, and sqlx's count of open transactions may be off), the
//! connection is closed instead of going back to the pool.

use std::collections::BTreeMap;

use sqlx::SqliteConnection;

use super::rows::{critical_points_json, encode_cells, encode_labels, leftovers_json, segments_json};
use crate::domain::{RobotRecord, TaskId, TaskState, Timestamp, Transition};
use crate::store::{Changeset, StoreError};

/// Writes `changes` inside the transaction open on `tx`.
pub(super) async fn changeset(tx: &mut SqliteConnection, changes: &Changeset) -> Result<(), StoreError> {
    let now = changes.at.unwrap_or_else(Timestamp::now);
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
            write_transition(tx, task.id, t).await?;
        }
    }
    for change in &changes.task_changes {
        sqlx::query("UPDATE tasks SET state = ?1, updated_at = ?2 WHERE id = ?3")
            .bind(change.state.as_str())
            .bind(change.transition.at.millis())
            .bind(change.task_id as i64)
            .execute(&mut *tx)
            .await?;
        write_transition(tx, change.task_id, &change.transition).await?;
    }
    for robot in &changes.robots {
        write_robot(tx, robot).await?;
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
            .bind(serde_json::to_string(&params).map_err(|e| StoreError::Corrupt(e.to_string()))?)
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
    for (robot, hash) in &changes.robot_tokens {
        sqlx::query("UPDATE robots SET token_sha256 = ?1 WHERE id = ?2")
            .bind(hash)
            .bind(*robot as i64)
            .execute(&mut *tx)
            .await?;
    }
    if let Some((robot, bids)) = &changes.bids {
        sqlx::query("DELETE FROM bids WHERE robot_id = ?1").bind(*robot as i64).execute(&mut *tx).await?;
        for (ordinal, bid) in bids.iter().enumerate() {
            sqlx::query(
                "INSERT INTO bids (robot_id, ordinal, target_x, target_y, path_cost, information_gain,
                                   region_min_x, region_min_y, region_max_x, region_max_y, submitted_at)
                 VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7, ?8, ?9, ?10, ?11)",
            )
            .bind(*robot as i64)
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
    }
    Ok(())
}

async fn write_robot(tx: &mut SqliteConnection, robot: &RobotRecord) -> Result<(), StoreError> {
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
    .execute(&mut *tx)
    .await?;
    Ok(())
}

async fn write_transition(tx: &mut SqliteConnection, task_id: TaskId, t: &Transition) -> Result<(), StoreError> {
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
    .execute(&mut *tx)
    .await?;
    Ok(())
}
