//! Operators stepping in (Simmons et al. 2000, §4.2): "the user can
//! designate specific robots to go to specific locations; the executive
//! then plans for the remaining robots, taking into account the
//! assignments", and hands the robot back to the pool when it is done. Also
//! forbidden regions and pausing.

use std::sync::atomic::AtomicU64;

use exploration::grid::CellClass;
use exploration::math::Point2;
use exploration::policy::PolicyConfig;

use super::{Mission, TaskDraft, transition};
use crate::domain::{
    Actor, MissionEvent, MissionState, OperatorNote, Override, Region, RobotId, Rooms, TaskKind, TaskRecord, TaskState,
    Timestamp,
};
use crate::error::Error;
use crate::store::Changeset;
use crate::validate::{MAX_FORBIDDEN_REGIONS, Place};

/// How far from the point an operator gives a frontier to pin may lie, metres.
const PIN_RADIUS_M: f64 = 1.0;

impl Mission {
    /// Checks a policy change and describes it.
    pub(crate) fn prepare_policy(&self, policy: PolicyConfig, actor: &str, reason: &str, now: Timestamp) -> Changeset {
        let before = self.record.spec.policy.name();
        let detail = if reason.is_empty() {
            format!("{before} -> {} {:?}", policy.name(), policy.params())
        } else {
            format!("{before} -> {} {:?}: {reason}", policy.name(), policy.params())
        };
        Changeset {
            policy: Some((self.record.id, policy)),
            events: vec![MissionEvent {
                id: 0,
                mission_id: self.record.id,
                at: now,
                kind: "policy_changed".to_owned(),
                detail,
                actor: actor.to_owned(),
            }],
            at: Some(now),
            ..Changeset::default()
        }
    }

    /// Describes an override of a robot's task.
    pub(crate) fn prepare_override(
        &self,
        robot_id: RobotId,
        action: Override,
        note: &OperatorNote,
        now: Timestamp,
        task_ids: &AtomicU64,
    ) -> Result<Changeset, Error> {
        let robot = self.robot(robot_id)?;
        let label = robot.label();
        let current = robot.current_task.and_then(|t| self.open_tasks.get(&t));
        let said = |what: String| if note.reason.is_empty() { what } else { format!("{what}: {}", note.reason) };
        let mut changes = Changeset { at: Some(now), ..Changeset::default() };
        let mut next = robot.clone();
        next.assignment_version += 1;
        let detail;
        match action {
            Override::Release | Override::Cancel => {
                let (state, verb) = if action == Override::Release {
                    let Some(task) = current else {
                        return Err(Error::FailedPrecondition(format!(
                            "{label} has no task to release; `coordctl robots` shows what each robot does"
                        )));
                    };
                    (TaskState::Released, format!("released from task {}", task.id))
                } else {
                    match current {
                        Some(task) if task.is_override() => {
                            (TaskState::Cancelled, format!("override {} ({}) cancelled", task.id, task.kind.as_str()))
                        }
                        Some(task) => {
                            return Err(Error::FailedPrecondition(format!(
                                "{label} is on {} task {} chosen by the {}, not on an override; use \
                                 `release` to take the task off it",
                                task.kind.as_str(),
                                task.id,
                                task.created_by
                            )));
                        }
                        None => {
                            return Err(Error::FailedPrecondition(format!("{label} has no override to cancel")));
                        }
                    }
                };
                let task = current.expect("checked above");
                let cause = said(format!("operator {}: {verb}", note.actor));
                changes.task_changes.push(operator_transition(task, state, &cause, &note.actor, now));
                next.current_task = None;
                detail = format!("{label}: {verb}");
            }
            Override::Goto(_)
            | Override::ExploreRegion(..)
            | Override::Hold
            | Override::Home
            | Override::PinFrontier(_) => {
                if robot.lost {
                    return Err(Error::FailedPrecondition(format!(
                        "{label} is lost (its lease ran out); it rejoins when it reports again, override it then"
                    )));
                }
                let draft = self.override_draft(robot, action, note)?;
                detail = format!("{label}: {} ({:.2}, {:.2})", draft.kind.as_str(), draft.target.x, draft.target.y);
                if let Some(task) = current {
                    let cause = said(format!("operator {}: {}", note.actor, detail));
                    changes.task_changes.push(operator_transition(
                        task,
                        TaskState::Overridden,
                        &cause,
                        &note.actor,
                        now,
                    ));
                }
                let cause = said(format!("operator {}", note.actor));
                let task = self.open_task(robot_id, draft, &cause, Actor::Operator, &note.actor, now, task_ids);
                next.current_task = Some(task.id);
                changes.new_tasks.push(task);
            }
        }
        changes.robots.push(next);
        changes.events.push(self.event("override", said(detail), &note.actor, now));
        Ok(changes)
    }

    /// The task an override creates, checked against the map.
    fn override_draft(
        &self,
        robot: &crate::domain::RobotRecord,
        action: Override,
        note: &OperatorNote,
    ) -> Result<TaskDraft, Error> {
        let frame = &self.record.spec.frame;
        let inside = |p: Point2, what: &str| {
            frame
                .cell_from_world(&p)
                .ok_or_else(|| Error::InvalidArgument(format!("{what} {}", crate::validate::outside_map(p, frame))))
        };
        let draft = |kind: TaskKind, target: Point2| TaskDraft {
            kind,
            target,
            created_by: format!("operator:{}", note.actor),
            note: note.reason.clone(),
            policy: "operator".to_owned(),
            utility: 0.0,
            path_cost: 0.0,
            gain_region: None,
        };
        Ok(match action {
            Override::Goto(p) => {
                let cell = inside(p, "target")?;
                if self.fusion.grid().class(cell) == CellClass::Occupied {
                    return Err(Error::FailedPrecondition(format!(
                        "{} is an obstacle in the fused map; pick a free or unknown point \
                         (`coordctl map export` draws the map)",
                        Place(p)
                    )));
                }
                draft(TaskKind::Goto, frame.world_from_cell(cell))
            }
            Override::ExploreRegion(min, max) => {
                let region = self.cell_rect(min, max).ok_or_else(|| {
                    Error::InvalidArgument(format!(
                        "region {}..{} does not overlap the mission map",
                        Place(min),
                        Place(max)
                    ))
                })?;
                // Heads for the centre until the next replanning picks the region's nearest frontier.
                let centre = exploration::grid::Cell::new(
                    region.x + region.width as i32 / 2,
                    region.y + region.height as i32 / 2,
                );
                TaskDraft { gain_region: Some(region), ..draft(TaskKind::Goto, frame.world_from_cell(centre)) }
            }
            Override::Hold => draft(TaskKind::Hold, robot.pose.position),
            Override::Home => draft(TaskKind::Home, self.record.spec.lifecycle.rendezvous.unwrap_or(robot.home)),
            Override::PinFrontier(p) => {
                let at = inside(p, "frontier")?;
                let radius = (PIN_RADIUS_M / frame.resolution).ceil() as i32;
                let nearest = self
                    .frontier
                    .cells()
                    .into_iter()
                    .filter(|c| (c.x - at.x).abs() <= radius && (c.y - at.y).abs() <= radius)
                    .min_by_key(|c| (c.distance_squared(at), *c))
                    .ok_or_else(|| {
                        Error::FailedPrecondition(format!(
                            "no frontier within {PIN_RADIUS_M} m of {}; `coordctl map export` draws the frontier",
                            Place(p)
                        ))
                    })?;
                if let Some(other) = self.open_tasks.values().find(|t| {
                    t.kind == TaskKind::Pin
                        && t.robot_id != robot.id
                        && frame.cell_from_world(&t.target) == Some(nearest)
                }) {
                    return Err(Error::FailedPrecondition(format!(
                        "that frontier is already pinned to robot {} (task {})",
                        other.robot_id, other.id
                    )));
                }
                draft(TaskKind::Pin, frame.world_from_cell(nearest))
            }
            Override::Release | Override::Cancel => unreachable!("handled by prepare_override"),
        })
    }

    /// Deletes the mission, once no robot is sent anywhere: it must have
    /// completed, or be paused. Its history goes with it; the deletion
    /// itself is logged (an event would be purged with the rest).
    pub(crate) fn prepare_delete(&self, now: Timestamp) -> Result<Changeset, Error> {
        let id = self.record.id;
        if self.record.state == MissionState::Active && !self.record.paused {
            return Err(Error::FailedPrecondition(format!(
                "mission {id} is active: pause it (PauseMission) or let it complete before deleting it"
            )));
        }
        Ok(Changeset { deleted: Some(id), at: Some(now), ..Changeset::default() })
    }

    /// Describes pausing (`pause`) or resuming the mission.
    pub(crate) fn prepare_pause(&self, pause: bool, note: &OperatorNote, now: Timestamp) -> Result<Changeset, Error> {
        let id = self.record.id;
        if pause == self.record.paused {
            return Err(Error::FailedPrecondition(if pause {
                format!("mission {id} is already paused")
            } else {
                format!("mission {id} is not paused")
            }));
        }
        let mut counters = self.counters();
        counters.paused = pause;
        let kind = if pause { "paused" } else { "resumed" };
        let detail = if note.reason.is_empty() { kind.to_owned() } else { format!("{kind}: {}", note.reason) };
        Ok(Changeset {
            mission: Some(counters),
            // Every assignment carries the paused flag: push it.
            robots: self
                .robots
                .values()
                .map(|s| {
                    let mut next = s.record.clone();
                    next.assignment_version += 1;
                    next
                })
                .collect(),
            events: vec![self.event(&format!("mission_{kind}"), detail, &note.actor, now)],
            at: Some(now),
            ..Changeset::default()
        })
    }

    /// Describes forbidding a region; `id` is its new identity.
    pub(crate) fn prepare_forbid(
        &self,
        id: u64,
        min: Point2,
        max: Point2,
        note: &OperatorNote,
        now: Timestamp,
    ) -> Result<(Changeset, Region), Error> {
        if self.forbidden.len() >= MAX_FORBIDDEN_REGIONS {
            return Err(Error::ResourceExhausted(format!(
                "mission {} already has {} forbidden regions, the most it may have: allow one before forbidding another",
                self.record.id,
                self.forbidden.len()
            )));
        }
        let Some(cells) = self.cell_rect(min, max) else {
            return Err(Error::InvalidArgument(format!(
                "region {}..{} does not overlap the mission map",
                Place(min),
                Place(max)
            )));
        };
        // Kept as the part on the map: the cells it forbids, in metres.
        let (min, max) = self.world_rect(cells);
        let region = Region {
            id,
            mission_id: self.record.id,
            min,
            max,
            actor: note.actor.clone(),
            reason: note.reason.clone(),
            created_at: now,
        };
        let detail = format!("region {id} ({:.2}, {:.2})..({:.2}, {:.2}) {}", min.x, min.y, max.x, max.y, note.reason);
        let changes = Changeset {
            forbidden: vec![region.clone()],
            events: vec![self.event("region_forbidden", detail.trim_end().to_owned(), &note.actor, now)],
            at: Some(now),
            ..Changeset::default()
        };
        Ok((changes, region))
    }

    /// Describes giving the mission its rooms (`Some`, a label per cell of
    /// its map) or taking them back (`None`).
    pub(crate) fn prepare_rooms(
        &self,
        rooms: Option<Vec<u32>>,
        note: &OperatorNote,
        now: Timestamp,
    ) -> Result<Changeset, Error> {
        let frame = &self.record.spec.frame;
        if let Some(labels) = &rooms
            && labels.len() != frame.len()
        {
            return Err(Error::InvalidArgument(format!(
                "label_runs cover {} cells, not the map's {} × {}",
                labels.len(),
                frame.width,
                frame.height
            )));
        }
        let detail = match &rooms {
            Some(labels) => {
                // Labels come in runs: one entry per run, not per cell, before sorting.
                let mut distinct: Vec<u32> =
                    labels.chunk_by(|a, b| a == b).map(|run| run[0]).filter(|&l| l != 0).collect();
                distinct.sort_unstable();
                distinct.dedup();
                format!("{} rooms given {}", distinct.len(), note.reason)
            }
            None => format!("back to the online segmentation {}", note.reason),
        };
        let kind = if rooms.is_some() { "segmentation_given" } else { "segmentation_online" };
        Ok(Changeset {
            given_segmentation: Some((self.record.id, rooms.map(Rooms::from))),
            events: vec![self.event(kind, detail.trim_end().to_owned(), &note.actor, now)],
            at: Some(now),
            ..Changeset::default()
        })
    }

    /// Describes allowing a forbidden region again.
    pub(crate) fn prepare_allow(&self, id: u64, note: &OperatorNote, now: Timestamp) -> Result<Changeset, Error> {
        if !self.forbidden.iter().any(|r| r.id == id) {
            let known: Vec<String> = self.forbidden.iter().map(|r| r.id.to_string()).collect();
            return Err(Error::NotFound(format!(
                "mission {} has no forbidden region {id}; its forbidden regions are [{}]",
                self.record.id,
                known.join(", ")
            )));
        }
        let detail =
            if note.reason.is_empty() { format!("region {id}") } else { format!("region {id}: {}", note.reason) };
        Ok(Changeset {
            allowed: vec![id],
            events: vec![self.event("region_allowed", detail, &note.actor, now)],
            at: Some(now),
            ..Changeset::default()
        })
    }
}

fn operator_transition(
    task: &TaskRecord,
    to: TaskState,
    cause: &str,
    by: &str,
    at: Timestamp,
) -> crate::store::TaskChange {
    let mut change = transition(task, to, cause, Actor::Operator, at);
    change.transition.by = by.to_owned();
    change
}
