//! The robot's link: its own gRPC client of the executive, its assignment
//! stream, and retries through outages and shedding (honouring the
//! executive's `grpc-retry-pushback-ms`).

use std::collections::VecDeque;
use std::time::Duration;

use tokio::sync::watch;
use tokio_util::sync::CancellationToken;
use tonic::{Code, Status};

use exploration::cost::{TraversalMap, cost_map};
use exploration::frontier::FrontierMap;
use exploration::grid::{Cell, OccupancyGrid};
use exploration::policy::{Capabilities, compute_bids};
use exploration::visibility::RangeSensor;
use exploration_proto::Bearer;
use exploration_proto::client::retry_pushback;
use exploration_proto::v1 as pb;
use exploration_proto::v1::fleet_client::FleetClient;

use super::{Bidding, Client, Faults, RobotError, RobotModel, SimRobot, TeamMap};
use crate::world::World;

/// Whether a refused call may succeed if made again: the executive was
/// unreachable or busy. RESOURCE_EXHAUSTED is that only with a retry hint
/// (load shed); without one it is a limit (a mission's robots, the
/// executive's cells, a full disk) that asking again for two minutes would
/// not lift, as the Python client reads it too.
fn retryable(status: &Status) -> bool {
    match status.code() {
        Code::Unavailable | Code::Unknown | Code::Cancelled | Code::DeadlineExceeded => true,
        Code::ResourceExhausted => retry_pushback(status).is_some(),
        _ => false,
    }
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
        let channel = exploration_proto::replicas::Replicas::from_list(endpoint, tls)
            .map_err(|e| RobotError::Rpc { what: "connect", status: Status::invalid_argument(e.to_string()) })?;
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
            target_switches: 0,
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
    pub(super) async fn submit_bids(
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

    pub(super) fn pose(&self, world: &World) -> pb::Pose {
        let p = world.frame.world_from_cell(self.cell);
        pb::Pose { x: p.x, y: p.y, theta: self.heading }
    }

    /// Sends a map update under the next sequence number; an update whose
    /// acknowledgement was lost is resent under the same number and
    /// recognised as applied.
    pub(super) async fn send_update(
        &mut self,
        world: &World,
        patch: Option<pb::MapPatch>,
    ) -> Result<pb::Assignment, RobotError> {
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

    pub(super) async fn get_assignment(&self) -> Result<pb::Assignment, RobotError> {
        let request = pb::GetAssignmentRequest { robot_id: self.id };
        retry("GetAssignment", self.retry_budget, || {
            let mut client = self.client.clone();
            async move { client.get_assignment(request).await }
        })
        .await
    }

    pub(super) async fn heartbeat(
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

    /// The stream must deliver what a response announced; count when it lags.
    pub(super) async fn check_stream(&mut self, version: u64) {
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
                tokio::time::sleep(retry_pushback(&status).unwrap_or(backoff).max(backoff)).await;
                backoff = (backoff * 2).min(Duration::from_millis(500));
            }
            Err(status) => return Err(RobotError::Rpc { what, status }),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn only_shed_calls_and_outages_are_tried_again() {
        let mut shed = Status::resource_exhausted("busy");
        shed.metadata_mut().insert(exploration_proto::client::RETRY_PUSHBACK_METADATA, 100u64.into());
        assert!(retryable(&shed));
        assert!(retryable(&Status::unavailable("restarting")));
        let limit = Status::resource_exhausted("mission 1 already has 1000 robots, the limit");
        assert!(!retryable(&limit), "a limit without a hint is final");
        assert!(!retryable(&Status::invalid_argument("pose.x is NaN")));
    }
}
