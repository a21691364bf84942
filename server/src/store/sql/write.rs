//! Changesets, written inside a transaction: the same statements for
//! every engine ([`super::statement`]).

use std::collections::BTreeMap;

use super::rows::{critical_points_json, encode_cells, leftovers_json, segments_json};
use super::statement::{Statement, Transaction};
use crate::domain::{MissionId, RobotId, RobotRecord, TaskId, TaskState, Timestamp, Transition};
use crate::store::{Changeset, Fence, LoggedPatch, MapSnapshot, MissionCounters, StoreError};

/// Writes a group of changesets, in order, inside the transaction open on
/// `tx`. Robot records and mission counters are written whole, so only the
/// last of each in the group is written, once, after everything they may
/// refer to.
pub(super) async fn group(tx: &mut impl Transaction, changesets: &[Changeset]) -> Result<(), StoreError> {
    let fences: std::collections::BTreeSet<(MissionId, u64)> =
        changesets.iter().filter_map(|c| c.fence).map(|f| (f.mission_id, f.token)).collect();
    for (mission_id, token) in fences {
        check_fence(tx, Fence { mission_id, token }).await?;
    }
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
    // Many rows per statement: each statement is a round trip to the database.
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
/// parameters, PostgreSQL 65 535; a robot record has 16).
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

/// Refuses to write unless the mission's lease still carries the writer's
/// token. The no-op update locks the lease row until the transaction ends
/// (PostgreSQL; SQLite has one writer at a time): a claim that would change
/// the token waits for this write, then changes it; a claim that changed it
/// first makes this write fail.
pub(super) async fn check_fence(tx: &mut impl Transaction, fence: Fence) -> Result<(), StoreError> {
    let check = Statement::new("UPDATE mission_leases SET token = token WHERE mission_id = $1 AND token = $2");
    match tx.execute(check.int(fence.mission_id as i64).int(fence.token as i64)).await? {
        0 => Err(StoreError::Fenced { mission_id: fence.mission_id }),
        _ => Ok(()),
    }
}

/// `(?, ?, …), (…)`: `rows` rows of `columns` parameters each, the first
/// of each row inside `first`'s text (`?` marks where), for a statement of
/// positional parameters ([`Statement::positional`]).
fn values_list(rows: usize, columns: usize, first: &str) -> String {
    let rest = ", ?".repeat(columns - 1);
    let row = format!("({first}{rest})");
    vec![row; rows].join(", ")
}

/// Appends map patches to the log, in order, in one statement.
async fn write_patches(tx: &mut impl Transaction, patches: &[(&LoggedPatch, Timestamp)]) -> Result<(), StoreError> {
    let mut insert = Statement::positional(format!(
        "INSERT INTO map_patches (mission_id, robot_id, seq, x, y, width, height, cells, cells_format, received_at)
         VALUES {}",
        values_list(patches.len(), 10, "(SELECT mission_id FROM robots WHERE id = ?)")
    ));
    for (logged, now) in patches {
        let rect = logged.patch.rect();
        let (cells, format) = encode_cells(&logged.patch);
        insert = insert
            .int(logged.robot_id as i64)
            .int(logged.robot_id as i64)
            .int(logged.seq as i64)
            .int(i64::from(rect.x))
            .int(i64::from(rect.y))
            .int(i64::from(rect.width))
            .int(i64::from(rect.height))
            .bytes(cells)
            .int(format)
            .int(now.millis());
    }
    tx.execute(insert).await?;
    Ok(())
}

/// Replaces a mission's map snapshot by a newer one. An older snapshot
/// than the stored one changes nothing.
async fn write_snapshot(tx: &mut impl Transaction, snapshot: &MapSnapshot, now: Timestamp) -> Result<(), StoreError> {
    // The compactor folds outside the mission's lock: a fold of a mission
    // deleted meanwhile must not leave a snapshot that no purge removes.
    let upsert = Statement::new(
        "INSERT INTO map_snapshots (mission_id, through_patch_id, folded, state, raw_bytes, taken_at)
         SELECT $1, $2, $3, $4, $5, $6 FROM missions WHERE id = $1 AND deleted_at IS NULL
         ON CONFLICT (mission_id) DO UPDATE SET through_patch_id = excluded.through_patch_id,
             folded = excluded.folded, state = excluded.state, raw_bytes = excluded.raw_bytes,
             taken_at = excluded.taken_at
         WHERE excluded.through_patch_id > map_snapshots.through_patch_id",
    );
    tx.execute(
        upsert
            .int(snapshot.mission_id as i64)
            .int(snapshot.through_patch_id as i64)
            .int(snapshot.folded as i64)
            .bytes(snapshot.bytes.clone())
            .int(snapshot.raw_bytes as i64)
            .int(now.millis()),
    )
    .await?;
    Ok(())
}

/// Removes at most `limit` of a mission's oldest patches that its stored
/// snapshot folds: never one it does not.
async fn forget_folded(tx: &mut impl Transaction, mission_id: MissionId, limit: u32) -> Result<(), StoreError> {
    let delete = Statement::new(
        "DELETE FROM map_patches WHERE id IN (
             SELECT id FROM map_patches WHERE mission_id = $1
                 AND id <= (SELECT through_patch_id FROM map_snapshots WHERE mission_id = $1)
             ORDER BY id LIMIT $2)",
    );
    tx.execute(delete.int(mission_id as i64).int(i64::from(limit))).await?;
    Ok(())
}

/// Writes robot records whole, in one statement.
async fn write_robots(tx: &mut impl Transaction, robots: &[&RobotRecord]) -> Result<(), StoreError> {
    let mut update = Statement::positional(format!(
        "UPDATE robots SET sensor_range_m = v.column2, field_of_view_rad = v.column3, speed_mps = v.column4,
                footprint_radius_m = v.column5, state = v.column6, pose_x = v.column7, pose_y = v.column8,
                pose_theta = v.column9, last_map_seq = v.column10, distance_m = v.column11,
                assignment_version = v.column12, assigned_distance_m = v.column13, current_task_id = v.column14,
                last_seen = v.column15, lost = v.column16
         FROM (VALUES {}) AS v WHERE robots.id = v.column1",
        values_list(robots.len(), 16, "?")
    ));
    for robot in robots {
        update = update
            .int(robot.id as i64)
            .real(robot.capabilities.sensor_range_m)
            .real(robot.capabilities.field_of_view_rad)
            .real(robot.capabilities.speed_mps)
            .real(robot.capabilities.footprint_radius_m)
            .text(robot.state.as_str())
            .real(robot.pose.position.x)
            .real(robot.pose.position.y)
            .real(robot.pose.heading)
            .int(robot.last_map_seq as i64)
            .real(robot.distance_m)
            .int(robot.assignment_version as i64)
            .real(robot.assigned_distance_m)
            .int(robot.current_task.map(|t| t as i64))
            .int(robot.last_seen.millis())
            .int(i64::from(robot.lost));
    }
    tx.execute(update).await?;
    Ok(())
}

/// Everything of a changeset but its robot records and mission counters.
async fn body(tx: &mut impl Transaction, changes: &Changeset, now: Timestamp) -> Result<(), StoreError> {
    // Tasks first: robots refer to them.
    for task in &changes.new_tasks {
        let insert = Statement::new(
            "INSERT INTO tasks (id, mission_id, robot_id, target_x, target_y, state, policy, utility, path_cost,
                                created_at, updated_at, gain_x, gain_y, gain_width, gain_height, kind,
                                created_by, note)
             VALUES ($1, $2, $3, $4, $5, $6, $7, $8, $9, $10, $11, $12, $13, $14, $15, $16, $17, $18)",
        );
        let gain = |side: fn(&exploration::grid::CellRect) -> i64| task.gain_region.as_ref().map(side);
        tx.execute(
            insert
                .int(task.id as i64)
                .int(task.mission_id as i64)
                .int(task.robot_id as i64)
                .real(task.target.x)
                .real(task.target.y)
                .text(task.state.as_str())
                .text(&task.policy)
                .real(task.utility)
                .real(task.path_cost)
                .int(task.created_at.millis())
                .int(task.updated_at.millis())
                .int(gain(|r| i64::from(r.x)))
                .int(gain(|r| i64::from(r.y)))
                .int(gain(|r| i64::from(r.width)))
                .int(gain(|r| i64::from(r.height)))
                .text(task.kind.as_str())
                .text(&task.created_by)
                .text(&task.note),
        )
        .await?;
        for t in &task.transitions {
            write_transition(tx, task.id, t).await?;
        }
    }
    for change in &changes.task_changes {
        let update = Statement::new("UPDATE tasks SET state = $1, updated_at = $2 WHERE id = $3");
        tx.execute(update.text(change.state.as_str()).int(change.transition.at.millis()).int(change.task_id as i64))
            .await?;
        write_transition(tx, change.task_id, &change.transition).await?;
    }
    if let Some((mission_id, policy)) = &changes.policy {
        let params: BTreeMap<&str, f64> = policy.params().clone();
        let params = serde_json::to_string(&params).map_err(|e| StoreError::Corrupt(e.to_string()))?;
        let update = Statement::new("UPDATE missions SET policy = $1, policy_params = $2 WHERE id = $3");
        tx.execute(update.text(policy.name()).text(&params).int(*mission_id as i64)).await?;
    }
    for event in &changes.events {
        let insert = Statement::new(
            "INSERT INTO mission_events (mission_id, at, kind, detail, actor) VALUES ($1, $2, $3, $4, $5)",
        );
        tx.execute(
            insert
                .int(event.mission_id as i64)
                .int(event.at.millis())
                .text(&event.kind)
                .text(&event.detail)
                .text(&event.actor),
        )
        .await?;
    }
    if let Some((mission_id, stored)) = &changes.segmentation {
        let upsert = Statement::new(
            "INSERT INTO segmentations (mission_id, computed_at, labels, segments, critical_points)
             VALUES ($1, $2, $3, $4, $5)
             ON CONFLICT (mission_id) DO UPDATE SET computed_at = excluded.computed_at, labels = excluded.labels,
                 segments = excluded.segments, critical_points = excluded.critical_points",
        );
        tx.execute(
            upsert
                .int(*mission_id as i64)
                .int(stored.computed_at.millis())
                .bytes(exploration_proto::label_runs::encode(&stored.segmentation.labels))
                .text(&segments_json(&stored.segmentation))
                .text(&critical_points_json(&stored.segmentation)),
        )
        .await?;
    }
    if let Some((mission_id, rooms)) = &changes.given_segmentation {
        let statement = match rooms {
            Some(rooms) => Statement::new(
                "INSERT INTO given_segmentations (mission_id, label_runs, set_at) VALUES ($1, $2, $3)
                 ON CONFLICT (mission_id) DO UPDATE SET label_runs = excluded.label_runs, set_at = excluded.set_at",
            )
            .int(*mission_id as i64)
            .bytes(exploration_proto::label_runs::encode(rooms))
            .int(changes.at.unwrap_or_else(Timestamp::now).millis()),
            None => Statement::new("DELETE FROM given_segmentations WHERE mission_id = $1").int(*mission_id as i64),
        };
        tx.execute(statement).await?;
    }
    for entry in &changes.blacklisted {
        let upsert = Statement::new(
            "INSERT INTO blacklist (robot_id, cell_x, cell_y, cause, created_at) VALUES ($1, $2, $3, $4, $5)
             ON CONFLICT (robot_id, cell_x, cell_y) DO UPDATE SET cause = excluded.cause,
                 created_at = excluded.created_at",
        );
        tx.execute(
            upsert
                .int(entry.robot_id as i64)
                .int(i64::from(entry.cell.x))
                .int(i64::from(entry.cell.y))
                .text(&entry.cause)
                .int(entry.created_at.millis()),
        )
        .await?;
    }
    for (robot, cell) in &changes.unblacklisted {
        let delete = Statement::new("DELETE FROM blacklist WHERE robot_id = $1 AND cell_x = $2 AND cell_y = $3");
        tx.execute(delete.int(*robot as i64).int(i64::from(cell.x)).int(i64::from(cell.y))).await?;
    }
    for region in &changes.forbidden {
        let insert = Statement::new(
            "INSERT INTO forbidden_regions (id, mission_id, min_x, min_y, max_x, max_y, actor, reason, created_at)
             VALUES ($1, $2, $3, $4, $5, $6, $7, $8, $9)",
        );
        tx.execute(
            insert
                .int(region.id as i64)
                .int(region.mission_id as i64)
                .real(region.min.x)
                .real(region.min.y)
                .real(region.max.x)
                .real(region.max.y)
                .text(&region.actor)
                .text(&region.reason)
                .int(region.created_at.millis()),
        )
        .await?;
    }
    for region in &changes.allowed {
        let update = Statement::new("UPDATE forbidden_regions SET allowed_at = $1 WHERE id = $2");
        tx.execute(update.int(now.millis()).int(*region as i64)).await?;
    }
    for (robot, hash) in &changes.robot_tokens {
        let update = Statement::new("UPDATE robots SET token_sha256 = $1 WHERE id = $2");
        tx.execute(update.text(hash).int(*robot as i64)).await?;
    }
    if let Some((robot, bids)) = &changes.bids {
        tx.execute(Statement::new("DELETE FROM bids WHERE robot_id = $1").int(*robot as i64)).await?;
        for (ordinal, bid) in bids.iter().enumerate() {
            let insert = Statement::new(
                "INSERT INTO bids (robot_id, ordinal, target_x, target_y, path_cost, information_gain,
                                   region_min_x, region_min_y, region_max_x, region_max_y, submitted_at)
                 VALUES ($1, $2, $3, $4, $5, $6, $7, $8, $9, $10, $11)",
            );
            tx.execute(
                insert
                    .int(*robot as i64)
                    .int(ordinal as i64)
                    .real(bid.target.x)
                    .real(bid.target.y)
                    .real(bid.path_cost)
                    .real(bid.information_gain)
                    .real(bid.gain_region.0.x)
                    .real(bid.gain_region.0.y)
                    .real(bid.gain_region.1.x)
                    .real(bid.gain_region.1.y)
                    .int(now.millis()),
            )
            .await?;
        }
    }
    if let Some(snapshot) = &changes.snapshot {
        write_snapshot(tx, snapshot, now).await?;
    }
    if let Some((mission_id, limit)) = changes.forget_folded {
        forget_folded(tx, mission_id, limit).await?;
    }
    if let Some(mission_id) = changes.deleted {
        mark_deleted(tx, mission_id, now).await?;
    }
    Ok(())
}

/// Hides a mission from every read and voids its robots' tokens; its rows
/// are purged later ([`purge_step`]), the largest task and region
/// identities it gave kept on its row.
async fn mark_deleted(tx: &mut impl Transaction, mission_id: MissionId, now: Timestamp) -> Result<(), StoreError> {
    let hide = Statement::new(
        "UPDATE missions SET deleted_at = $1,
                last_task_id = (SELECT MAX(id) FROM tasks WHERE mission_id = $2),
                last_region_id = (SELECT MAX(id) FROM forbidden_regions WHERE mission_id = $2)
         WHERE id = $2 AND deleted_at IS NULL",
    );
    tx.execute(hide.int(now.millis()).int(mission_id as i64)).await?;
    let void = Statement::new("UPDATE robots SET token_sha256 = NULL WHERE mission_id = $1");
    tx.execute(void.int(mission_id as i64)).await?;
    Ok(())
}

/// Removes one batch of at most `limit` rows (of the largest tables; the
/// others at the end, at most a few per robot) of deleted mission
/// `mission_id`, children before their parents; the last batch marks the
/// mission purged.
pub(super) async fn purge_step(tx: &mut impl Transaction, mission_id: MissionId, limit: u32) -> Result<(), StoreError> {
    let id = mission_id as i64;
    let limit = i64::from(limit.max(1));
    let patches = Statement::new(
        "DELETE FROM map_patches WHERE id IN (SELECT id FROM map_patches WHERE mission_id = $1 ORDER BY id LIMIT $2)",
    );
    if tx.execute(patches.int(id).int(limit)).await? > 0 {
        return Ok(());
    }
    let some_tasks = "(SELECT id FROM tasks WHERE mission_id = $1 ORDER BY id LIMIT $2)";
    let transitions = Statement::new(format!("DELETE FROM task_transitions WHERE task_id IN {some_tasks}"));
    tx.execute(transitions.int(id).int(limit)).await?;
    let tasks = Statement::new(format!("DELETE FROM tasks WHERE id IN {some_tasks}"));
    if tx.execute(tasks.int(id).int(limit)).await? > 0 {
        return Ok(());
    }
    let events = Statement::new(
        "DELETE FROM mission_events WHERE id IN
             (SELECT id FROM mission_events WHERE mission_id = $1 ORDER BY id LIMIT $2)",
    );
    if tx.execute(events.int(id).int(limit)).await? > 0 {
        return Ok(());
    }
    for sql in [
        "DELETE FROM bids WHERE robot_id IN (SELECT id FROM robots WHERE mission_id = $1)",
        "DELETE FROM blacklist WHERE robot_id IN (SELECT id FROM robots WHERE mission_id = $1)",
        "DELETE FROM forbidden_regions WHERE mission_id = $1",
        "DELETE FROM segmentations WHERE mission_id = $1",
        "DELETE FROM given_segmentations WHERE mission_id = $1",
        "DELETE FROM map_snapshots WHERE mission_id = $1",
        "DELETE FROM mission_leases WHERE mission_id = $1",
        "DELETE FROM robots WHERE mission_id = $1",
        "UPDATE missions SET purged = 1 WHERE id = $1",
    ] {
        tx.execute(Statement::new(sql).int(id)).await?;
    }
    Ok(())
}

async fn write_counters(tx: &mut impl Transaction, m: &MissionCounters, now: Timestamp) -> Result<(), StoreError> {
    let update = Statement::new(
        "UPDATE missions SET state = $1, replans = $2, map_updates = $3, updated_at = $4, paused = $5,
                    leftovers = $6
             WHERE id = $7",
    );
    tx.execute(
        update
            .text(m.state.as_str())
            .int(m.replans as i64)
            .int(m.map_updates as i64)
            .int(now.millis())
            .int(i64::from(m.paused))
            .text(&leftovers_json(&m.leftovers))
            .int(m.id as i64),
    )
    .await?;
    Ok(())
}

async fn write_transition(tx: &mut impl Transaction, task_id: TaskId, t: &Transition) -> Result<(), StoreError> {
    let insert = Statement::new(
        "INSERT INTO task_transitions (task_id, from_state, to_state, cause, actor, at, by_name)
         VALUES ($1, $2, $3, $4, $5, $6, $7)",
    );
    tx.execute(
        insert
            .int(task_id as i64)
            .maybe_text(t.from.map(TaskState::as_str))
            .text(t.to.as_str())
            .text(&t.cause)
            .text(t.actor.as_str())
            .int(t.at.millis())
            .text(&t.by),
    )
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
