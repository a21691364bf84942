//! Replanning, the mission's side: when a plan is due (Burgard et al. 2005,
//! §II-C), what a plan made on a [`super::job::PlanningJob`] changes
//! ([`Mission::prepare_plan`]), and whether it still fits the mission it
//! comes back to. The job itself is in `job.rs`; when and where plans are
//! made is the executive's planner.

use std::sync::atomic::AtomicU64;

use tokio::time::Instant;

use exploration::grid::Cell;

use super::job::JobOutcome;
use super::{HOME_TOLERANCE_M, Mission, TaskDraft, transition};
use crate::domain::{
    Actor, BY_EXECUTIVE, BY_POLICY, Leftovers, MissionState, RobotId, StoredSegmentation, TaskId, TaskKind, TaskState,
    Timestamp,
};
use crate::store::Changeset;

/// The state a plan was made on (see [`Mission::plan_still_fits`]).
#[derive(Debug, Clone, PartialEq, Eq)]
pub(crate) struct PlanBasis {
    /// The robots whose new bids the plan took.
    fresh_bids: Vec<RobotId>,
    structure: u64,
    demands: u64,
    frontier_churn: usize,
    layer_changes: usize,
}

impl Mission {
    /// Why the mission should replan now, if it should (Burgard et al. 2005,
    /// §II-C: when a robot reached its target, or travelled or waited long
    /// enough; and when the frontier changed enough).
    pub(crate) fn replan_reason(&self, now: Instant) -> Option<String> {
        if self.robots.is_empty() || self.record.paused {
            return None;
        }
        if let Some(reason) = &self.pending_replan {
            return Some(reason.clone());
        }
        let frame = &self.record.spec.frame;
        let settings = &self.record.spec.replan;
        let scoped = self.record.spec.scoped_by_communication;
        for slot in self.robots.values() {
            let robot = &slot.record;
            if let Some(task) = robot.current_task.and_then(|t| self.open_tasks.get(&t)) {
                let on_frontier = match task.kind {
                    TaskKind::Explore | TaskKind::Pin => true,
                    TaskKind::Goto => task.gain_region.is_some(),
                    TaskKind::Hold | TaskKind::Home => false,
                };
                let explored = frame.cell_from_world(&task.target).is_none_or(|cell| !self.frontier.contains(cell));
                // Once per task: a policy may keep a robot on an explored target.
                if on_frontier && explored && !self.explored_tasks.contains(&task.id) {
                    return Some(format!("target of robot {} explored", robot.id));
                }
                let travelled = robot.distance_m - robot.assigned_distance_m;
                if travelled >= settings.distance_m {
                    return Some(format!("robot {} travelled {travelled:.1} m", robot.id));
                }
            } else if self.frontier_churn > 0 && !self.frontier.is_empty() {
                return Some(format!("robot {} idle and the frontier changed", robot.id));
            } else if scoped && self.layer_changes > 0 && self.record.state != MissionState::Completed {
                // Its sub-team's map may still have a frontier the fused map has not.
                return Some(format!("robot {} idle and its sub-team's map changed", robot.id));
            }
        }
        let threshold = ((self.frontier_at_replan as f64) * settings.frontier_change).max(1.0);
        if self.frontier_churn as f64 >= threshold {
            return Some(format!("frontier changed by {} cells", self.frontier_churn));
        }
        let changed = self.frontier_churn > 0 || (scoped && self.layer_changes > 0);
        if changed && now.duration_since(self.last_replan) >= settings.interval {
            return Some("replanning interval elapsed".to_owned());
        }
        if self.record.state == MissionState::Completed && self.frontier_churn > 0 {
            return Some("the frontier changed after completion".to_owned());
        }
        None
    }

    /// Why a mission planned off the request path should replan now: what
    /// [`Mission::replan_reason`] says, except that the triggers that only
    /// say the map changed (the frontier, distance travelled, time) wait
    /// until `min_gap` has passed since the last plan. A demand (a task
    /// ended, a robot joined, ...) is planned at once.
    pub(crate) fn replan_reason_off_path(&self, now: Instant, min_gap: std::time::Duration) -> Option<String> {
        if !self.plan_demanded() && now.duration_since(self.last_replan) < min_gap {
            return None;
        }
        self.replan_reason(now)
    }

    /// Records whom a robot can communicate with now.
    pub(crate) fn set_peers(&mut self, robot: RobotId, peers: Vec<RobotId>) {
        let Some(slot) = self.robots.get_mut(&robot).filter(|s| s.peers != peers) else { return };
        slot.peers = peers;
        if self.record.spec.scoped_by_communication {
            self.structure += 1;
            self.demand_replan(format!("robot {robot}'s sub-team changed"));
        }
    }

    /// Describes what a plan changes: tasks that end, tasks that start, robots
    /// whose assignment moves, and the mission's state.
    pub(crate) fn prepare_plan(
        &self,
        outcome: &JobOutcome,
        reason: &str,
        now: Timestamp,
        task_ids: &AtomicU64,
    ) -> Changeset {
        let frame = &self.record.spec.frame;
        let completed = outcome.complete;
        let mut changes = Changeset { at: Some(now), ..Changeset::default() };
        let policy = self.record.spec.policy.name();
        // By identity: the plan was made on a snapshot of the pool.
        let planned = outcome.order.iter().zip(&outcome.plan.targets);
        let pool = planned.filter_map(|(id, target)| {
            self.robots.get(id).filter(|s| self.in_pool(&s.record)).map(|slot| (slot, target))
        });
        for (slot, target) in pool {
            let robot = &slot.record;
            let current = robot.current_task.and_then(|t| self.open_tasks.get(&t));
            let wanted = if completed {
                // Burgard et al. 2005 stop here; a fleet also wants its robots back.
                let home = self.record.spec.lifecycle.rendezvous.unwrap_or(robot.home);
                let at_home = (robot.pose.position - home).norm() <= HOME_TOLERANCE_M.max(2.0 * frame.resolution);
                // A robot already on its way home finishes the trip and says
                // so, even from within the tolerance (another robot may stand
                // between it and its cell for a while).
                let going_home = current.is_some_and(|t| t.kind == TaskKind::Home);
                ((!at_home || going_home) && !slot.home_failed).then(|| TaskDraft {
                    kind: TaskKind::Home,
                    target: home,
                    created_by: BY_EXECUTIVE.to_owned(),
                    note: "mission complete".to_owned(),
                    policy: BY_EXECUTIVE.to_owned(),
                    utility: 0.0,
                    path_cost: 0.0,
                    gain_region: None,
                })
            } else {
                // A plan made off the lock may target what was explored
                // meanwhile: that robot keeps what it has until the next plan.
                let explored_since =
                    |cell: Cell| outcome.frontier_targets.contains(&cell) && !self.frontier.contains(cell);
                if !self.record.spec.scoped_by_communication && target.as_ref().is_some_and(|t| explored_since(t.cell))
                {
                    continue;
                }
                target.as_ref().map(|t| TaskDraft {
                    kind: TaskKind::Explore,
                    target: frame.world_from_cell(t.cell),
                    created_by: BY_POLICY.to_owned(),
                    note: String::new(),
                    policy: policy.to_owned(),
                    utility: t.utility,
                    path_cost: t.path_cost,
                    gain_region: t.gain_region,
                })
            };
            let keep = match (current, &wanted) {
                (Some(task), Some(w)) => {
                    task.kind == w.kind && frame.cell_from_world(&task.target) == frame.cell_from_world(&w.target)
                }
                (None, None) => true,
                _ => false,
            };
            let mut next = robot.clone();
            // The distance trigger counts from the latest replanning.
            next.assigned_distance_m = next.distance_m;
            if keep {
                if next != *robot {
                    changes.robots.push(next);
                }
                continue;
            }
            if let Some(task) = current {
                let (state, cause, actor) = if completed {
                    (TaskState::Cancelled, "mission complete: no reachable frontier left".to_owned(), Actor::Executive)
                } else {
                    (TaskState::Preempted, reason.to_owned(), Actor::Policy)
                };
                changes.task_changes.push(transition(task, state, &cause, actor, now));
            }
            next.current_task = None;
            if let Some(draft) = wanted {
                let actor = if completed { Actor::Executive } else { Actor::Policy };
                let task = self.open_task(robot.id, draft, reason, actor, "", now, task_ids);
                next.current_task = Some(task.id);
                changes.new_tasks.push(task);
            }
            next.assignment_version += 1;
            changes.robots.push(next);
        }
        self.prepare_overrides(outcome, now, task_ids, &mut changes);
        changes.unblacklisted.extend(outcome.expired.iter().copied());
        let mut counters = self.counters();
        counters.replans += 1;
        if !outcome.undecided {
            counters.state = if completed { MissionState::Completed } else { MissionState::Active };
            counters.leftovers = if completed { outcome.leftovers.clone() } else { Leftovers::default() };
        }
        if counters.state != self.record.state {
            // Every robot's assignment carries the mission state: push it.
            for slot in self.robots.values() {
                if !changes.robots.iter().any(|r| r.id == slot.record.id) {
                    let mut next = slot.record.clone();
                    next.assignment_version += 1;
                    changes.robots.push(next);
                }
            }
        }
        changes.mission = Some(counters);
        if let Some(segmentation) = &outcome.plan.segmentation {
            changes.segmentation =
                Some((self.record.id, StoredSegmentation { computed_at: now, segmentation: segmentation.clone() }));
        }
        changes
    }

    /// A replanning was made but could not be committed; it stays due.
    pub(crate) fn note_replan_failed(&mut self) {
        self.replan_failed = true;
        if self.pending_replan.is_none() {
            self.pending_replan = Some("an earlier replanning could not be committed".to_owned());
        }
    }

    /// Whether the last replanning could not be committed.
    pub(crate) fn replan_failed(&self) -> bool {
        self.replan_failed
    }

    /// Resets the replanning triggers after a committed replanning.
    /// `demands_before_commit` is [`Mission::demands`] just before the plan's
    /// own changes were applied: a demand made after the snapshot stays.
    pub(crate) fn mark_replanned(&mut self, now: Instant, basis: &PlanBasis, demands_before_commit: u64) {
        self.replan_failed = false;
        let frame = self.record.spec.frame;
        let explored: Vec<TaskId> = self
            .open_tasks
            .values()
            .filter(|t| frame.cell_from_world(&t.target).is_none_or(|c| !self.frontier.contains(c)))
            .map(|t| t.id)
            .collect();
        self.explored_tasks = explored.into_iter().collect();
        self.last_replan = now;
        self.frontier_at_replan = self.frontier.len();
        // What changed while the plan was made still counts towards the next.
        self.frontier_churn = self.frontier_churn.saturating_sub(basis.frontier_churn);
        self.layer_changes = self.layer_changes.saturating_sub(basis.layer_changes);
        if demands_before_commit == basis.demands {
            self.pending_replan = None;
        }
        for robot in &basis.fresh_bids {
            self.fresh_bids.remove(robot);
        }
    }

    /// After a committed plan: a robot of the pool the plan had a target
    /// for, still without a task (its target was explored while the plan
    /// was made, see [`Mission::prepare_plan`]), is owed a plan at once, as
    /// a demand. Left to the map news alone it would stand idle until the
    /// planner's least gap between plans had passed.
    pub(crate) fn demand_for_robots_left_idle(&mut self, outcome: &JobOutcome) {
        if outcome.complete {
            return;
        }
        let idle = outcome.order.iter().zip(&outcome.plan.targets).find_map(|(id, target)| {
            let slot = self.robots.get(id)?;
            let left = target.is_some() && slot.record.current_task.is_none() && self.in_pool(&slot.record);
            left.then_some(*id)
        });
        if let Some(robot) = idle {
            self.demand_replan(format!("robot {robot}'s target was explored while it was planned"));
        }
    }

    /// What a plan is made on, to tell at commit whether it still fits.
    pub(crate) fn plan_basis(&self) -> PlanBasis {
        PlanBasis {
            fresh_bids: self.fresh_bids.iter().copied().collect(),
            structure: self.structure,
            demands: self.demands,
            frontier_churn: self.frontier_churn,
            layer_changes: self.layer_changes,
        }
    }

    /// Whether a plan made on `basis` may still be committed: neither the
    /// policy, the forbidden regions, pausing nor the sub-teams changed
    /// since. Other changes leave it usable for the robots it still fits
    /// ([`Mission::prepare_plan`] checks each), and what they demand is
    /// planned next.
    pub(crate) fn plan_still_fits(&self, basis: &PlanBasis) -> bool {
        self.structure == basis.structure && !self.record.paused
    }

    /// How many demands for a plan there have been.
    pub(crate) fn demands(&self) -> u64 {
        self.demands
    }

    /// Whether a replanning is demanded (a task ended, a robot joined,
    /// ...): someone waits for it, unlike for map news alone.
    pub(crate) fn plan_demanded(&self) -> bool {
        self.pending_replan.is_some()
    }

    /// Asks for a replanning at the next opportunity.
    pub(super) fn demand_replan(&mut self, reason: String) {
        self.pending_replan = Some(reason);
        self.demands += 1;
    }
}

#[cfg(test)]
mod tests {
    use std::sync::Arc;
    use std::sync::atomic::AtomicU64;

    use exploration::fusion::Patch;
    use exploration::grid::CellRect;
    use exploration::math::Point2;
    use exploration::policy::{Capabilities, PolicyConfig};

    use super::super::testing::{left_half_known, nearest_spec};
    use super::*;
    use crate::domain::{Heartbeat, MissionRecord, Pose, RobotRecord, RobotState};
    use crate::store::{Changeset, LoggedPatch};

    /// A 4 m × 2 m mission of 0.1 m cells under `nearest`, with two robots,
    /// the left half of the map known and free.
    fn mission() -> Mission {
        let record = MissionRecord {
            id: 1,
            spec: nearest_spec("unit"),
            state: MissionState::Active,
            replans: 0,
            map_updates: 0,
            paused: false,
            leftovers: Leftovers::default(),
            created_at: Timestamp(0),
        };
        let now = Instant::now();
        let mut mission = Mission::new(record, now);
        // Far apart, so that their nearest frontier cells differ.
        for (id, x, y) in [(1, 0.5, 0.15), (2, 1.5, 1.85)] {
            mission.insert_robot(robot(id, x, y), now);
        }
        mission.apply(left_half_known(1));
        mission
    }

    fn robot(id: RobotId, x: f64, y: f64) -> RobotRecord {
        RobotRecord {
            id,
            mission_id: 1,
            name: format!("r{id}"),
            capabilities: Capabilities {
                sensor_range_m: 1.0,
                field_of_view_rad: std::f64::consts::TAU,
                speed_mps: 0.5,
                footprint_radius_m: 0.0,
            },
            state: RobotState::Idle,
            pose: Pose { position: Point2::new(x, y), heading: 0.0 },
            last_map_seq: 0,
            distance_m: 0.0,
            assignment_version: 0,
            assigned_distance_m: 0.0,
            current_task: None,
            last_seen: Timestamp(0),
            lost: false,
            home: Point2::new(x, y),
        }
    }

    /// Plans `mission` as the planner does: snapshot, run, prepare, apply.
    fn plan(mission: &mut Mission, ids: &AtomicU64) -> Changeset {
        let basis = mission.plan_basis();
        let reason = mission.replan_reason(Instant::now()).expect("a plan is due");
        let outcome = mission.planning_job(1).run();
        let changes = mission.prepare_plan(&outcome, &reason, Timestamp(1), ids);
        let demands = mission.demands();
        mission.apply(changes.clone());
        mission.mark_replanned(Instant::now(), &basis, demands);
        changes
    }

    #[test]
    fn a_plan_gives_each_robot_in_the_pool_a_frontier_task() {
        let mut mission = mission();
        let ids = AtomicU64::new(10);
        let changes = plan(&mut mission, &ids);
        assert_eq!(changes.new_tasks.len(), 2, "both robots get a task");
        assert_eq!(changes.new_tasks.iter().map(|t| t.id).collect::<Vec<_>>(), vec![11, 12]);
        for task in &changes.new_tasks {
            let cell = mission.record().spec.frame.cell_from_world(&task.target).unwrap();
            assert!(mission.frontier().contains(cell), "{task:?} targets the frontier");
        }
        assert_eq!(mission.record().replans, 1);
        assert!(mission.replan_reason(Instant::now()).is_none(), "nothing is due right after a plan");
    }

    #[test]
    fn a_plan_made_before_the_policy_changed_no_longer_fits() {
        let mut mission = mission();
        let basis = mission.plan_basis();
        // Map news alone: the plan still fits (it counts towards the next one).
        let more = Patch::from_probabilities(CellRect::new(20, 0, 2, 20), &[0.1; 40], &[]).unwrap();
        mission.apply(Changeset {
            patches: vec![LoggedPatch { robot_id: 2, seq: 1, patch: Arc::new(more) }],
            ..Changeset::default()
        });
        assert!(mission.plan_still_fits(&basis));
        mission.apply(Changeset {
            policy: Some((1, PolicyConfig::default_for("minpos").unwrap())),
            ..Changeset::default()
        });
        assert!(!mission.plan_still_fits(&basis));
    }

    #[test]
    fn a_demand_made_while_a_plan_is_made_stays_after_it() {
        let mut mission = mission();
        let ids = AtomicU64::new(0);
        plan(&mut mission, &ids);
        // A robot arrives while the next plan is made.
        let basis = mission.plan_basis();
        let outcome = mission.planning_job(1).run();
        let task = mission.open_tasks.values().next().unwrap().clone();
        mission.apply(Changeset {
            task_changes: vec![transition(&task, TaskState::Reached, "robot arrived", Actor::Robot, Timestamp(2))],
            ..Changeset::default()
        });
        assert!(mission.plan_still_fits(&basis), "the plan is still good for the others");
        let changes = mission.prepare_plan(&outcome, "test", Timestamp(3), &ids);
        let demands = mission.demands();
        mission.apply(changes);
        mission.mark_replanned(Instant::now(), &basis, demands);
        assert!(
            mission.replan_reason(Instant::now()).is_some_and(|r| r.contains("robot arrived")),
            "it is planned next"
        );
    }

    #[test]
    fn a_robot_whose_target_was_explored_while_it_was_planned_is_planned_again_at_once() {
        let mut mission = mission();
        let ids = AtomicU64::new(0);
        plan(&mut mission, &ids);
        // Robot 1 arrives; the plan that answers it is made on a snapshot.
        let task = mission.open_tasks.values().find(|t| t.robot_id == 1).unwrap().clone();
        let mut arrived = mission.robots[&1].record.clone();
        arrived.current_task = None;
        mission.apply(Changeset {
            task_changes: vec![transition(&task, TaskState::Reached, "robot arrived", Actor::Robot, Timestamp(2))],
            robots: vec![arrived],
            ..Changeset::default()
        });
        let basis = mission.plan_basis();
        let outcome = mission.planning_job(1).run();
        let order = outcome.order.iter().position(|&id| id == 1).unwrap();
        let target = outcome.plan.targets[order].as_ref().expect("robot 1 is given a target").cell;
        // Meanwhile the rest of the map becomes known, that target with it.
        let rest = Patch::from_probabilities(CellRect::new(20, 0, 20, 20), &[0.1; 400], &[]).unwrap();
        mission.apply(Changeset {
            patches: vec![LoggedPatch { robot_id: 2, seq: 1, patch: Arc::new(rest) }],
            ..Changeset::default()
        });
        assert!(!mission.frontier().contains(target), "the target was explored");
        let changes = mission.prepare_plan(&outcome, "test", Timestamp(3), &ids);
        let demands = mission.demands();
        mission.apply(changes);
        mission.mark_replanned(Instant::now(), &basis, demands);
        mission.demand_for_robots_left_idle(&outcome);
        assert_eq!(mission.robots[&1].record.current_task, None, "robot 1 was left without a task");
        let hour = std::time::Duration::from_secs(3600);
        assert!(
            mission.replan_reason_off_path(Instant::now(), hour).is_some_and(|r| r.contains("robot 1")),
            "robot 1 does not wait for the least gap between plans"
        );
    }

    #[test]
    fn changes_made_while_a_plan_is_made_still_count_after_it() {
        let mut mission = mission();
        let ids = AtomicU64::new(0);
        plan(&mut mission, &ids);
        let basis = mission.plan_basis();
        let outcome = mission.planning_job(1).run();
        // While that plan was made, the rest of the map became known: churn
        // that must still trigger the next plan after this one is committed.
        let rest = Patch::from_probabilities(CellRect::new(20, 0, 20, 20), &[0.1; 400], &[]).unwrap();
        mission.apply(Changeset {
            patches: vec![LoggedPatch { robot_id: 2, seq: 1, patch: Arc::new(rest) }],
            ..Changeset::default()
        });
        assert!(mission.plan_still_fits(&basis));
        let changes = mission.prepare_plan(&outcome, "test", Timestamp(3), &ids);
        let demands = mission.demands();
        mission.apply(changes);
        mission.mark_replanned(Instant::now(), &basis, demands);
        assert!(mission.replan_reason(Instant::now()).is_some(), "the churn after the snapshot is kept");
    }

    #[test]
    fn a_plan_is_matched_to_robots_by_identity() {
        let mut mission = mission();
        let ids = AtomicU64::new(0);
        let outcome = mission.planning_job(1).run();
        // Robot 1 leaves the pool (its lease ran out) after the snapshot.
        let mut lost = mission.robot(1).unwrap().clone();
        lost.lost = true;
        mission.apply(Changeset { robots: vec![lost], ..Changeset::default() });
        let changes = mission.prepare_plan(&outcome, "test", Timestamp(4), &ids);
        let planned_for_2 = outcome.plan.targets[1].as_ref().unwrap().cell;
        assert_ne!(Some(planned_for_2), outcome.plan.targets[0].as_ref().map(|t| t.cell), "distinct targets");
        assert_eq!(changes.new_tasks.len(), 1, "no task for the robot that left: {changes:?}");
        let task = &changes.new_tasks[0];
        assert_eq!(task.robot_id, 2);
        let frame = mission.record().spec.frame;
        assert_eq!(frame.cell_from_world(&task.target), Some(planned_for_2), "robot 2's own target");
    }
    /// A heartbeat that ends a task is applied once queued for the disk, so
    /// that its mission need not wait for the write; its robot is told the
    /// assignment it moved only once it is durable ([`Mission::tell`]), not
    /// by another robot's report applied meanwhile, and never told an older
    /// one after a newer.
    #[test]
    fn an_assignment_moved_by_a_queued_changeset_is_told_once_it_is_durable() {
        let mut mission = mission();
        let ids = AtomicU64::new(10);
        plan(&mut mission, &ids);
        let mut told = mission.watch(1).unwrap();
        let task = told.borrow_and_update().task.as_ref().map(|t| t.id).expect("robot 1 was told its task");
        let at = |x, y| Pose { position: Point2::new(x, y), heading: 0.0 };
        let arrived = Heartbeat {
            pose: at(0.5, 0.15),
            state: RobotState::Arrived,
            task_id: Some(task),
            reason: String::new(),
            peers: None,
        };
        let changes = mission.prepare_heartbeat(1, arrived, Timestamp(2)).unwrap();
        assert!(!mission.only_liveness(&changes));
        let moved = mission.apply_queued(changes);
        assert_eq!(mission.robot(1).unwrap().current_task, None, "applied at once");
        assert_eq!(mission.assignment(1).unwrap().task, None, "as it stands: for answers given once durable");
        assert_eq!(mission.assignment_told(1).unwrap().task.map(|t| t.id), Some(task), "what may be told now");
        // Robot 2 reports meanwhile; that tells robot 1 nothing.
        let alive = Heartbeat {
            pose: at(1.5, 1.85),
            state: RobotState::Moving,
            task_id: None,
            reason: String::new(),
            peers: None,
        };
        let changes = mission.prepare_heartbeat(2, alive, Timestamp(3)).unwrap();
        assert!(mission.only_liveness(&changes));
        mission.apply_unsaved(changes);
        assert!(!told.has_changed().unwrap(), "told before it is durable");
        let stale = mission.assignment_told(1).unwrap();
        mission.tell(moved);
        assert!(told.has_changed().unwrap());
        let now_told = told.borrow_and_update().clone();
        assert_eq!(now_told.task, None);
        assert!(now_told.version > stale.version);
        mission.tell(vec![stale]);
        assert!(!told.has_changed().unwrap(), "an older assignment after a newer");
    }
}
