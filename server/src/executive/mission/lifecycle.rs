//! What keeps a fleet honest: leases, stall detection, blacklisted targets,
//! and how operator tasks that follow the frontier (regions, pins) end.
//!
//! The failures exploration packages are known for: robots that go silent
//! and keep their targets (leases), robots stuck on one goal forever (stall
//! detection, explore_lite's `progress_timeout`), targets tried forever or
//! given up forever (a per-robot blacklist whose entries expire when the map
//! around them changes).

use std::sync::atomic::AtomicU64;

use tokio::time::Instant;

use exploration::completion::LeftReason;
use exploration::cost::{CostCache, TraversalKind};
use exploration::frontier::FrontierCluster;
use exploration::grid::{Cell, CellClass, CellRect, GridFrame, OccupancyGrid};
use exploration::policy::{RobotView, Target};

use super::{JobOutcome, Mission, TaskDraft, transition};
use crate::domain::{
    Actor, BlacklistEntry, LeftoverReason, MissionEvent, RobotId, TaskKind, TaskRecord, TaskState, Timestamp,
};
use crate::store::Changeset;

/// A robot counts as progressing when it gets this much closer to its target, metres.
const PROGRESS_M: f64 = 0.25;
/// Radius of the neighbourhood whose change lifts a blacklist entry, metres.
const BLACKLIST_WINDOW_M: f64 = 1.0;
/// Radius around a blacklisted target that the robot is not sent to, metres.
const EXCLUSION_M: f64 = 0.5;
/// Other entries of the same robot this close widen an entry's exclusion.
const ESCALATION_M: f64 = 2.0;

/// A working robot's progress: how close it has come to its current
/// target, and when and where it last made progress. A new target keeps the
/// clock running, so that replanning cannot hide a robot that does not move.
#[derive(Debug, Clone, Copy)]
pub(super) struct Progress {
    task: crate::domain::TaskId,
    best_m: f64,
    since: Instant,
    at: exploration::math::Point2,
}

/// A blacklist entry with the state of the map around it when it was made.
#[derive(Debug, Clone)]
pub(super) struct Blacklisted {
    pub(super) entry: BlacklistEntry,
    /// (free, occupied) cells in the window around the target.
    signature: (u32, u32),
}

/// The cells around a blacklisted target that the robot is not sent to.
/// Failures that repeat in one place widen it: each other live entry of the
/// robot within 2 m doubles the radius (up to 16 times), so a robot that
/// cannot get into an area is not sent to each of its frontier cells in turn.
pub(super) fn exclusion(frame: &GridFrame, cell: Cell, robot_entries: &[Cell]) -> CellRect {
    let near = robot_entries
        .iter()
        .filter(|&&other| other != cell && other.distance(cell) * frame.resolution <= ESCALATION_M)
        .count()
        .min(4);
    let radius = (EXCLUSION_M * f64::from(1u32 << near) / frame.resolution).ceil().max(2.0) as u32;
    CellRect::new(cell.x - radius as i32, cell.y - radius as i32, 2 * radius + 1, 2 * radius + 1)
}

fn window(frame: &GridFrame, cell: Cell) -> Option<CellRect> {
    let radius = (BLACKLIST_WINDOW_M / frame.resolution).ceil() as u32;
    frame.clip(&CellRect::new(cell.x - radius as i32, cell.y - radius as i32, 2 * radius + 1, 2 * radius + 1))
}

fn signature(grid: &OccupancyGrid, cell: Cell) -> (u32, u32) {
    let Some(window) = window(grid.frame(), cell) else { return (0, 0) };
    window.cells().fold((0, 0), |(free, occupied), c| match grid.class(c) {
        CellClass::Free => (free + 1, occupied),
        CellClass::Occupied => (free, occupied + 1),
        CellClass::Unknown | CellClass::Uncertain => (free, occupied),
    })
}

/// The domain's name for a reason the completion analysis gives.
pub(super) fn leftover_reason(reason: LeftReason) -> LeftoverReason {
    match reason {
        LeftReason::TooSmall => LeftoverReason::TooSmall,
        LeftReason::Forbidden => LeftoverReason::Forbidden,
        LeftReason::Blacklisted => LeftoverReason::Blacklisted,
        LeftReason::TooNarrow => LeftoverReason::TooNarrow,
        LeftReason::Disconnected => LeftoverReason::Disconnected,
    }
}

/// The next frontier of an operator's region for a robot: the cheapest
/// frontier cell inside the region (and outside forbidden ones) on the
/// robot's own cost map; `None` when none is reachable.
pub(super) fn region_target(
    clusters: &[FrontierCluster],
    robot: &RobotView,
    region: CellRect,
    forbidden: &[CellRect],
    costs: &mut CostCache<'_>,
) -> Option<Target> {
    let map = costs.cost_map(TraversalKind::free_space(robot.capabilities.footprint_radius_m), robot.cell);
    clusters
        .iter()
        .flat_map(|c| c.cells.iter().copied())
        .filter(|&c| region.contains(c) && !forbidden.iter().any(|r| r.contains(c)))
        .filter_map(|c| robot.cost_to(&map, c).map(|cost| (c, cost)))
        .min_by(|a, b| a.1.total_cmp(&b.1).then(a.0.cmp(&b.0)))
        .map(|(cell, cost)| Target { cell, utility: -cost, path_cost: cost, gain_region: Some(region) })
}

impl Mission {
    /// Takes a stored or new blacklist entry in, noting the map around it.
    pub(super) fn add_blacklisted(&mut self, entry: BlacklistEntry) {
        let signature = signature(self.fusion.grid(), entry.cell);
        if let Some(slot) = self.robots.get_mut(&entry.robot_id) {
            slot.blacklist.retain(|b| b.entry.cell != entry.cell);
            slot.blacklist.push(Blacklisted { entry, signature });
        }
    }

    /// The blacklist entry a failed task leaves, for tasks whose target is a
    /// frontier (explore, pin, an operator's region).
    pub(super) fn blacklist_entry(&self, task: &TaskRecord, cause: &str, now: Timestamp) -> Option<BlacklistEntry> {
        let on_frontier = match task.kind {
            TaskKind::Explore | TaskKind::Pin => true,
            TaskKind::Goto => task.gain_region.is_some(),
            TaskKind::Hold | TaskKind::Home => false,
        };
        let cell = self.record.spec.frame.cell_from_world(&task.target).filter(|_| on_frontier)?;
        Some(BlacklistEntry { robot_id: task.robot_id, cell, cause: cause.to_owned(), created_at: now })
    }

    /// Entries whose neighbourhood changed since they were made: the way
    /// there may be open now.
    pub(super) fn expired_blacklist(&self) -> Vec<(RobotId, Cell)> {
        let grid = self.fusion.grid();
        self.robots
            .values()
            .flat_map(|slot| slot.blacklist.iter().map(move |b| (slot.record.id, b)))
            .filter(|(_, b)| signature(grid, b.entry.cell) != b.signature)
            .map(|(robot, b)| (robot, b.entry.cell))
            .collect()
    }

    /// Records that a robot reported at `now`: renews its lease and follows
    /// its progress towards its target.
    pub(crate) fn heard_from(&mut self, id: RobotId, now: Instant) {
        let Some(slot) = self.robots.get(&id) else { return };
        let task = slot.record.current_task.and_then(|t| self.open_tasks.get(&t)).map(|t| (t.id, t.target));
        let position = slot.record.pose.position;
        let Some(slot) = self.robots.get_mut(&id) else { return };
        slot.last_heard = now;
        slot.progress = task.map(|(task, target)| {
            let distance = (target - position).norm();
            match slot.progress {
                // Progress: closer to this target, or moved anywhere.
                Some(p)
                    if (p.task == task && distance <= p.best_m - PROGRESS_M)
                        || (position - p.at).norm() >= PROGRESS_M =>
                {
                    Progress { task, best_m: distance, since: now, at: position }
                }
                Some(p) if p.task == task => p,
                Some(p) => Progress { task, best_m: distance, ..p },
                None => Progress { task, best_m: distance, since: now, at: position },
            }
        });
    }

    /// Robots whose lease ran out lose their task; robots that made no
    /// progress for the stall time have it failed and the target
    /// blacklisted for them. `None` when nothing is due.
    pub(crate) fn prepare_sweep(&self, now: Instant, at: Timestamp) -> Option<Changeset> {
        let lifecycle = self.record.spec.lifecycle;
        let mut changes = Changeset { at: Some(at), ..Changeset::default() };
        for slot in self.robots.values() {
            let robot = &slot.record;
            if robot.lost {
                continue;
            }
            let task = robot.current_task.and_then(|t| self.open_tasks.get(&t));
            let silent = now.saturating_duration_since(slot.last_heard);
            if silent >= lifecycle.lease {
                let cause = format!(
                    "no report for {:.0} s (lease {:.0} s)",
                    silent.as_secs_f64(),
                    lifecycle.lease.as_secs_f64()
                );
                let mut next = robot.clone();
                next.lost = true;
                if let Some(task) = task {
                    changes.task_changes.push(transition(task, TaskState::Released, &cause, Actor::Lease, at));
                    next.current_task = None;
                }
                next.assignment_version += 1;
                changes.robots.push(next);
                changes.events.push(self.event("robot_lost", format!("{}: {cause}", robot.label()), "lease", at));
                continue;
            }
            let Some((task, progress)) = task.zip(slot.progress) else { continue };
            if task.kind == TaskKind::Hold || self.record.paused {
                continue;
            }
            if now.saturating_duration_since(progress.since) >= lifecycle.stall {
                let cause = format!("no progress towards the target for {:.0} s", lifecycle.stall.as_secs_f64());
                changes.blacklisted.extend(self.blacklist_entry(task, &cause, at));
                changes.task_changes.push(transition(task, TaskState::Failed, &cause, Actor::Executive, at));
                let mut next = robot.clone();
                next.current_task = None;
                next.assignment_version += 1;
                changes.robots.push(next);
            }
        }
        (!changes.robots.is_empty()).then_some(changes)
    }

    /// A mission event.
    pub(super) fn event(&self, kind: &str, detail: String, actor: &str, at: Timestamp) -> MissionEvent {
        MissionEvent { id: 0, mission_id: self.record.id, at, kind: kind.to_owned(), detail, actor: actor.to_owned() }
    }

    /// Operator tasks that follow the frontier: a region's robot moves on to
    /// the region's next frontier, or back to the pool when none is left; a
    /// pinned robot goes back to the pool once its frontier is explored.
    pub(super) fn prepare_overrides(
        &self,
        outcome: &JobOutcome,
        now: Timestamp,
        task_ids: &AtomicU64,
        changes: &mut Changeset,
    ) {
        let frame = self.record.spec.frame;
        let end = |changes: &mut Changeset, task: &TaskRecord, next: Option<TaskRecord>, cause: &str| {
            let Some(slot) = self.robots.get(&task.robot_id) else { return };
            let state = if next.is_some() { TaskState::Preempted } else { TaskState::Reached };
            changes.task_changes.push(transition(task, state, cause, Actor::Executive, now));
            let mut record = slot.record.clone();
            record.current_task = next.as_ref().map(|t| t.id);
            record.assignment_version += 1;
            changes.new_tasks.extend(next);
            changes.robots.retain(|r| r.id != record.id);
            changes.robots.push(record);
        };
        for (robot, target) in &outcome.region_targets {
            let Some(task) =
                self.robots.get(robot).and_then(|s| s.record.current_task).and_then(|t| self.open_tasks.get(&t))
            else {
                continue;
            };
            match target {
                None => end(changes, task, None, "no reachable frontier left in the region"),
                Some(t) if frame.cell_from_world(&task.target) != Some(t.cell) => {
                    let draft = TaskDraft {
                        kind: TaskKind::Goto,
                        target: frame.world_from_cell(t.cell),
                        created_by: task.created_by.clone(),
                        note: task.note.clone(),
                        policy: task.policy.clone(),
                        utility: t.utility,
                        path_cost: t.path_cost,
                        gain_region: task.gain_region,
                    };
                    let next = self.open_task(
                        *robot,
                        draft,
                        "next frontier of the region",
                        Actor::Executive,
                        "",
                        now,
                        task_ids,
                    );
                    end(changes, task, Some(next), "next frontier of the region");
                }
                Some(_) => {}
            }
        }
        for task in self.open_tasks.values().filter(|t| t.kind == TaskKind::Pin) {
            let explored = frame.cell_from_world(&task.target).is_none_or(|c| !self.frontier.contains(c));
            if explored && self.robots.get(&task.robot_id).is_some_and(|s| s.record.current_task == Some(task.id)) {
                end(changes, task, None, "pinned frontier explored");
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use exploration::math::Point2;

    #[test]
    fn repeated_failures_in_one_place_widen_the_exclusion() {
        let frame = GridFrame::new(0.1, Point2::new(0.0, 0.0), 200, 200);
        let target = Cell::new(100, 100);
        // Alone: 0.5 m around the target.
        assert_eq!(exclusion(&frame, target, &[target]).width, 11);
        // Two more failures within 2 m: four times as wide.
        let nearby = [target, Cell::new(110, 100), Cell::new(100, 115)];
        assert_eq!(exclusion(&frame, target, &nearby).width, 41);
        // Failures far away do not count.
        let far = [target, Cell::new(150, 100), Cell::new(100, 170)];
        assert_eq!(exclusion(&frame, target, &far).width, 11);
        // At most 16 times.
        let many: Vec<Cell> = (0..10).map(|i| Cell::new(100 + i, 101)).chain([target]).collect();
        assert_eq!(exclusion(&frame, target, &many).width, 2 * 80 + 1);
    }
}
