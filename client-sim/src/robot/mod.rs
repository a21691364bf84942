//! One simulated robot: its own gRPC client, its own map, its sensor, its motion.
//!
//! A robot behaves as a real one talking to the executive would: it senses
//! with a range sensor (ray casting in the true world), sends the cells its
//! map gained as a patch with its pose and a sequence number, follows its
//! assigned target along a shortest path one cell per step, and reports
//! arrival. It watches its assignment stream and retries through outages of
//! the executive, resending an unacknowledged update under the same number.
//!
//! With unlimited communication the team shares one map (Burgard et al.
//! 2005, §III), on which every robot plans its path, and each robot sends
//! the executive its own measurements. With limited communication each
//! robot knows only what it measured and what peers in range passed on:
//! every robot keeps a log of the measurements it integrated (its own and
//! forwarded ones) and, for each peer, how much of it that peer already
//! has, so nothing is sent or integrated twice and robots that meet end up
//! with their clusters' joint map (§III); it plans on its own map and sends
//! the executive its whole knowledge.
//!
//! Here: the robot's state and its step (move, sense, report, adopt);
//! `body.rs`: sensing, the maps it keeps and shares, the way around others;
//! `link.rs`: its gRPC client, assignment stream and retries.

use std::collections::VecDeque;
use std::time::Duration;

use exploration_proto::client::status_line;
use exploration_proto::replicas::Replicas;
use tokio::sync::watch;
use tonic::Status;

use exploration::cost::{TraversalMap, shortest_path};
use exploration::grid::{Cell, CellClass, CellRect, OccupancyGrid};
use exploration::policy::Capabilities;
use exploration::visibility::RangeSensor;
use exploration_proto::Bearer;
use exploration_proto::v1 as pb;
use exploration_proto::v1::fleet_client::FleetClient;

use crate::world::World;

mod body;
mod link;

pub use body::{Occupancy, TeamMap};
pub(crate) use link::retry;

/// The speed at which a robot moves one cell per step.
pub const REFERENCE_SPEED_MPS: f64 = 0.5;

/// What every robot of the team can do.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RobotModel {
    /// Sensor range, metres.
    pub sensor_range_m: f64,
    /// Sensor field of view, radians.
    pub field_of_view_rad: f64,
    /// Speed, metres per second: a robot of 0.5 m/s moves one cell per step,
    /// faster and slower ones proportionally more or fewer.
    pub speed_mps: f64,
    /// Footprint radius, metres.
    pub footprint_radius_m: f64,
}

/// Why a robot could not go on.
#[derive(Debug, thiserror::Error)]
pub enum RobotError {
    /// The executive refused a request for good.
    #[error("{what}: {}", status_line(.status))]
    Rpc {
        /// Which request.
        what: &'static str,
        /// The executive's answer.
        status: Status,
    },
    /// The executive stayed unreachable past the retry budget.
    #[error("{what}: the executive stayed unreachable for {budget:?}: {}", status_line(.status))]
    Unreachable {
        /// Which request.
        what: &'static str,
        /// How long the robot kept trying.
        budget: Duration,
        /// The last error.
        status: Status,
    },
}

/// The robot's view of its assignment.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Task {
    id: u64,
    target: Cell,
    /// A hold: stay, nothing to arrive at.
    hold: bool,
}

/// A fleet client that sends a bearer token.
type Client = FleetClient<tonic::service::interceptor::InterceptedService<Replicas, Bearer>>;

/// How a simulated robot misbehaves (failure injection).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Faults {
    /// From this step on it is dead: silent, still.
    pub dies_at: Option<u64>,
    /// From this step on it cannot move, but reports as usual.
    pub freezes_at: Option<u64>,
    /// Targets inside this rectangle of cells it reports unreachable.
    pub unreachable: Option<CellRect>,
}

/// How a step went.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct StepOutcome {
    /// The robot moved one cell.
    pub moved: bool,
    /// It has a task.
    pub has_task: bool,
    /// The executive reports the mission complete.
    pub mission_completed: bool,
    /// The robot is dead (failure injection): it did nothing.
    pub dead: bool,
}

/// A simulated robot.
#[derive(Debug)]
pub struct SimRobot {
    /// Its name in the mission.
    pub name: String,
    /// Its identity at the executive.
    pub id: u64,
    client: Client,
    /// The cell it stands on.
    pub cell: Cell,
    heading: f64,
    sensor: RangeSensor,
    /// What it knows: its measurements, and its peers' under limited communication.
    pub own: OccupancyGrid,
    /// Reachable free cells it knows.
    pub known_reachable: usize,
    /// Every measurement it integrated, its own and those peers passed on, in
    /// order (cell index, occupied): what it forwards to the others.
    log: Vec<(u32, bool)>,
    /// For each robot of the team (by index), how much of `log` it has.
    sent: Vec<usize>,
    /// Cells its own sensor has covered (its map also holds what peers sent).
    seen: Vec<bool>,
    /// Cells changed since the last update sent.
    dirty: Option<CellRect>,
    /// Plan on its own map and send its knowledge (limited communication).
    limited: bool,
    /// Cells it may move this step, accumulated from its speed.
    stride: f64,
    /// The robots it can communicate with now (limited communication).
    pub peers: Vec<u64>,
    seq: u64,
    task: Option<Task>,
    acknowledged_task: Option<u64>,
    path: VecDeque<Cell>,
    /// Metres travelled.
    pub distance_m: f64,
    /// Cells visited, in order.
    pub trajectory: Vec<Cell>,
    retry_budget: Duration,
    stream: watch::Receiver<Option<pb::Assignment>>,
    /// Steps at which the stream had not yet delivered the version a response named.
    pub stream_lags: u64,
    /// Map updates the executive acknowledged (or recognised as already applied).
    pub acknowledged_updates: u64,
    /// Times it was sent to a target out of sensor range of the one it had,
    /// before reaching that (not counting new targets after it reported one
    /// unreachable): how much a policy makes robots change their minds. A
    /// new cell in sensor range of the old looks at the same place, as when
    /// a frontier recedes while the robot approaches it.
    pub target_switches: u64,
    capabilities: Capabilities,
    bidding: Option<Bidding>,
    steps_since_bid: u64,
    /// The mission is paused: hold.
    paused: bool,
    faults: Faults,
    steps: u64,
    /// Steps it has waited for a robot in its way.
    waited: u32,
}

/// Steps a robot waits for another in its way before it goes around it.
const WAIT_BEFORE_DETOUR: u32 = 3;

/// Steps a robot waits for another in its way, with no way around it,
/// before the two squeeze past each other.
const WAIT_BEFORE_SQUEEZING_PAST: u32 = 10;

/// How a robot bids (Simmons et al. 2000, §4.1), when its mission's policy wants bids.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Bidding {
    /// Bid every this many steps.
    pub every: u64,
    /// Bid frontier cells at least this far apart, metres.
    pub spacing_m: f64,
}

impl SimRobot {
    /// Makes the robot misbehave as `faults` say.
    pub fn inject(&mut self, faults: Faults) {
        self.faults = faults;
    }

    /// The faults injected so far.
    pub fn faults(&self) -> Faults {
        self.faults
    }

    /// Whether it is dead (failure injection) at this step.
    pub fn is_dead(&self) -> bool {
        self.faults.dies_at.is_some_and(|s| self.steps >= s)
    }

    /// One step: move (unless `blocked`: interference) into free cells no
    /// other robot stands on (`occupied` holds the team's cells and is kept
    /// up to date), sense, report, adopt the assignment.
    pub async fn step(
        &mut self,
        world: &World,
        team: &mut TeamMap,
        blocked: bool,
        occupied: &mut Occupancy,
    ) -> Result<StepOutcome, RobotError> {
        let mut outcome = StepOutcome::default();
        self.steps += 1;
        if self.is_dead() {
            outcome.dead = true;
            return Ok(outcome);
        }
        let frozen = self.faults.freezes_at.is_some_and(|s| self.steps >= s);
        let blocked = blocked || frozen || self.paused;
        // Move along the path, as many cells as the speed allows this step.
        self.stride += self.capabilities.speed_mps / REFERENCE_SPEED_MPS;
        while self.stride >= 1.0 {
            self.stride -= 1.0;
            if blocked {
                continue;
            }
            let Some(&next) = self.path.front() else {
                self.stride = self.stride.min(1.0);
                break;
            };
            if world.is_blocked(next) {
                self.path.clear();
                break;
            }
            if occupied.is_taken(next) {
                // Another robot stands there: wait, after a while go around
                // it, and where there is no way around (two robots head-on
                // in a corridor one cell wide) squeeze past it in the end, as
                // robots negotiate passing; otherwise both would wait forever.
                self.waited += 1;
                let around = self.waited >= WAIT_BEFORE_DETOUR && self.detour(world, team, occupied);
                if around || self.waited < WAIT_BEFORE_SQUEEZING_PAST {
                    break;
                }
            }
            self.path.pop_front();
            self.waited = 0;
            occupied.step(self.cell, next);
            let (dx, dy) = (next.x - self.cell.x, next.y - self.cell.y);
            self.heading = f64::from(dy).atan2(f64::from(dx));
            self.distance_m += self.cell.distance(next) * world.frame.resolution;
            self.cell = next;
            self.trajectory.push(next);
            outcome.moved = true;
            if self.task.is_some_and(|t| t.target == next) {
                break;
            }
        }
        // Arrived: say so; the answer carries the next assignment.
        if let Some(task) = self.task.filter(|t| t.target == self.cell && !t.hold) {
            let assignment = self.heartbeat(world, pb::RobotState::Arrived, task.id, "").await?;
            self.adopt(assignment, world, team).await?;
        }
        self.sense(world, team);
        let patch = self.patch();
        let assignment = self.send_update(world, patch).await?;
        let completed = assignment.mission_state == pb::MissionState::Completed as i32;
        self.paused = assignment.mission_state == pb::MissionState::Paused as i32;
        self.adopt(assignment, world, team).await?;
        // Bidding robots (Simmons et al. 2000) bid on a fresh map now and
        // then, and whenever they have nothing to do.
        if let Some(bidding) = self.bidding {
            self.steps_since_bid += 1;
            if self.steps_since_bid >= bidding.every || self.task.is_none() {
                self.steps_since_bid = 0;
                let assignment = self.submit_bids(world, team, bidding.spacing_m).await?;
                self.adopt(assignment, world, team).await?;
            }
        }
        outcome.has_task = self.task.is_some();
        outcome.mission_completed = completed;
        Ok(outcome)
    }

    /// Takes up an assignment: plans a path to a new target, acknowledges it,
    /// or reports failure when the target cannot be reached.
    async fn adopt(&mut self, mut assignment: pb::Assignment, world: &World, team: &TeamMap) -> Result<(), RobotError> {
        // Up to a few rounds: a failure report brings a new assignment.
        for round in 0..4 {
            self.check_stream(assignment.version).await;
            let target = assignment
                .target
                .as_ref()
                .filter(|_| assignment.task_id != 0)
                .and_then(|p| world.frame.cell_from_world(&exploration::math::Point2::new(p.x, p.y)));
            let hold = assignment.kind == pb::TaskKind::Hold as i32;
            let task = target.map(|target| Task { id: assignment.task_id, target, hold });
            if task == self.task {
                return Ok(());
            }
            let same_place = (self.capabilities.sensor_range_m / world.frame.resolution).max(1.0);
            if round == 0 && is_switch(self.task, task, self.cell, same_place) {
                self.target_switches += 1;
            }
            self.task = task;
            self.path.clear();
            let Some(task) = task else {
                return Ok(());
            };
            if task.hold {
                return Ok(());
            }
            if self.faults.unreachable.is_some_and(|r| r.contains(task.target)) {
                assignment =
                    self.heartbeat(world, pb::RobotState::Failed, task.id, "injected: cannot get there").await?;
                continue;
            }
            let map = if self.limited { &self.own } else { &team.grid };
            let path = if self.capabilities.footprint_radius_m > 0.0 {
                let traversal = TraversalMap::free_space(map, self.capabilities.footprint_radius_m);
                shortest_path(&world.frame, self.cell, task.target, |c| traversal.passable(c))
            } else {
                shortest_path(&world.frame, self.cell, task.target, |c| map.class(c) == CellClass::Free)
            };
            match path {
                Some(path) => {
                    self.path = path.into_iter().skip(1).collect();
                    if self.acknowledged_task != Some(task.id) {
                        self.acknowledged_task = Some(task.id);
                        let next = self.heartbeat(world, pb::RobotState::Moving, task.id, "").await?;
                        if next.version > assignment.version {
                            assignment = next;
                            continue;
                        }
                    }
                    return Ok(());
                }
                None => {
                    assignment =
                        self.heartbeat(world, pb::RobotState::Failed, task.id, "no known path to the target").await?;
                }
            }
        }
        Ok(())
    }
}

/// Whether going from task `from` to task `to` at `cell` abandons a target
/// before reaching it for one more than `same_place` cells away.
fn is_switch(from: Option<Task>, to: Option<Task>, cell: Cell, same_place: f64) -> bool {
    match (from, to) {
        (Some(from), Some(to)) => {
            !from.hold && !to.hold && from.target != cell && from.target.distance(to.target) > same_place
        }
        _ => false,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn task(x: i32) -> Option<Task> {
        Some(Task { id: x as u64, target: Cell::new(x, 0), hold: false })
    }

    #[test]
    fn only_a_jump_away_from_an_unreached_target_is_a_switch() {
        let here = Cell::new(0, 5);
        assert!(is_switch(task(10), task(30), here, 5.0), "abandoned for a far target");
        assert!(!is_switch(task(10), task(14), here, 5.0), "the frontier receded: the same place");
        assert!(!is_switch(task(10), task(30), Cell::new(10, 0), 5.0), "reached, then sent on");
        assert!(!is_switch(None, task(30), here, 5.0), "first task");
        assert!(!is_switch(task(10), None, here, 5.0), "task withdrawn");
        let hold = Some(Task { id: 1, target: Cell::new(10, 0), hold: true });
        assert!(!is_switch(hold, task(30), here, 5.0), "released from a hold");
    }
}
