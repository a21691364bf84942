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

use std::collections::{HashSet, VecDeque};
use std::time::Duration;

use tokio::sync::watch;
use tokio_util::sync::CancellationToken;
use tonic::transport::Channel;
use tonic::{Code, Status};

use exploration::cost::{TraversalMap, cost_map, shortest_path};
use exploration::frontier::FrontierMap;
use exploration::grid::{Cell, CellClass, CellRect, GridFrame, OccupancyGrid};
use exploration::policy::{Capabilities, compute_bids};
use exploration::visibility::RangeSensor;
use exploration_proto::Bearer;
use exploration_proto::v1 as pb;
use exploration_proto::v1::fleet_client::FleetClient;

use crate::world::World;

/// Probability a robot reports for a cell its sensor saw empty.
const P_FREE: f32 = 0.05;
/// Probability a robot reports for a cell that stopped a beam.
const P_OCCUPIED: f32 = 0.95;
/// How a robot's map stores a cell seen free (percent).
const KNOWN_FREE: u8 = 5;
/// How a robot's map stores a cell seen occupied (percent).
const KNOWN_OCCUPIED: u8 = 95;
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
    #[error("{what}: {status}")]
    Rpc {
        /// Which request.
        what: &'static str,
        /// The executive's answer.
        status: Status,
    },
    /// The executive stayed unreachable past the retry budget.
    #[error("{what}: the executive stayed unreachable for {budget:?}: {status}")]
    Unreachable {
        /// Which request.
        what: &'static str,
        /// How long the robot kept trying.
        budget: Duration,
        /// The last error.
        status: Status,
    },
}

/// What the whole team knows: the union of the robots' maps. Robots plan
/// their paths on it (the shared map of Burgard et al. 2005, §III), and the
/// fleet measures coverage with it.
#[derive(Debug, Clone)]
pub struct TeamMap {
    /// Known cells: free or occupied.
    pub grid: OccupancyGrid,
    /// Reachable free cells known.
    pub known_reachable: usize,
    /// Per cell: how many robots sensed it (for the overlap figure).
    pub sensed_by: Vec<u8>,
}

impl TeamMap {
    /// Nothing known yet.
    pub fn new(frame: GridFrame) -> Self {
        Self { grid: OccupancyGrid::unknown(frame), known_reachable: 0, sensed_by: vec![0; frame.len()] }
    }
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
type Client = FleetClient<tonic::service::interceptor::InterceptedService<Channel, Bearer>>;

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

/// How a robot bids (Simmons et al. 2000, §4.1), when its mission's policy wants bids.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Bidding {
    /// Bid every this many steps.
    pub every: u64,
    /// Bid frontier cells at least this far apart, metres.
    pub spacing_m: f64,
}

fn retryable(status: &Status) -> bool {
    matches!(
        status.code(),
        Code::Unavailable | Code::Unknown | Code::Cancelled | Code::DeadlineExceeded | Code::ResourceExhausted
    )
}

/// How long the executive asked to wait before retrying a call it shed
/// (`grpc-retry-pushback-ms`), if it did.
fn pushback(status: &Status) -> Option<Duration> {
    let ms = status.metadata().get("grpc-retry-pushback-ms")?.to_str().ok()?.parse::<u64>().ok()?;
    Some(Duration::from_millis(ms.min(10_000)))
}

impl SimRobot {
    /// Connects to the executive and registers (or resumes) the robot,
    /// with the operator's token when the executive wants one; then talks
    /// with the token its registration returned.
    #[allow(clippy::too_many_arguments)]
    pub async fn connect(
        endpoint: &str,
        tls: Option<&exploration_proto::client::ClientTls>,
        operator_token: Option<&str>,
        mission_id: u64,
        name: String,
        start: Cell,
        world: &World,
        model: RobotModel,
        bidding: Option<Bidding>,
        limited: bool,
        team_size: usize,
        retry_budget: Duration,
        stop: CancellationToken,
    ) -> Result<Self, RobotError> {
        let channel = exploration_proto::client::endpoint(endpoint, tls)
            .map_err(|e| RobotError::Rpc { what: "connect", status: Status::invalid_argument(e.to_string()) })?
            .tcp_nodelay(true)
            .connect_lazy();
        let bearer = |token: Option<&str>| {
            Bearer::new(token).map_err(|e| RobotError::Rpc {
                what: "connect",
                status: Status::invalid_argument(format!("the token is not valid metadata: {e}")),
            })
        };
        let registrar = FleetClient::with_interceptor(channel.clone(), bearer(operator_token)?);
        let frame = world.frame;
        let point = frame.world_from_cell(start);
        let request = pb::RegisterRobotRequest {
            mission_id,
            name: name.clone(),
            capabilities: Some(pb::RobotCapabilities {
                sensor_range_m: model.sensor_range_m,
                field_of_view_rad: model.field_of_view_rad,
                speed_mps: model.speed_mps,
                footprint_radius_m: model.footprint_radius_m,
            }),
            pose: Some(pb::Pose { x: point.x, y: point.y, theta: 0.0 }),
        };
        let response = retry("RegisterRobot", retry_budget, || {
            let mut client = registrar.clone();
            let request = request.clone();
            async move { client.register_robot(request).await }
        })
        .await?;
        let mut client = FleetClient::with_interceptor(channel, bearer(Some(&response.token))?)
            .max_decoding_message_size(exploration_proto::MAX_MESSAGE_BYTES);
        let robot = response.robot.ok_or_else(|| RobotError::Rpc {
            what: "RegisterRobot",
            status: Status::internal("the response holds no robot"),
        })?;
        let (tx, rx) = watch::channel(None);
        tokio::spawn(watch_assignments(client.clone(), robot.id, tx, stop));
        client = client.max_encoding_message_size(64 << 20);
        Ok(Self {
            name,
            id: robot.id,
            client,
            cell: start,
            heading: 0.0,
            sensor: RangeSensor {
                range_cells: model.sensor_range_m / frame.resolution,
                field_of_view: model.field_of_view_rad,
            },
            own: OccupancyGrid::unknown(frame),
            known_reachable: 0,
            log: Vec::new(),
            sent: vec![0; team_size],
            seen: vec![false; frame.len()],
            dirty: None,
            limited,
            stride: 0.0,
            peers: Vec::new(),
            seq: robot.last_map_seq,
            task: None,
            acknowledged_task: None,
            path: VecDeque::new(),
            distance_m: 0.0,
            trajectory: vec![start],
            retry_budget,
            stream: rx,
            stream_lags: 0,
            acknowledged_updates: 0,
            capabilities: Capabilities {
                sensor_range_m: model.sensor_range_m,
                field_of_view_rad: model.field_of_view_rad,
                speed_mps: model.speed_mps,
                footprint_radius_m: model.footprint_radius_m,
            },
            bidding,
            steps_since_bid: 0,
            paused: false,
            faults: Faults::default(),
            steps: 0,
            waited: 0,
        })
    }

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

    /// One time step: move (unless `blocked`: interference), sense, report,
    /// adopt the assignment.
    /// One step: move (into free cells no other robot stands on; `occupied`
    /// holds the team's cells and is kept up to date), sense, report.
    pub async fn step(
        &mut self,
        world: &World,
        team: &mut TeamMap,
        blocked: bool,
        occupied: &mut HashSet<Cell>,
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
            if occupied.contains(&next) {
                // Another robot stands there: wait, and after a while go around it.
                self.waited += 1;
                if self.waited >= WAIT_BEFORE_DETOUR {
                    self.detour(world, team, occupied);
                }
                break;
            }
            self.path.pop_front();
            self.waited = 0;
            occupied.remove(&self.cell);
            occupied.insert(next);
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

    /// A path to the task's target around the cells other robots stand on,
    /// when there is one; otherwise the robot keeps waiting on its path.
    fn detour(&mut self, world: &World, team: &TeamMap, occupied: &HashSet<Cell>) {
        let Some(task) = self.task else { return };
        let map = if self.limited { &self.own } else { &team.grid };
        let free = |c: Cell| !occupied.contains(&c) || c == self.cell;
        let path = if self.capabilities.footprint_radius_m > 0.0 {
            let traversal = TraversalMap::free_space(map, self.capabilities.footprint_radius_m);
            shortest_path(&world.frame, self.cell, task.target, |c| traversal.passable(c) && free(c))
        } else {
            shortest_path(&world.frame, self.cell, task.target, |c| map.class(c) == CellClass::Free && free(c))
        };
        if let Some(path) = path {
            self.path = path.into_iter().skip(1).collect();
            self.waited = 0;
        }
    }

    /// Tells the executive at once when the robots in range change, with
    /// what they passed on, so that it plans this robot's sub-team on the
    /// map the sub-team holds now rather than the one of the last step.
    pub async fn hear_peers(&mut self, peers: Vec<u64>, world: &World, team: &TeamMap) -> Result<(), RobotError> {
        if peers == self.peers || self.is_dead() {
            self.peers = peers;
            return Ok(());
        }
        self.peers = peers;
        let patch = self.patch();
        let assignment = self.send_update(world, patch).await?;
        self.adopt(assignment, world, team).await
    }

    /// Computes bids on the team's map (§4.1) and sends them.
    async fn submit_bids(
        &mut self,
        world: &World,
        team: &TeamMap,
        spacing_m: f64,
    ) -> Result<pb::Assignment, RobotError> {
        let map = if self.limited { &self.own } else { &team.grid };
        let frontier = FrontierMap::detect(map).cells();
        let traversal = TraversalMap::free_space(map, self.capabilities.footprint_radius_m);
        let costs = cost_map(&traversal, &[self.cell]);
        let bids = compute_bids(map, &frontier, &costs, &self.capabilities, spacing_m);
        let frame = world.frame;
        let corner = |x: i32, y: i32| pb::Point {
            x: frame.origin.x + f64::from(x) * frame.resolution,
            y: frame.origin.y + f64::from(y) * frame.resolution,
        };
        let request = pb::SubmitBidsRequest {
            robot_id: self.id,
            bids: bids
                .iter()
                .map(|b| {
                    let target = frame.world_from_cell(b.target);
                    let (low, high) = (
                        corner(b.gain_region.x, b.gain_region.y),
                        corner(b.gain_region.x_end(), b.gain_region.y_end()),
                    );
                    pb::Bid {
                        target: Some(pb::Point { x: target.x, y: target.y }),
                        path_cost: b.path_cost_m,
                        information_gain: b.information_gain,
                        gain_region: Some(pb::Rect { min_x: low.x, min_y: low.y, max_x: high.x, max_y: high.y }),
                    }
                })
                .collect(),
        };
        let response = retry("SubmitBids", self.retry_budget, || {
            let mut client = self.client.clone();
            let request = request.clone();
            async move { client.submit_bids(request).await }
        })
        .await?;
        response.assignment.ok_or_else(|| RobotError::Rpc {
            what: "SubmitBids",
            status: Status::internal("the response holds no assignment"),
        })
    }

    /// Senses from the current cell into its map, its log and the team's map.
    fn sense(&mut self, world: &World, team: &mut TeamMap) {
        let frame = world.frame;
        let own = &mut self.own;
        let (log, dirty, known, seen) = (&mut self.log, &mut self.dirty, &mut self.known_reachable, &mut self.seen);
        self.sensor.scan(
            self.cell,
            self.heading,
            |c| world.is_blocked(c),
            |cell, hit| {
                if !frame.contains(cell) {
                    return;
                }
                let i = frame.index(cell);
                // Overlap counts robots that swept a cell, whatever they knew of it.
                if !seen[i] {
                    seen[i] = true;
                    team.sensed_by[i] = team.sensed_by[i].saturating_add(1);
                }
                if own.class(cell) != CellClass::Unknown {
                    return;
                }
                own.set(cell, if hit { KNOWN_OCCUPIED } else { KNOWN_FREE });
                log.push((i as u32, hit));
                *dirty = Some(dirty.map_or(CellRect::new(cell.x, cell.y, 1, 1), |r| r.including(cell)));
                if world.reachable[i] {
                    *known += 1;
                }
                if team.grid.class(cell) == CellClass::Unknown {
                    team.grid.set(cell, if hit { KNOWN_OCCUPIED } else { KNOWN_FREE });
                    if world.reachable[i] {
                        team.known_reachable += 1;
                    }
                }
            },
        );
    }

    /// Passes the measurements `to` was not sent yet, and marks them sent
    /// (Burgard et al. 2005, §III: a per-peer log). Forwarded measurements
    /// count too, so that robots that meet end up with their clusters' joint
    /// map, the map the executive plans their sub-team on; `to` integrates a
    /// measurement only once, into cells it does not know yet.
    pub fn share_with(&mut self, to: &mut SimRobot, to_index: usize, world: &World) {
        let frame = world.frame;
        let start = self.sent[to_index];
        for &(i, occupied) in &self.log[start..] {
            let cell = frame.cell(i as usize);
            if to.own.class(cell) == CellClass::Unknown {
                to.own.set(cell, if occupied { KNOWN_OCCUPIED } else { KNOWN_FREE });
                to.log.push((i, occupied));
                to.dirty = Some(to.dirty.map_or(CellRect::new(cell.x, cell.y, 1, 1), |r| r.including(cell)));
                if world.reachable[i as usize] {
                    to.known_reachable += 1;
                }
            }
        }
        self.sent[to_index] = self.log.len();
    }

    /// The cells changed since the last update, as a patch of its map:
    /// only its own measurements with unlimited communication (the executive
    /// fuses the robots'), all it knows with limited communication.
    fn patch(&mut self) -> Option<pb::MapPatch> {
        let rect = self.dirty.take()?;
        let mut values = Vec::with_capacity(rect.area() as usize);
        let mut unknown = Vec::with_capacity(rect.area() as usize);
        for cell in rect.cells() {
            match self.own.value(cell) {
                KNOWN_FREE => {
                    values.push(P_FREE);
                    unknown.push(0);
                }
                KNOWN_OCCUPIED => {
                    values.push(P_OCCUPIED);
                    unknown.push(0);
                }
                _ => {
                    values.push(0.5);
                    unknown.push(1);
                }
            }
        }
        let any_unknown = unknown.iter().any(|&u| u != 0);
        Some(pb::MapPatch {
            x: rect.x as u32,
            y: rect.y as u32,
            width: rect.width,
            height: rect.height,
            encoding: pb::CellEncoding::Probability as i32,
            values,
            unknown: if any_unknown { unknown } else { Vec::new() },
        })
    }

    fn pose(&self, world: &World) -> pb::Pose {
        let p = world.frame.world_from_cell(self.cell);
        pb::Pose { x: p.x, y: p.y, theta: self.heading }
    }

    /// Sends a map update under the next sequence number; an update whose
    /// acknowledgement was lost is resent under the same number and
    /// recognised as applied.
    async fn send_update(&mut self, world: &World, patch: Option<pb::MapPatch>) -> Result<pb::Assignment, RobotError> {
        self.seq += 1;
        let request = pb::UpdateMapRequest {
            robot_id: self.id,
            seq: self.seq,
            pose: Some(self.pose(world)),
            patches: patch.into_iter().collect(),
            peers: self.peers.clone(),
            peers_reported: self.limited,
        };
        let client = self.client.clone();
        let result = retry("UpdateMap", self.retry_budget, || {
            let mut client = client.clone();
            let request = request.clone();
            async move { client.update_map(request).await }
        })
        .await;
        match result {
            Ok(response) => {
                self.acknowledged_updates += 1;
                response.assignment.ok_or_else(|| RobotError::Rpc {
                    what: "UpdateMap",
                    status: Status::internal("the response holds no assignment"),
                })
            }
            // Applied before the executive went down: fetch the assignment.
            Err(RobotError::Rpc { status, .. }) if status.code() == Code::AlreadyExists => {
                self.acknowledged_updates += 1;
                self.get_assignment().await
            }
            Err(e) => Err(e),
        }
    }

    async fn get_assignment(&self) -> Result<pb::Assignment, RobotError> {
        let request = pb::GetAssignmentRequest { robot_id: self.id };
        retry("GetAssignment", self.retry_budget, || {
            let mut client = self.client.clone();
            async move { client.get_assignment(request).await }
        })
        .await
    }

    async fn heartbeat(
        &mut self,
        world: &World,
        state: pb::RobotState,
        task_id: u64,
        reason: &str,
    ) -> Result<pb::Assignment, RobotError> {
        let request = pb::HeartbeatRequest {
            robot_id: self.id,
            pose: Some(self.pose(world)),
            state: state as i32,
            task_id,
            reason: reason.to_owned(),
            peers: self.peers.clone(),
            peers_reported: self.limited,
        };
        let response = retry("Heartbeat", self.retry_budget, || {
            let mut client = self.client.clone();
            let request = request.clone();
            async move { client.heartbeat(request).await }
        })
        .await?;
        response.assignment.ok_or_else(|| RobotError::Rpc {
            what: "Heartbeat",
            status: Status::internal("the response holds no assignment"),
        })
    }

    /// Takes up an assignment: plans a path to a new target, acknowledges it,
    /// or reports failure when the target cannot be reached.
    async fn adopt(&mut self, mut assignment: pb::Assignment, world: &World, team: &TeamMap) -> Result<(), RobotError> {
        // Up to a few rounds: a failure report brings a new assignment.
        for _ in 0..4 {
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

    /// The stream must deliver what a response announced; count when it lags.
    async fn check_stream(&mut self, version: u64) {
        let caught_up = tokio::time::timeout(
            Duration::from_secs(2),
            self.stream.wait_for(|a| a.as_ref().is_some_and(|a| a.version >= version)),
        )
        .await;
        if !matches!(caught_up, Ok(Ok(_))) {
            self.stream_lags += 1;
        }
    }
}

/// Follows a robot's assignment stream, reconnecting through outages, and
/// keeps the newest assignment in `tx`.
async fn watch_assignments(
    mut client: Client,
    robot_id: u64,
    tx: watch::Sender<Option<pb::Assignment>>,
    stop: CancellationToken,
) {
    let mut backoff = Duration::from_millis(50);
    loop {
        let stream = tokio::select! {
            () = stop.cancelled() => return,
            r = client.watch_assignment(pb::WatchAssignmentRequest { robot_id }) => r,
        };
        if let Ok(response) = stream {
            backoff = Duration::from_millis(50);
            let mut stream = response.into_inner();
            loop {
                let message = tokio::select! {
                    () = stop.cancelled() => return,
                    m = stream.message() => m,
                };
                match message {
                    Ok(Some(a)) => {
                        tx.send_if_modified(|current| {
                            let newer = current.as_ref().is_none_or(|c| a.version > c.version);
                            if newer {
                                *current = Some(a);
                            }
                            newer
                        });
                    }
                    _ => break,
                }
            }
        }
        tokio::select! {
            () = stop.cancelled() => return,
            () = tokio::time::sleep(backoff) => {}
        }
        backoff = (backoff * 2).min(Duration::from_secs(1));
    }
}

/// Calls `call` until it succeeds, fails for good, or the executive stays
/// unreachable for `budget`.
pub(crate) async fn retry<T, F, Fut>(what: &'static str, budget: Duration, mut call: F) -> Result<T, RobotError>
where
    F: FnMut() -> Fut,
    Fut: std::future::Future<Output = Result<tonic::Response<T>, Status>>,
{
    let started = tokio::time::Instant::now();
    let mut backoff = Duration::from_millis(20);
    loop {
        match call().await {
            Ok(response) => return Ok(response.into_inner()),
            Err(status) if retryable(&status) => {
                if started.elapsed() >= budget {
                    return Err(RobotError::Unreachable { what, budget, status });
                }
                tracing::debug!(what, %status, "executive unreachable or busy; retrying");
                tokio::time::sleep(pushback(&status).unwrap_or(backoff).max(backoff)).await;
                backoff = (backoff * 2).min(Duration::from_millis(500));
            }
            Err(status) => return Err(RobotError::Rpc { what, status }),
        }
    }
}
