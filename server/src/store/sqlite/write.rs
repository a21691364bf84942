//! One changeset, written in one transaction.
//!
//! A commit either writes all of a changeset or none of it, and a failure
//! never leaves a connection inside a transaction: whatever state SQLite and
//! sqlx were left in (after a full disk SQLite may or may not have rolled
//! back by itself, and sqlx's count of open transactions may be off), the
//! connection is closed instead of going back to the pool.

use std::collections::BTreeMap;

use sqlx::SqliteConnection;

use super::rows::{CELLS_LZ4, critical_points_json, encode_cells, leftovers_json, segments_json};
use crate::domain::{MissionId, RobotId, RobotRecord, TaskId, TaskState, Timestamp, Transition};
use crate::store::{Changeset, LoggedPatch, MapSnapshot, MissionCounters, StoreError};

/// Writes a group of changesets, in order, inside the transaction open on
/// `tx`. Robot records and mission counters are written whole, so only the
/// last of each in the group is written, once, after everything they may
/// refer to.
pub(super) async fn group(tx: &mut SqliteConnection, changesets: &[Changeset]) -> Result<(), StoreError> {
    let mut robots: BTreeMap<RobotId, &RobotRecord> = BTreeMap::new();
    let mut counters: BTreeMap<MissionId, (&MissionCounters, Timestamp)> = BTreeMap::new();
    let mut patches = Vec::new();
    for changes in changesets {
        let now = changes.at.unwrap_or_else(Timestamp::now);
        body(tx, changes, now).await?;
        robots.extend(changes.robots.iter().map(|r| (r.id, r)));
        counters.extend(changes.mission.iter().map(|m| (m.id, (m, now))));
        patches.extend(changes.patches.iter().map(|p| (p, now)));
    }
    // Many rows per statement: each statement is a round trip to SQLite's thread.
    for chunk in statement_chunks(&patches) {
        write_patches(tx, chunk).await?;
    }
    let robots: Vec<&RobotRecord> = robots.into_values().collect();
    for chunk in statement_chunks(&robots) {
        write_robots(tx, chunk).await?;
    }
    for (m, now) in counters.into_values() {
        write_counters(tx, m, now).await?;
    }
    Ok(())
}

/// Most rows written by one statement (SQLite takes at most 32 766
/// parameters; a robot record has 16).
const MAX_ROWS_PER_STATEMENT: usize = 256;

/// `rows` in chunks whose lengths are powers of two, largest first, at most
/// [`MAX_ROWS_PER_STATEMENT`]. A statement's text depends on its row count,
/// and sqlx keeps the last 100 texts prepared per connection: with a chunk
/// of any length, groups of 1 to 256 changesets gave hundreds of texts, and
/// preparing them took 6 % of the executive's CPU at full map-update load.
/// Powers of two make nine texts per statement, prepared once.
fn statement_chunks<T>(rows: &[T]) -> impl Iterator<Item = &[T]> {
    let mut rest = rows;
    std::iter::from_fn(move || {
        if rest.is_empty() {
            return None;
        }
        let length = MAX_ROWS_PER_STATEMENT.min(1 << rest.len().ilog2());
        let (chunk, after) = rest.split_at(length);
        rest = after;
        Some(chunk)
    })
}

/// Appends map patches to the log, in order, in one statement.
async fn write_patches(tx: &mut SqliteConnection, patches: &[(&LoggedPatch, Timestamp)]) -> Result<(), StoreError> {
    let mut insert = sqlx::QueryBuilder::<sqlx::Sqlite>::new(
        "INSERT INTO map_patches (mission_id, robot_id, seq, x, y, width, height, cells, cells_format, received_at) ",
    );
    insert.push_values(patches, |mut row, (logged, now)| {
        let rect = logged.patch.rect();
        row.push("(SELECT mission_id FROM robots WHERE id = ")
            .push_bind_unseparated(logged.robot_id as i64)
            .push_unseparated(")")
            .push_bind(logged.robot_id as i64)
            .push_bind(logged.seq as i64)
            .push_bind(i64::from(rect.x))
            .push_bind(i64::from(rect.y))
            .push_bind(i64::from(rect.width))
            .push_bind(i64::from(rect.height))
            .push_bind(encode_cells(&logged.patch))
            .push_bind(CELLS_LZ4)
            .push_bind(now.millis());
    });
    insert.build().execute(&mut *tx).await?;
    Ok(())
}

/// Replaces a mission's map snapshot by a newer one. An older snapshot
/// than the stored one changes nothing.
async fn write_snapshot(tx: &mut SqliteConnection, snapshot: &MapSnapshot, now: Timestamp) -> Result<(), StoreError> {
    sqlx::query(
        "INSERT INTO map_snapshots (mission_id, through_patch_id, folded, state, raw_bytes, taken_at)
         VALUES (?1, ?2, ?3, ?4, ?5, ?6)
         ON CONFLICT (mission_id) DO UPDATE SET through_patch_id = excluded.through_patch_id,
             folded = excluded.folded, state = excluded.state, raw_bytes = excluded.raw_bytes,
             taken_at = excluded.taken_at
         WHERE excluded.through_patch_id > map_snapshots.through_patch_id",
    )
    .bind(snapshot.mission_id as i64)
    .bind(snapshot.through_patch_id as i64)
    .bind(snapshot.folded as i64)
    .bind(&snapshot.bytes)
    .bind(snapshot.raw_bytes as i64)
    .bind(now.millis())
    .execute(&mut *tx)
    .await?;
    Ok(())
}

/// Removes at most `limit` of a mission's oldest patches that its stored
/// snapshot folds: never one it does not.
async fn forget_folded(tx: &mut SqliteConnection, mission_id: MissionId, limit: u32) -> Result<(), StoreError> {
    sqlx::query(
        "DELETE FROM map_patches WHERE id IN (
             SELECT id FROM map_patches WHERE mission_id = ?1
                 AND id <= (SELECT through_patch_id FROM map_snapshots WHERE mission_id = ?1)
             ORDER BY id LIMIT ?2)",
    )
    .bind(mission_id as i64)
    .bind(i64::from(limit))
    .execute(&mut *tx)
    .await?;
    Ok(())
}

/// Writes robot records whole, in one statement.
async fn write_robots(tx: &mut SqliteConnection, robots: &[&RobotRecord]) -> Result<(), StoreError> {
    let mut update = sqlx::QueryBuilder::<sqlx::Sqlite>::new(
        "UPDATE robots SET sensor_range_m = v.column2, field_of_view_rad = v.column3, speed_mps = v.column4,
                footprint_radius_m = v.column5, state = v.column6, pose_x = v.column7, pose_y = v.column8,
                pose_theta = v.column9, last_map_seq = v.column10, distance_m = v.column11,
                assignment_version = v.column12, assigned_distance_m = v.column13, current_task_id = v.column14,
                last_seen = v.column15, lost = v.column16
         FROM (",
    );
    update.push_values(robots, |mut row, robot| {
        row.push_bind(robot.id as i64)
            .push_bind(robot.capabilities.sensor_range_m)
            .push_bind(robot.capabilities.field_of_view_rad)
            .push_bind(robot.capabilities.speed_mps)
            .push_bind(robot.capabilities.footprint_radius_m)
            .push_bind(robot.state.as_str())
            .push_bind(robot.pose.position.x)
            .push_bind(robot.pose.position.y)
            .push_bind(robot.pose.heading)
            .push_bind(robot.last_map_seq as i64)
            .push_bind(robot.distance_m)
            .push_bind(robot.assignment_version as i64)
            .push_bind(robot.assigned_distance_m)
            .push_bind(robot.current_task.map(|t| t as i64))
            .push_bind(robot.last_seen.millis())
            .push_bind(i64::from(robot.lost));
    });
    update.push(") AS v WHERE robots.id = v.column1");
    update.build().execute(&mut *tx).await?;
    Ok(())
}

/// Everything of a changeset but its robot records and mission counters.
async fn body(tx: &mut SqliteConnection, changes: &Changeset, now: Timestamp) -> Result<(), StoreError> {
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
        .bind(exploration_proto::label_runs::encode(&stored.segmentation.labels))
        .bind(segments_json(&stored.segmentation))
        .bind(critical_points_json(&stored.segmentation))
        .execute(&mut *tx)
        .await?;
    }
    if let Some((mission_id, rooms)) = &changes.given_segmentation {
        match rooms {
            Some(rooms) => {
                sqlx::query(
                    "INSERT INTO given_segmentations (mission_id, label_runs, set_at) VALUES (?1, ?2, ?3)
                     ON CONFLICT (mission_id) DO UPDATE SET label_runs = excluded.label_runs, set_at = excluded.set_at",
                )
                .bind(*mission_id as i64)
                .bind(exploration_proto::label_runs::encode(rooms))
                .bind(changes.at.unwrap_or_else(Timestamp::now).millis())
                .execute(&mut *tx)
                .await?;
            }
            None => {
                sqlx::query("DELETE FROM given_segmentations WHERE mission_id = ?1")
                    .bind(*mission_id as i64)
                    .execute(&mut *tx)
                    .await?;
            }
        }
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
    if let Some(snapshot) = &changes.snapshot {
        write_snapshot(tx, snapshot, now).await?;
    }
    if let Some((mission_id, limit)) = changes.forget_folded {
        forget_folded(tx, mission_id, limit).await?;
    }
    Ok(())
}

async fn write_counters(tx: &mut SqliteConnection, m: &MissionCounters, now: Timestamp) -> Result<(), StoreError> {
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rows_are_written_in_chunks_of_nine_lengths_at_most() {
        let mut lengths = std::collections::BTreeSet::new();
        for n in 0..2_000usize {
            let rows: Vec<usize> = (0..n).collect();
            let chunks: Vec<&[usize]> = statement_chunks(&rows).collect();
            assert_eq!(chunks.concat(), rows, "every row once, in order");
            for chunk in &chunks {
                assert!(chunk.len().is_power_of_two() && chunk.len() <= MAX_ROWS_PER_STATEMENT);
                lengths.insert(chunk.len());
            }
            if n <= MAX_ROWS_PER_STATEMENT {
                assert_eq!(chunks.len(), n.count_ones() as usize, "{n} rows");
            }
        }
        assert_eq!(lengths.len(), 9);
    }
}
