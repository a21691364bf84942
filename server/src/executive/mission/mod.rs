//! One mission's live state, and the rules that change it.
//!
//! Every operation follows the same three steps, so that nothing is
//! acknowledged before it is durable and a failed write changes nothing:
//! `prepare_*` checks the request against the state and describes its effect
//! as a [`Changeset`] without touching anything; the executive commits that
//! changeset to the store; [`Mission::apply`] then makes it the live state
//! and pushes changed assignments to the robots' watchers. A map update is
//! applied as soon as its write is queued and acknowledged once the write
//! is durable; if the write fails, the mission is reloaded from the store
//! (`executive::writer`).
//!
//! [`reports`] prepares what robots send (map updates, heartbeats, bids);
//! [`lifecycle`] adds what keeps a fleet honest (leases, stall detection,
//! blacklisted targets, completion with reasons); [`operator`] the overrides
//! of Simmons et al. 2000, §4.2, policy changes, forbidden regions and
//! pausing; [`planning`] turns a plan into tasks.

mod job;
mod lifecycle;
mod map_log;
mod operator;
mod planning;
mod reports;
#[cfg(test)]
pub(crate) mod testing;

pub(crate) use job::JobOutcome;
pub(crate) use planning::PlanBasis;

use std::collections::{BTreeMap, HashMap};
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};

use tokio::sync::watch;
use tokio::time::Instant;

use exploration::frontier::FrontierMap;
use exploration::fusion::MapFusion;
use exploration::grid::{CellRect, OccupancyGrid};
use exploration::math::Point2;
use exploration::policy::{Bid as PolicyBid, Policy};

use crate::domain::{
    Actor, AssignedTask, Assignment, BY_EXECUTIVE, MissionRecord, MissionState, Region, RobotId, RobotRecord, Rooms,
    TaskId, TaskKind, TaskRecord, TaskState, Timestamp, Transition,
};
use crate::error::Error;
use crate::store::{Changeset, CommitId, Fence, MissionCounters, StoredMap, TaskChange};

/// How close to its home a robot counts as home, metres.
const HOME_TOLERANCE_M: f64 = 0.5;

/// A task about to be created.
#[derive(Debug, Clone)]
struct TaskDraft {
    kind: TaskKind,
    target: Point2,
    created_by: String,
    note: String,
    policy: String,
    utility: f64,
    path_cost: f64,
    gain_region: Option<CellRect>,
}

/// What the store holds of a mission besides its record.
#[derive(Debug, Default)]
pub(crate) struct StoredMission {
    pub(crate) robots: Vec<RobotRecord>,
    pub(crate) map: StoredMap,
    pub(crate) open_tasks: Vec<TaskRecord>,
    pub(crate) blacklist: Vec<crate::domain::BlacklistEntry>,
    pub(crate) forbidden: Vec<Region>,
    pub(crate) rooms: Option<Rooms>,
}

/// A robot and the channel its assignment is pushed on.
#[derive(Debug)]
struct RobotSlot {
    record: RobotRecord,
    watch: watch::Sender<Assignment>,
    /// Whom it can communicate with, as it last said.
    peers: Vec<RobotId>,
    /// When it last reported, on the executive's clock (paused in tests).
    last_heard: Instant,
    /// How close it has come to its current target, and since when.
    progress: Option<lifecycle::Progress>,
    /// Targets it must not be sent to again until the map around them changes.
    blacklist: Vec<lifecycle::Blacklisted>,
    /// Its home task failed since the mission completed: do not send it again.
    home_failed: bool,
}

/// A mission's live state.
#[derive(Debug)]
pub(crate) struct Mission {
    record: MissionRecord,
    policy: Arc<dyn Policy>,
    fusion: MapFusion,
    frontier: FrontierMap,
    known_cells: u64,
    robots: BTreeMap<RobotId, RobotSlot>,
    names: HashMap<String, RobotId>,
    open_tasks: BTreeMap<TaskId, TaskRecord>,
    /// Each robot's latest bids, in cells.
    bids: BTreeMap<RobotId, Vec<PolicyBid>>,
    /// Robots whose bids arrived since they were last planned for.
    fresh_bids: std::collections::BTreeSet<RobotId>,
    last_replan: Instant,
    frontier_at_replan: usize,
    frontier_churn: usize,
    /// Patches since the last replanning that may have changed some robot's
    /// own map without changing the fused one (missions scoped by communication).
    layer_changes: usize,
    /// Why the next operation must replan, when an event asked for it.
    pending_replan: Option<String>,
    /// Counts the changes that make a plan made before them unusable (the
    /// policy, the forbidden regions, pausing, the sub-teams).
    structure: u64,
    /// Counts the events that demand a new plan (robots joining, tasks
    /// ending, ...): a plan made before the latest one is still committed
    /// for the robots it fits, and the demand stays for the next plan.
    demands: u64,
    /// Tasks whose target was found explored at a replanning (not to trigger again).
    explored_tasks: std::collections::HashSet<TaskId>,
    /// Regions where no target is assigned.
    forbidden: Vec<Region>,
    /// Rooms and corridors given with the mission (Wurm et al. 2008, §VI).
    rooms: Option<Rooms>,
    /// The last replanning could not be committed: the sweep tries again.
    replan_failed: bool,
    /// Robots whose records changed only by liveness reports since they
    /// were last written (see [`Mission::apply_unsaved`]).
    unsaved: std::collections::BTreeSet<RobotId>,
    /// The robots of the write-behind changeset in flight, to mark again if
    /// it fails.
    unsaved_in_flight: Vec<RobotId>,
    /// Bumped whenever something an operator watches changes.
    changed: watch::Sender<u64>,
    /// Where the fused map changed lately, for watchers.
    map_log: map_log::MapLog,
    /// The last changeset queued for the store; the next one follows it
    /// (see [`crate::store::Store::submit`]).
    last_commit: Option<CommitId>,
    /// How many times the mission was reloaded after a failed write.
    generation: u64,
    /// The lease this replica holds the mission by, when replicas share the
    /// database: every changeset carries it (see [`crate::store::lease`]).
    fence: Option<Fence>,
    /// Deleted by an operator: nothing more of it is written.
    deleted: bool,
}

impl Mission {
    /// A mission from its stored state: replays the map log, reopens its tasks.
    pub(crate) fn restore(record: MissionRecord, stored: StoredMission, now: Instant) -> Result<Self, Error> {
        let StoredMission { robots, map, open_tasks, blacklist, forbidden, rooms } = stored;
        let policy: Arc<dyn Policy> = Arc::from(record.spec.policy.build());
        let fusion = map
            .fuse(&record.spec.frame, robots.len())
            .map_err(|e| Error::Internal(format!("mission {}: its stored map: {e}", record.id)))?;
        let known_cells = fusion.grid().known_cells() as u64;
        let frontier = FrontierMap::detect(fusion.grid());
        let mut mission = Self {
            policy,
            fusion,
            frontier_at_replan: frontier.len(),
            frontier,
            known_cells,
            robots: BTreeMap::new(),
            names: HashMap::new(),
            open_tasks: open_tasks.into_iter().map(|t| (t.id, t)).collect(),
            bids: BTreeMap::new(),
            fresh_bids: std::collections::BTreeSet::new(),
            last_replan: now,
            frontier_churn: 0,
            layer_changes: 0,
            pending_replan: Some("executive restarted".to_owned()),
            structure: 0,
            demands: 0,
            explored_tasks: std::collections::HashSet::new(),
            forbidden,
            rooms,
            replan_failed: false,
            unsaved: std::collections::BTreeSet::new(),
            unsaved_in_flight: Vec::new(),
            changed: watch::channel(0).0,
            map_log: map_log::MapLog::default(),
            last_commit: None,
            generation: 0,
            fence: None,
            deleted: false,
            record,
        };
        for robot in robots {
            mission.insert_robot(robot, now);
        }
        for entry in blacklist {
            mission.add_blacklisted(entry);
        }
        Ok(mission)
    }

    /// A mission just created.
    pub(crate) fn new(record: MissionRecord, now: Instant) -> Self {
        let mut mission = Self::restore(record, StoredMission::default(), now)
            .unwrap_or_else(|_| unreachable!("an empty log always applies"));
        mission.pending_replan = None;
        mission
    }

    pub(crate) fn record(&self) -> &MissionRecord {
        &self.record
    }

    /// The last changeset queued for the store.
    pub(crate) fn last_commit(&self) -> Option<CommitId> {
        self.last_commit
    }

    /// The lease this replica holds the mission by, if replicas share the database.
    pub(crate) fn fence(&self) -> Option<Fence> {
        self.fence
    }

    /// Whether an operator deleted it (see [`Self::prepare_delete`]).
    pub(crate) fn is_deleted(&self) -> bool {
        self.deleted
    }

    /// Its deletion is durable: nothing more of it may be written.
    pub(crate) fn mark_deleted(&mut self) {
        self.deleted = true;
        // Its watchers look again, and are told it is gone.
        self.changed.send_modify(|v| *v += 1);
    }

    /// This replica claimed the mission with `fence`.
    pub(crate) fn set_fence(&mut self, fence: Fence) {
        self.fence = Some(fence);
    }

    /// `id` was queued for the store after every earlier changeset.
    pub(crate) fn set_last_commit(&mut self, id: CommitId) {
        self.last_commit = Some(id);
    }

    /// The last changeset was refused on its own, after every earlier one
    /// was written: the next follows none.
    pub(crate) fn chain_broken_by_own_failure(&mut self) {
        self.last_commit = None;
    }

    /// Counts reloads after failed writes, to reload once per failure.
    pub(crate) fn generation(&self) -> u64 {
        self.generation
    }

    /// Becomes `fresh`, the mission as the store holds it after a write that
    /// the live state held already failed. The robots' assignment streams,
    /// the operators' watchers and what is known only in memory about each
    /// robot's liveness carry over; the map's watchers are sent the whole
    /// map again.
    pub(crate) fn replace_after_failed_write(&mut self, fresh: Mission) {
        let old = std::mem::replace(self, fresh);
        self.generation = old.generation + 1;
        self.fence = old.fence;
        self.last_commit = None;
        self.map_log = map_log::MapLog::after(old.map_log.version());
        self.pending_replan = Some("the mission was reloaded after a failed write".to_owned());
        for (id, old_slot) in old.robots {
            let Some(assignment) = self.robots.get(&id).map(|slot| self.assignment_for(&slot.record)) else { continue };
            let Some(slot) = self.robots.get_mut(&id) else { continue };
            slot.watch = old_slot.watch;
            slot.peers = old_slot.peers;
            slot.last_heard = old_slot.last_heard;
            slot.progress = old_slot.progress;
            slot.watch.send_replace(assignment);
        }
        self.changed = old.changed;
        self.changed.send_modify(|v| *v += 1);
    }

    pub(crate) fn robot_count(&self) -> usize {
        self.robots.len()
    }

    pub(crate) fn known_cells(&self) -> u64 {
        self.known_cells
    }

    pub(crate) fn frontier_cells(&self) -> usize {
        self.frontier.len()
    }

    pub(crate) fn grid(&self) -> &OccupancyGrid {
        self.fusion.grid()
    }

    pub(crate) fn frontier(&self) -> &FrontierMap {
        &self.frontier
    }

    /// Where the fused map changed lately.
    pub(crate) fn map_log(&self) -> &map_log::MapLog {
        &self.map_log
    }

    pub(crate) fn robot_by_name(&self, name: &str) -> Option<&RobotRecord> {
        self.names.get(name).and_then(|id| self.robots.get(id)).map(|s| &s.record)
    }

    pub(crate) fn robot(&self, id: RobotId) -> Result<&RobotRecord, Error> {
        self.robots.get(&id).map(|s| &s.record).ok_or_else(|| Error::NotFound(format!("robot {id} does not exist")))
    }

    pub(crate) fn robots(&self) -> impl Iterator<Item = &RobotRecord> {
        self.robots.values().map(|s| &s.record)
    }

    /// The target of a robot's current task.
    pub(crate) fn target_of(&self, robot: &RobotRecord) -> Option<Point2> {
        robot.current_task.and_then(|t| self.open_tasks.get(&t)).map(|t| t.target)
    }

    /// Adds a robot just registered (or restored); its lease starts now.
    pub(crate) fn insert_robot(&mut self, record: RobotRecord, now: Instant) {
        let assignment = self.assignment_for(&record);
        let (watch, _) = watch::channel(assignment);
        self.names.insert(record.name.clone(), record.id);
        self.robots.insert(
            record.id,
            RobotSlot {
                record,
                watch,
                peers: Vec::new(),
                last_heard: now,
                progress: None,
                blacklist: Vec::new(),
                home_failed: false,
            },
        );
        self.demand_replan("robot joined".to_owned());
        self.changed.send_modify(|v| *v += 1);
    }

    /// A receiver that sees a new value whenever an operator's view of the
    /// mission changes (assignments, liveness, state).
    pub(crate) fn subscribe(&self) -> watch::Receiver<u64> {
        self.changed.subscribe()
    }

    /// The mission's forbidden regions.
    pub(crate) fn forbidden(&self) -> &[Region] {
        &self.forbidden
    }

    /// Whether the mission was given its rooms and corridors.
    pub(crate) fn has_rooms(&self) -> bool {
        self.rooms.is_some()
    }

    /// How many targets are blacklisted for a robot.
    pub(crate) fn blacklisted(&self, id: RobotId) -> usize {
        self.robots.get(&id).map_or(0, |s| s.blacklist.len())
    }

    /// The kind of a robot's current task.
    pub(crate) fn task_kind_of(&self, robot: &RobotRecord) -> Option<TaskKind> {
        robot.current_task.and_then(|t| self.open_tasks.get(&t)).map(|t| t.kind)
    }

    /// Whether the policy assigns this robot: it is heard from and not under an override.
    fn in_pool(&self, robot: &RobotRecord) -> bool {
        !robot.lost && !robot.current_task.and_then(|t| self.open_tasks.get(&t)).is_some_and(TaskRecord::is_override)
    }

    /// The robot's assignment as it stands. For an answer given only once
    /// the caller's own changeset is durable (changesets become durable in
    /// order, so everything applied before it is durable too); otherwise
    /// see [`Mission::assignment_told`].
    pub(crate) fn assignment(&self, id: RobotId) -> Result<Assignment, Error> {
        Ok(self.assignment_for(self.robot(id)?))
    }

    /// The robot's assignment as far as it may be told now: the one last
    /// pushed to its stream while a changeset that changed it is not yet
    /// durable (see [`Mission::apply_queued`]), else as it stands.
    pub(crate) fn assignment_told(&self, id: RobotId) -> Result<Assignment, Error> {
        let robot = self.robot(id)?;
        match self.robots.get(&id) {
            Some(slot) if slot.watch.borrow().version != robot.assignment_version => Ok(slot.watch.borrow().clone()),
            _ => Ok(self.assignment_for(robot)),
        }
    }

    fn assignment_for(&self, robot: &RobotRecord) -> Assignment {
        let task = robot.current_task.and_then(|t| self.open_tasks.get(&t)).map(|t| AssignedTask {
            id: t.id,
            kind: t.kind,
            target: t.target,
            utility: t.utility,
            path_cost: t.path_cost,
            gain_region: t.gain_region.map(|r| self.world_rect(r)),
        });
        Assignment {
            robot_id: robot.id,
            version: robot.assignment_version,
            task,
            policy: self.record.spec.policy.name(),
            mission_state: self.record.state,
            paused: self.record.paused,
        }
    }

    /// A receiver of the robot's assignments.
    pub(crate) fn watch(&self, id: RobotId) -> Result<watch::Receiver<Assignment>, Error> {
        self.robots
            .get(&id)
            .map(|s| s.watch.subscribe())
            .ok_or_else(|| Error::NotFound(format!("robot {id} does not exist")))
    }

    /// A rectangle of cells as its world corners.
    fn world_rect(&self, r: CellRect) -> (Point2, Point2) {
        let frame = &self.record.spec.frame;
        let corner = |x: i32, y: i32| {
            Point2::new(
                frame.origin.x + f64::from(x) * frame.resolution,
                frame.origin.y + f64::from(y) * frame.resolution,
            )
        };
        (corner(r.x, r.y), corner(r.x_end(), r.y_end()))
    }

    fn counters(&self) -> MissionCounters {
        MissionCounters {
            id: self.record.id,
            state: self.record.state,
            replans: self.record.replans,
            map_updates: self.record.map_updates,
            paused: self.record.paused,
            leftovers: self.record.leftovers.clone(),
        }
    }

    /// Makes a durable changeset the live state, and tells the robots
    /// every assignment that moved: every changeset queued before it is
    /// durable too.
    pub(crate) fn apply(&mut self, changes: Changeset) {
        self.apply_changes(changes);
        self.tell(self.moved_assignments());
    }

    /// Makes a changeset queued but not yet durable the live state, so that
    /// the mission need not be held while the disk works, and returns the
    /// assignments that moved, to [`Mission::tell`] once it is durable:
    /// before that no robot is told them (changesets become durable in
    /// order, so those of earlier changesets may be told with it).
    pub(crate) fn apply_queued(&mut self, changes: Changeset) -> Vec<Assignment> {
        self.apply_changes(changes);
        self.moved_assignments()
    }

    /// The assignments whose version moved since they were last told.
    fn moved_assignments(&self) -> Vec<Assignment> {
        self.robots
            .values()
            .filter(|s| s.watch.borrow().version != s.record.assignment_version)
            .map(|s| self.assignment_for(&s.record))
            .collect()
    }

    /// Tells the robots assignments of a changeset now durable, unless a
    /// newer one was told already.
    pub(crate) fn tell(&self, assignments: Vec<Assignment>) {
        for assignment in assignments {
            if let Some(slot) = self.robots.get(&assignment.robot_id)
                && slot.watch.borrow().version < assignment.version
            {
                slot.watch.send_replace(assignment);
            }
        }
    }

    fn apply_changes(&mut self, changes: Changeset) {
        for logged in &changes.patches {
            match self.fusion.apply(logged.robot_id, &logged.patch) {
                Ok(change) => {
                    self.layer_changes += 1;
                    self.known_cells += change.newly_known;
                    if let Some(rect) = change.changed {
                        let delta = self.frontier.update(self.fusion.grid(), rect);
                        self.frontier_churn += delta.added + delta.removed;
                        self.map_log.record(rect);
                    }
                }
                // Prepared changesets were checked against the grid.
                Err(e) => {
                    tracing::error!(mission = self.record.id, error = %e, "checked patch did not apply")
                }
            }
        }
        for task in changes.new_tasks {
            self.open_tasks.insert(task.id, task);
        }
        for change in &changes.task_changes {
            if change.state.is_terminal() {
                let Some(task) = self.open_tasks.remove(&change.task_id) else { continue };
                if change.state == TaskState::Failed
                    && task.kind == TaskKind::Home
                    && task.created_by == BY_EXECUTIVE
                    && let Some(slot) = self.robots.get_mut(&task.robot_id)
                {
                    slot.home_failed = true;
                }
                // Its robot is free: the others' plan may change too.
                if change.state != TaskState::Preempted {
                    self.demand_replan(format!("task {}: {}", task.id, change.transition.cause));
                }
            } else if let Some(task) = self.open_tasks.get_mut(&change.task_id) {
                task.state = change.state;
                task.updated_at = change.transition.at;
            }
        }
        if let Some((_, policy)) = changes.policy {
            self.policy = Arc::from(policy.build());
            self.record.spec.policy = policy;
            self.structure += 1;
            self.demand_replan("policy changed".to_owned());
        }
        if let Some(counters) = changes.mission {
            if counters.state == MissionState::Active && self.record.state == MissionState::Completed {
                for slot in self.robots.values_mut() {
                    slot.home_failed = false;
                }
            }
            if !counters.paused && self.record.paused {
                self.demand_replan("mission resumed".to_owned());
            } else if counters.paused && !self.record.paused {
                // A plan made before the pause must not be committed after it.
                self.structure += 1;
            }
            self.record.state = counters.state;
            self.record.replans = counters.replans;
            self.record.map_updates = counters.map_updates;
            self.record.paused = counters.paused;
            self.record.leftovers = counters.leftovers;
        }
        for robot in changes.robots {
            let Some(slot) = self.robots.get_mut(&robot.id) else {
                continue;
            };
            let (was_lost, is_lost, id) = (slot.record.lost, robot.lost, robot.id);
            slot.record = robot;
            if was_lost && !is_lost {
                self.demand_replan(format!("robot {id} reported again"));
            }
        }
        for entry in changes.blacklisted {
            self.add_blacklisted(entry);
        }
        for (robot, cell) in &changes.unblacklisted {
            if let Some(slot) = self.robots.get_mut(robot) {
                slot.blacklist.retain(|b| b.entry.cell != *cell);
            }
        }
        if !changes.forbidden.is_empty() || !changes.allowed.is_empty() {
            self.forbidden.retain(|r| !changes.allowed.contains(&r.id));
            self.forbidden.extend(changes.forbidden);
            self.structure += 1;
            self.demand_replan("forbidden regions changed".to_owned());
        }
        if let Some((_, rooms)) = changes.given_segmentation {
            self.rooms = rooms;
            self.structure += 1;
            self.demand_replan("given segmentation changed".to_owned());
        }
        self.changed.send_modify(|v| *v += 1);
    }

    /// The cells of a world rectangle, clipped to the map; `None` outside it.
    fn cell_rect(&self, min: Point2, max: Point2) -> Option<CellRect> {
        self.record.spec.frame.rect_from_world(&min, &max)
    }

    /// A new task for a robot, with its first transition.
    #[allow(clippy::too_many_arguments)]
    fn open_task(
        &self,
        robot_id: RobotId,
        draft: TaskDraft,
        cause: &str,
        actor: Actor,
        by: &str,
        now: Timestamp,
        task_ids: &AtomicU64,
    ) -> TaskRecord {
        TaskRecord {
            id: task_ids.fetch_add(1, Ordering::Relaxed) + 1,
            mission_id: self.record.id,
            robot_id,
            kind: draft.kind,
            target: draft.target,
            state: TaskState::Assigned,
            policy: draft.policy,
            utility: draft.utility,
            path_cost: draft.path_cost,
            gain_region: draft.gain_region,
            created_by: draft.created_by,
            note: draft.note,
            created_at: now,
            updated_at: now,
            transitions: vec![Transition {
                from: None,
                to: TaskState::Assigned,
                at: now,
                cause: cause.to_owned(),
                actor,
                by: by.to_owned(),
            }],
        }
    }
}

fn transition(task: &TaskRecord, to: TaskState, cause: &str, actor: Actor, at: Timestamp) -> TaskChange {
    TaskChange {
        task_id: task.id,
        state: to,
        transition: Transition { from: Some(task.state), to, at, cause: cause.to_owned(), actor, by: String::new() },
    }
}
