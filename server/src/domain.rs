//! The executive's own types: what the service converts requests into, what
//! the executive works on and what the store persists. No protocol types and
//! no SQL here.

use std::collections::BTreeMap;
use std::time::{Duration, SystemTime, UNIX_EPOCH};

use exploration::fusion::Patch;
use exploration::grid::{CellRect, GridFrame};
use exploration::math::Point2;
use exploration::policy::{Capabilities, PolicyConfig};

/// A mission's identity.
pub type MissionId = u64;
/// A robot's identity (unique across missions).
pub type RobotId = u64;
/// A task's identity (unique across missions).
pub type TaskId = u64;

/// Milliseconds since the Unix epoch, the executive's clock for records.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub struct Timestamp(pub i64);

impl Timestamp {
    /// Now, by the system clock.
    pub fn now() -> Self {
        Self::from(SystemTime::now())
    }

    /// Milliseconds since the epoch.
    pub fn millis(self) -> i64 {
        self.0
    }
}

impl From<SystemTime> for Timestamp {
    fn from(t: SystemTime) -> Self {
        let millis = match t.duration_since(UNIX_EPOCH) {
            Ok(d) => d.as_millis() as i64,
            Err(e) => -(e.duration().as_millis() as i64),
        };
        Self(millis)
    }
}

/// A planar pose in a mission's world frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Pose {
    /// Position, metres.
    pub position: Point2,
    /// Heading, radians.
    pub heading: f64,
}

/// When to replan besides arrivals and failures (Burgard et al. 2005, §II-C).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ReplanSettings {
    /// Replan once a robot travelled this far since its assignment, metres.
    pub distance_m: f64,
    /// Replan once this much time passed since the last replanning.
    pub interval: Duration,
    /// Replan once this share of the frontier was added or removed.
    pub frontier_change: f64,
}

impl Default for ReplanSettings {
    fn default() -> Self {
        Self { distance_m: 3.0, interval: Duration::from_secs(30), frontier_change: 0.25 }
    }
}

/// How the executive watches a mission's robots.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LifecycleSettings {
    /// A robot not heard from for this long loses its task.
    pub lease: Duration,
    /// A robot that gets no closer to its target for this long has the task
    /// failed (explore_lite's `progress_timeout`, 30 s).
    pub stall: Duration,
    /// Where robots go when the mission completes; each its start pose when `None`.
    pub rendezvous: Option<Point2>,
}

impl Default for LifecycleSettings {
    fn default() -> Self {
        Self { lease: Duration::from_secs(15), stall: Duration::from_secs(30), rendezvous: None }
    }
}

/// What a mission is made of.
#[derive(Debug, Clone, PartialEq)]
pub struct MissionSpec {
    /// Human-readable name.
    pub name: String,
    /// Its grid.
    pub frame: GridFrame,
    /// Its coordination policy.
    pub policy: PolicyConfig,
    /// Its replanning triggers.
    pub replan: ReplanSettings,
    /// Each connected sub-team is coordinated apart (Burgard et al. 2005, §II-D).
    pub scoped_by_communication: bool,
    /// Each request that makes a replanning due is answered after it
    /// (simulations: deterministic); otherwise plans are made off the
    /// request path.
    pub lockstep: bool,
    /// Leases, stall detection, rendezvous.
    pub lifecycle: LifecycleSettings,
}

/// Where a mission is in its life.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum MissionState {
    /// Robots are being assigned targets.
    Active,
    /// No reachable frontier is left.
    Completed,
}

impl MissionState {
    /// The name stored and logged.
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Active => "active",
            Self::Completed => "completed",
        }
    }

    /// Parses a stored name.
    pub fn parse(s: &str) -> Option<Self> {
        match s {
            "active" => Some(Self::Active),
            "completed" => Some(Self::Completed),
            _ => None,
        }
    }
}

/// A mission as stored.
#[derive(Debug, Clone, PartialEq)]
pub struct MissionRecord {
    /// Its identity.
    pub id: MissionId,
    /// What it is.
    pub spec: MissionSpec,
    /// Where it is.
    pub state: MissionState,
    /// Replannings so far.
    pub replans: u64,
    /// Map updates applied so far.
    pub map_updates: u64,
    /// Paused by an operator.
    pub paused: bool,
    /// The frontier left at completion, and why.
    pub leftovers: Leftovers,
    /// When it was created.
    pub created_at: Timestamp,
}

/// Why part of the frontier was not explored.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
pub enum LeftoverReason {
    /// Smaller than the policy's minimum frontier size.
    TooSmall,
    /// Behind passages narrower than every robot's footprint.
    TooNarrow,
    /// Not connected to any robot through known free space.
    Disconnected,
    /// Blacklisted for every robot that could reach it.
    Blacklisted,
    /// Inside a forbidden region.
    Forbidden,
}

impl LeftoverReason {
    /// The name stored and shown.
    pub fn as_str(self) -> &'static str {
        match self {
            Self::TooSmall => "too_small",
            Self::TooNarrow => "too_narrow",
            Self::Disconnected => "disconnected",
            Self::Blacklisted => "blacklisted",
            Self::Forbidden => "forbidden",
        }
    }

    /// Parses a stored name.
    pub fn parse(s: &str) -> Option<Self> {
        Some(match s {
            "too_small" => Self::TooSmall,
            "too_narrow" => Self::TooNarrow,
            "disconnected" => Self::Disconnected,
            "blacklisted" => Self::Blacklisted,
            "forbidden" => Self::Forbidden,
            _ => return None,
        })
    }
}

/// One frontier cluster left at completion.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Leftover {
    /// Why it was left.
    pub reason: LeftoverReason,
    /// Its frontier cells.
    pub cells: usize,
    /// Its cell nearest to its centroid, in the world frame.
    pub position: Point2,
}

/// Frontier clusters listed as left at most: a map a robot wrote may leave
/// millions of one-cell pockets (2.8 million in a 25-million-cell mission),
/// and every `GetMission`, `ListMissions` and `WatchMission` carries them.
pub const MOST_LEFTOVERS: usize = 1_000;

/// The frontier left at completion: the largest clusters, and how many
/// more there were.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Leftovers {
    /// At most [`MOST_LEFTOVERS`] clusters, the largest first.
    pub listed: Vec<Leftover>,
    /// Clusters left beyond those listed.
    pub unlisted_clusters: u64,
    /// Their frontier cells.
    pub unlisted_cells: u64,
}

impl Leftovers {
    /// The largest [`MOST_LEFTOVERS`] of `all`, largest first (equal ones
    /// in their order in `all`), and a tally of the rest.
    pub fn keep_largest(mut all: Vec<Leftover>) -> Self {
        all.sort_by_key(|l| std::cmp::Reverse(l.cells));
        let rest = all.split_off(all.len().min(MOST_LEFTOVERS));
        Self {
            listed: all,
            unlisted_clusters: rest.len() as u64,
            unlisted_cells: rest.iter().map(|l| l.cells as u64).sum(),
        }
    }

    /// Whether nothing was left.
    pub fn is_empty(&self) -> bool {
        self.listed.is_empty() && self.unlisted_clusters == 0
    }
}

/// A region where no target is assigned.
#[derive(Debug, Clone, PartialEq)]
pub struct Region {
    /// Its identity.
    pub id: u64,
    /// Its mission.
    pub mission_id: MissionId,
    /// Lower-left corner, world frame.
    pub min: Point2,
    /// Upper-right corner, world frame.
    pub max: Point2,
    /// Who forbade it.
    pub actor: String,
    /// Why.
    pub reason: String,
    /// When.
    pub created_at: Timestamp,
}

impl Region {
    /// Whether a point lies inside (edges included).
    pub fn contains(&self, p: &Point2) -> bool {
        p.x >= self.min.x && p.x <= self.max.x && p.y >= self.min.y && p.y <= self.max.y
    }
}

/// A target a robot must not be sent to until the map around it changes.
#[derive(Debug, Clone, PartialEq)]
pub struct BlacklistEntry {
    /// The robot.
    pub robot_id: RobotId,
    /// The target cell.
    pub cell: exploration::grid::Cell,
    /// Why ("reported unreachable: ...", "no progress for 30 s").
    pub cause: String,
    /// When.
    pub created_at: Timestamp,
}

/// Who asks for an operator action, and why.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub struct OperatorNote {
    /// The operator's name ("operator" when none was given).
    pub actor: String,
    /// The reason given.
    pub reason: String,
}

/// What an operator asks of a robot (Simmons et al. 2000, §4.2).
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Override {
    /// Go to a point.
    Goto(Point2),
    /// Explore a region, nearest frontier first: (min, max) corners.
    ExploreRegion(Point2, Point2),
    /// Stay.
    Hold,
    /// Go to the start pose or the rendezvous.
    Home,
    /// Explore the frontier at a point.
    PinFrontier(Point2),
    /// End the robot's task, whatever it is.
    Release,
    /// End the robot's override.
    Cancel,
}

/// What a robot reports it is doing.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum RobotState {
    /// Waiting.
    Idle,
    /// Travelling to its target.
    Moving,
    /// Reached its target.
    Arrived,
    /// Cannot carry out its task.
    Failed,
}

impl RobotState {
    /// The name stored and logged.
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Idle => "idle",
            Self::Moving => "moving",
            Self::Arrived => "arrived",
            Self::Failed => "failed",
        }
    }

    /// Parses a stored name.
    pub fn parse(s: &str) -> Option<Self> {
        match s {
            "idle" => Some(Self::Idle),
            "moving" => Some(Self::Moving),
            "arrived" => Some(Self::Arrived),
            "failed" => Some(Self::Failed),
            _ => None,
        }
    }
}

/// What a robot registers with.
#[derive(Debug, Clone, PartialEq)]
pub struct RobotSpec {
    /// Unique within the mission.
    pub name: String,
    /// What it can do.
    pub capabilities: Capabilities,
    /// Where it is.
    pub pose: Pose,
}

/// A robot as stored.
#[derive(Debug, Clone, PartialEq)]
pub struct RobotRecord {
    /// Its identity.
    pub id: RobotId,
    /// Its mission.
    pub mission_id: MissionId,
    /// Its name.
    pub name: String,
    /// What it can do.
    pub capabilities: Capabilities,
    /// What it last reported doing.
    pub state: RobotState,
    /// Where it last was.
    pub pose: Pose,
    /// Highest applied map sequence number; 0 before the first update.
    pub last_map_seq: u64,
    /// Distance travelled, summed over reported poses, metres.
    pub distance_m: f64,
    /// Bumped whenever its assignment changes.
    pub assignment_version: u64,
    /// `distance_m` at the latest replanning (state of the distance trigger
    /// of Burgard et al. 2005, §II-C).
    pub assigned_distance_m: f64,
    /// The task it works on.
    pub current_task: Option<TaskId>,
    /// When it was last heard from.
    pub last_seen: Timestamp,
    /// Its lease ran out; it is out of the pool until it reports again.
    pub lost: bool,
    /// Where it registered.
    pub home: Point2,
}

impl RobotRecord {
    /// How messages and events name it: `robot 3 (scout-a)`, the id for
    /// scripts and the name operators gave it.
    pub fn label(&self) -> String {
        format!("robot {} ({})", self.id, self.name)
    }
}

/// A map update as the executive applies it.
#[derive(Debug, Clone, PartialEq)]
pub struct MapUpdate {
    /// Per-robot sequence number.
    pub seq: u64,
    /// The robot's pose.
    pub pose: Pose,
    /// Validated patches (not yet checked against the mission's grid).
    pub patches: Vec<Patch>,
    /// The robots it can communicate with, when it said.
    pub peers: Option<Vec<RobotId>>,
}

/// A robot's report.
#[derive(Debug, Clone, PartialEq)]
pub struct Heartbeat {
    /// Where it is.
    pub pose: Pose,
    /// What it does.
    pub state: RobotState,
    /// The task the state refers to.
    pub task_id: Option<TaskId>,
    /// Why it failed, if it did.
    pub reason: String,
    /// The robots it can communicate with, when it said.
    pub peers: Option<Vec<RobotId>>,
}

/// One bid of a robot (Simmons et al. 2000, §4.1).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Bid {
    /// Candidate target.
    pub target: Point2,
    /// Path cost to it.
    pub path_cost: f64,
    /// Expected information gain.
    pub information_gain: f64,
    /// Bounding rectangle of the gain region: (min, max) corners.
    pub gain_region: (Point2, Point2),
}

/// The lifecycle of a task.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum TaskState {
    /// Chosen, not yet acknowledged.
    Assigned,
    /// The robot is on its way.
    Active,
    /// The robot arrived.
    Reached,
    /// Replaced by a replanning.
    Preempted,
    /// Replaced by an operator's override.
    Overridden,
    /// The robot could not carry it out.
    Failed,
    /// Taken from the robot.
    Released,
    /// Ended with the mission.
    Cancelled,
}

impl TaskState {
    /// The name stored and logged.
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Assigned => "assigned",
            Self::Active => "active",
            Self::Reached => "reached",
            Self::Preempted => "preempted",
            Self::Overridden => "overridden",
            Self::Failed => "failed",
            Self::Released => "released",
            Self::Cancelled => "cancelled",
        }
    }

    /// Parses a stored name.
    pub fn parse(s: &str) -> Option<Self> {
        Some(match s {
            "assigned" => Self::Assigned,
            "active" => Self::Active,
            "reached" => Self::Reached,
            "preempted" => Self::Preempted,
            "overridden" => Self::Overridden,
            "failed" => Self::Failed,
            "released" => Self::Released,
            "cancelled" => Self::Cancelled,
            _ => return None,
        })
    }

    /// Whether the task has ended.
    pub fn is_terminal(self) -> bool {
        !matches!(self, Self::Assigned | Self::Active)
    }
}

/// What a task asks of its robot.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum TaskKind {
    /// A frontier the policy chose.
    Explore,
    /// A point an operator chose, or the next frontier of an operator's region.
    Goto,
    /// Stay.
    Hold,
    /// Go home.
    Home,
    /// A frontier an operator pinned to the robot.
    Pin,
}

impl TaskKind {
    /// The name stored and shown.
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Explore => "explore",
            Self::Goto => "goto",
            Self::Hold => "hold",
            Self::Home => "home",
            Self::Pin => "pin",
        }
    }

    /// Parses a stored name.
    pub fn parse(s: &str) -> Option<Self> {
        Some(match s {
            "explore" => Self::Explore,
            "goto" => Self::Goto,
            "hold" => Self::Hold,
            "home" => Self::Home,
            "pin" => Self::Pin,
            _ => return None,
        })
    }
}

/// Who changed a task's state.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Actor {
    /// A replanning.
    Policy,
    /// The robot's own report.
    Robot,
    /// An operator.
    Operator,
    /// A lease that ran out.
    Lease,
    /// The executive itself (mission end).
    Executive,
}

impl Actor {
    /// The name stored and logged.
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Policy => "policy",
            Self::Robot => "robot",
            Self::Operator => "operator",
            Self::Lease => "lease",
            Self::Executive => "executive",
        }
    }

    /// Parses a stored name.
    pub fn parse(s: &str) -> Option<Self> {
        Some(match s {
            "policy" => Self::Policy,
            "robot" => Self::Robot,
            "operator" => Self::Operator,
            "lease" => Self::Lease,
            "executive" => Self::Executive,
            _ => return None,
        })
    }
}

/// One state change of a task.
#[derive(Debug, Clone, PartialEq)]
pub struct Transition {
    /// The state before; `None` when the task was created.
    pub from: Option<TaskState>,
    /// The state after.
    pub to: TaskState,
    /// When.
    pub at: Timestamp,
    /// Why, in a few words.
    pub cause: String,
    /// Who.
    pub actor: Actor,
    /// The operator's name, for operator transitions; empty otherwise.
    pub by: String,
}

/// A task as stored.
#[derive(Debug, Clone, PartialEq)]
pub struct TaskRecord {
    /// Its identity.
    pub id: TaskId,
    /// Its mission.
    pub mission_id: MissionId,
    /// The robot it was given to.
    pub robot_id: RobotId,
    /// What it asks.
    pub kind: TaskKind,
    /// Where to go.
    pub target: Point2,
    /// Where it is in its life.
    pub state: TaskState,
    /// The policy that chose it.
    pub policy: String,
    /// The policy's figure of merit.
    pub utility: f64,
    /// The policy's path cost.
    pub path_cost: f64,
    /// The information-gain region expected at the target, if estimated;
    /// the region to explore, for an operator's region.
    pub gain_region: Option<CellRect>,
    /// "policy", "executive", or the operator's name.
    pub created_by: String,
    /// Why it was created, when someone said.
    pub note: String,
    /// When it was created.
    pub created_at: Timestamp,
    /// When it last changed.
    pub updated_at: Timestamp,
    /// Every change, oldest first (may be empty when not loaded).
    pub transitions: Vec<Transition>,
}

/// `TaskRecord::created_by` of the tasks the policy chose.
pub const BY_POLICY: &str = "policy";
/// `TaskRecord::created_by` of the tasks the executive set itself (going home at the end).
pub const BY_EXECUTIVE: &str = "executive";

impl TaskRecord {
    /// Whether an operator set it: its robot is out of the policy's pool
    /// until it ends.
    pub fn is_override(&self) -> bool {
        self.created_by != BY_POLICY && self.created_by != BY_EXECUTIVE
    }
}

/// Where a robot should go now.
#[derive(Debug, Clone, PartialEq)]
pub struct Assignment {
    /// The robot.
    pub robot_id: RobotId,
    /// Bumped at every change.
    pub version: u64,
    /// The task, if any.
    pub task: Option<AssignedTask>,
    /// The mission's policy.
    pub policy: &'static str,
    /// The mission's state.
    pub mission_state: MissionState,
    /// The mission is paused: hold.
    pub paused: bool,
}

/// The task part of an [`Assignment`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AssignedTask {
    /// The task.
    pub id: TaskId,
    /// What to do.
    pub kind: TaskKind,
    /// Where to go.
    pub target: Point2,
    /// The policy's figure of merit.
    pub utility: f64,
    /// The policy's path cost.
    pub path_cost: f64,
    /// The information-gain region expected at the target, in world coordinates.
    pub gain_region: Option<(Point2, Point2)>,
}

/// Something that happened to a mission as a whole.
#[derive(Debug, Clone, PartialEq)]
pub struct MissionEvent {
    /// Its identity (0 before it is stored).
    pub id: u64,
    /// The mission.
    pub mission_id: MissionId,
    /// When.
    pub at: Timestamp,
    /// What ("policy_changed", ...).
    pub kind: String,
    /// Details.
    pub detail: String,
    /// Who.
    pub actor: String,
}

/// A mission's latest segmentation, as kept.
#[derive(Debug, Clone, PartialEq)]
pub struct StoredSegmentation {
    /// When it was computed.
    pub computed_at: Timestamp,
    /// The segmentation.
    pub segmentation: exploration::segment::Segmentation,
}

/// Rooms and corridors given with a mission (Wurm et al. 2008, §VI): a
/// label per cell of its map, row-major, 0 for none.
pub type Rooms = std::sync::Arc<[u32]>;

/// Policy parameters as given by a client, before validation.
pub type ParamOverrides = BTreeMap<String, f64>;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_largest_leftovers_are_listed_and_the_rest_counted() {
        let left =
            |cells: usize, x: f64| Leftover { reason: LeftoverReason::TooSmall, cells, position: Point2::new(x, 0.0) };
        let few = Leftovers::keep_largest(vec![left(1, 0.0), left(5, 1.0), left(1, 2.0)]);
        assert_eq!(few.listed, vec![left(5, 1.0), left(1, 0.0), left(1, 2.0)]);
        assert_eq!((few.unlisted_clusters, few.unlisted_cells), (0, 0));
        // A pocket a cell: the 1 000 largest listed, the others counted.
        let mut pockets: Vec<Leftover> = (0..2_500).map(|i| left(1, f64::from(i))).collect();
        pockets[1_700] = left(30, -1.0);
        let many = Leftovers::keep_largest(pockets);
        assert_eq!(many.listed.len(), MOST_LEFTOVERS);
        assert_eq!(many.listed[0], left(30, -1.0));
        assert_eq!(many.listed[1], left(1, 0.0));
        assert_eq!((many.unlisted_clusters, many.unlisted_cells), (1_500, 1_500));
        assert!(!many.is_empty() && Leftovers::default().is_empty());
    }
}
