//! What robots report: map updates, heartbeats and bids, checked against
//! the mission and turned into changesets; and the liveness reports that
//! are acknowledged once applied and written behind.

use std::sync::Arc;

use exploration::policy::Bid as PolicyBid;

use super::{Mission, transition};
use crate::domain::{
    Actor, Bid, Heartbeat, MapUpdate, Pose, RobotId, RobotRecord, RobotState, TaskKind, TaskState, Timestamp,
};
use crate::error::Error;
use crate::store::{Changeset, LoggedPatch};

impl Mission {
    /// Checks a robot's bids against the map: each target on it, each gain
    /// region overlapping it (only its part on the map counts).
    pub(crate) fn check_bids(&self, robot_id: RobotId, bids: &[Bid]) -> Result<(), Error> {
        self.robot(robot_id)?;
        let frame = &self.record.spec.frame;
        for (i, bid) in bids.iter().enumerate() {
            crate::validate::on_map(bid.target, frame, &format!("bids[{i}].target"))?;
            if frame.rect_from_world(&bid.gain_region.0, &bid.gain_region.1).is_none() {
                return Err(Error::InvalidArgument(format!(
                    "bids[{i}].gain_region does not overlap the mission map; give the region the target would reveal"
                )));
            }
        }
        Ok(())
    }

    /// Takes a robot's bids (from the store or a request) into the mission's
    /// cells; a bid off the map (stored by an older executive) is dropped.
    pub(crate) fn set_bids(&mut self, robot: RobotId, bids: &[Bid]) {
        let frame = self.record.spec.frame;
        let converted: Vec<PolicyBid> = bids
            .iter()
            .filter_map(|b| {
                Some(PolicyBid {
                    target: frame.cell_from_world(&b.target)?,
                    path_cost_m: b.path_cost,
                    information_gain: b.information_gain,
                    gain_region: frame.rect_from_world(&b.gain_region.0, &b.gain_region.1)?,
                })
            })
            .collect();
        if converted.len() < bids.len() {
            tracing::warn!(
                mission = self.record.id,
                robot,
                dropped = bids.len() - converted.len(),
                "bids off the mission map dropped"
            );
        }
        self.bids.insert(robot, converted);
        if self.policy.uses_bids() {
            self.demand_replan(format!("robot {robot} submitted bids"));
        }
    }

    /// The robot's bids arrived just now (not restored): the next plan takes
    /// them even if the robot has a task.
    pub(crate) fn mark_bids_fresh(&mut self, robot: RobotId) {
        self.fresh_bids.insert(robot);
    }

    fn check_pose(&self, pose: &Pose) -> Result<(), Error> {
        let frame = &self.record.spec.frame;
        if frame.cell_from_world(&pose.position).is_none() {
            return Err(Error::InvalidArgument(format!("pose {}", crate::validate::outside_map(pose.position, frame))));
        }
        Ok(())
    }

    /// The robot record after it reported `pose` at `now`.
    fn moved(robot: &RobotRecord, pose: Pose, now: Timestamp) -> RobotRecord {
        let mut next = robot.clone();
        next.distance_m += (pose.position - robot.pose.position).norm();
        next.pose = pose;
        next.last_seen = now;
        // A report renews the lease: a lost robot rejoins the pool.
        next.lost = false;
        next
    }

    /// Checks a map update and describes its effect.
    pub(crate) fn prepare_update(
        &self,
        robot_id: RobotId,
        update: MapUpdate,
        now: Timestamp,
    ) -> Result<Changeset, Error> {
        let robot = self.robot(robot_id)?;
        if update.seq == 0 {
            return Err(Error::InvalidArgument(
                "seq must be at least 1; number each robot's map updates 1, 2, 3, ...".to_owned(),
            ));
        }
        if update.seq == robot.last_map_seq {
            return Err(Error::AlreadyExists(format!(
                "map update {} of robot {robot_id} was already applied; the next one must be numbered above {}",
                update.seq, robot.last_map_seq
            )));
        }
        if update.seq < robot.last_map_seq {
            return Err(Error::FailedPrecondition(format!(
                "map update {} of robot {robot_id} is stale: update {} was already applied; number updates above {}",
                update.seq, robot.last_map_seq, robot.last_map_seq
            )));
        }
        self.check_pose(&update.pose)?;
        for (i, patch) in update.patches.iter().enumerate() {
            patch
                .check_inside(&self.record.spec.frame)
                .map_err(|e| Error::InvalidArgument(format!("patch {i}: {e}")))?;
        }
        let mut next = Self::moved(robot, update.pose, now);
        next.last_map_seq = update.seq;
        let mut counters = self.counters();
        counters.map_updates += 1;
        Ok(Changeset {
            mission: Some(counters),
            robots: vec![next],
            patches: update
                .patches
                .into_iter()
                .map(|patch| LoggedPatch { robot_id, seq: update.seq, patch: Arc::new(patch) })
                .collect(),
            at: Some(now),
            ..Changeset::default()
        })
    }

    /// Checks a heartbeat and describes its effect.
    pub(crate) fn prepare_heartbeat(
        &self,
        robot_id: RobotId,
        heartbeat: Heartbeat,
        now: Timestamp,
    ) -> Result<Changeset, Error> {
        let robot = self.robot(robot_id)?;
        self.check_pose(&heartbeat.pose)?;
        let mut next = Self::moved(robot, heartbeat.pose, now);
        next.state = heartbeat.state;
        if let Some(named) = heartbeat.task_id.filter(|t| robot.current_task != Some(*t)) {
            if let Some(other) = self.open_tasks.get(&named).filter(|t| t.robot_id != robot_id) {
                return Err(Error::FailedPrecondition(format!(
                    "task {named} is robot {}'s, not robot {robot_id}'s; report on the robot's own task",
                    other.robot_id
                )));
            }
            // One of its own tasks that has already ended (it was replaced
            // while the robot drove): the report renews the lease and the
            // pose, but ends nothing and leaves the robot's state as it was.
            if matches!(heartbeat.state, RobotState::Arrived | RobotState::Failed) {
                next.state = robot.state;
            }
        }
        let mut changes = Changeset { at: Some(now), ..Changeset::default() };
        let current = robot.current_task.filter(|t| heartbeat.task_id == Some(*t));
        if let Some(task) = current.and_then(|t| self.open_tasks.get(&t)) {
            let ended = match heartbeat.state {
                // A hold lasts until an operator ends it.
                RobotState::Arrived if task.kind == TaskKind::Hold => None,
                RobotState::Arrived => Some((TaskState::Reached, "robot arrived".to_owned())),
                RobotState::Failed => {
                    let cause = if heartbeat.reason.is_empty() {
                        "robot reported the target unreachable".to_owned()
                    } else {
                        format!("robot reported the target unreachable: {}", heartbeat.reason)
                    };
                    changes.blacklisted.extend(self.blacklist_entry(task, &cause, now));
                    Some((TaskState::Failed, cause))
                }
                RobotState::Moving if task.state == TaskState::Assigned => {
                    changes.task_changes.push(transition(task, TaskState::Active, "robot moving", Actor::Robot, now));
                    None
                }
                _ => None,
            };
            if let Some((state, cause)) = ended {
                changes.task_changes.push(transition(task, state, &cause, Actor::Robot, now));
                next.current_task = None;
                next.assignment_version += 1;
            }
        }
        changes.robots.push(next);
        Ok(changes)
    }

    /// Whether a prepared heartbeat only says where a robot is and that it
    /// lives: no task starts or ends, nothing is blacklisted, and the robot
    /// was not lost. Losing such a report in a crash is the same as losing
    /// it on the way (the robot reports again within a second), so it is
    /// acknowledged once applied and written behind; everything else is
    /// written before it is acknowledged.
    pub(crate) fn only_liveness(&self, changes: &Changeset) -> bool {
        let [next] = changes.robots.as_slice() else { return false };
        let Ok(now) = self.robot(next.id) else { return false };
        let mut same = next.clone();
        same.pose = now.pose;
        same.distance_m = now.distance_m;
        same.last_seen = now.last_seen;
        same.state = now.state;
        changes.task_changes.is_empty()
            && changes.new_tasks.is_empty()
            && changes.blacklisted.is_empty()
            && changes.mission.is_none()
            && same == *now
    }

    /// Applies a liveness report without writing it (see [`Mission::only_liveness`]).
    pub(crate) fn apply_unsaved(&mut self, changes: Changeset) {
        self.unsaved.extend(changes.robots.iter().map(|r| r.id));
        // Liveness moves no assignment; and assignments a changeset still
        // on its way to the disk moved are not to be told yet.
        self.apply_changes(changes);
    }

    /// The records of the robots changed only by liveness reports, to write.
    pub(crate) fn take_unsaved(&mut self) -> Option<Changeset> {
        if self.unsaved.is_empty() {
            return None;
        }
        self.unsaved_in_flight = std::mem::take(&mut self.unsaved).into_iter().collect();
        let robots = self.unsaved_in_flight.iter().filter_map(|id| self.robots.get(id)).map(|s| s.record.clone());
        Some(Changeset { robots: robots.collect(), ..Changeset::default() })
    }

    /// The write-behind changeset failed: its robots are written next time.
    pub(crate) fn keep_unsaved_again(&mut self) {
        self.unsaved.extend(self.unsaved_in_flight.drain(..));
    }
}
