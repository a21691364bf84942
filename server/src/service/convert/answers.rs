//! What the executive holds, as the answers' messages: missions, robots,
//! tasks and their history, assignments, events, the segmentation, the
//! policy catalogue. Nothing here can fail: the executive's records are
//! valid by construction.

use exploration::grid::GridFrame;
use exploration::math::Point2;
use exploration::policy::{Capabilities, PolicyConfig, catalogue};
use exploration_proto::v1 as pb;

use crate::domain::{
    Actor, Assignment, Leftover, LeftoverReason, LifecycleSettings, MissionEvent, MissionState, Region, ReplanSettings,
    RobotState, StoredSegmentation, TaskKind, TaskRecord, TaskState, Timestamp, Transition,
};
use crate::executive::{MissionSummary, RobotSummary};

/// A grid frame in proto form.
pub fn frame_to_proto(f: &GridFrame) -> pb::MapFrame {
    pb::MapFrame {
        resolution: f.resolution,
        origin: Some(pb::Point { x: f.origin.x, y: f.origin.y }),
        width: f.width,
        height: f.height,
    }
}

/// A policy choice in proto form.
pub fn policy_to_proto(p: &PolicyConfig) -> pb::PolicySpec {
    pb::PolicySpec {
        name: p.name().to_owned(),
        params: p.params().iter().map(|(k, v)| ((*k).to_owned(), *v)).collect(),
    }
}

impl From<&ReplanSettings> for pb::ReplanSettings {
    fn from(s: &ReplanSettings) -> Self {
        Self { distance_m: s.distance_m, interval_s: s.interval.as_secs_f64(), frontier_change: s.frontier_change }
    }
}

impl From<&LifecycleSettings> for pb::LifecycleSettings {
    fn from(s: &LifecycleSettings) -> Self {
        Self {
            lease_s: s.lease.as_secs_f64(),
            stall_s: s.stall.as_secs_f64(),
            rendezvous: s.rendezvous.map(|p| pb::Point { x: p.x, y: p.y }),
        }
    }
}

fn task_kind(k: TaskKind) -> pb::TaskKind {
    match k {
        TaskKind::Explore => pb::TaskKind::Explore,
        TaskKind::Goto => pb::TaskKind::Goto,
        TaskKind::Hold => pb::TaskKind::Hold,
        TaskKind::Home => pb::TaskKind::Home,
        TaskKind::Pin => pb::TaskKind::Pin,
    }
}

/// A forbidden region in proto form.
pub fn region(r: &Region) -> pb::Region {
    pb::Region {
        id: r.id,
        mission_id: r.mission_id,
        area: Some(rect(r.min, r.max)),
        actor: r.actor.clone(),
        reason: r.reason.clone(),
        created_at: Some(timestamp(r.created_at)),
    }
}

fn leftover(l: &Leftover) -> pb::Leftover {
    pb::Leftover {
        reason: match l.reason {
            LeftoverReason::TooSmall => pb::LeftoverReason::TooSmall,
            LeftoverReason::TooNarrow => pb::LeftoverReason::TooNarrow,
            LeftoverReason::Disconnected => pb::LeftoverReason::Disconnected,
            LeftoverReason::Blacklisted => pb::LeftoverReason::Blacklisted,
            LeftoverReason::Forbidden => pb::LeftoverReason::Forbidden,
        } as i32,
        cells: l.cells as u64,
        position: Some(pb::Point { x: l.position.x, y: l.position.y }),
    }
}

fn timestamp(t: Timestamp) -> prost_types::Timestamp {
    let millis = t.millis();
    prost_types::Timestamp { seconds: millis.div_euclid(1000), nanos: (millis.rem_euclid(1000) * 1_000_000) as i32 }
}

fn mission_state(s: MissionState, paused: bool) -> pb::MissionState {
    match s {
        _ if paused => pb::MissionState::Paused,
        MissionState::Active => pb::MissionState::Active,
        MissionState::Completed => pb::MissionState::Completed,
    }
}

impl From<&MissionSummary> for pb::Mission {
    fn from(m: &MissionSummary) -> Self {
        let r = &m.record;
        Self {
            id: r.id,
            name: r.spec.name.clone(),
            frame: Some(frame_to_proto(&r.spec.frame)),
            policy: Some(policy_to_proto(&r.spec.policy)),
            replan: Some((&r.spec.replan).into()),
            state: mission_state(r.state, r.paused) as i32,
            created_at: Some(timestamp(r.created_at)),
            robots: m.robots as u32,
            known_cells: m.known_cells,
            frontier_cells: m.frontier_cells,
            replans: r.replans,
            map_updates: r.map_updates,
            scoped_by_communication: r.spec.scoped_by_communication,
            lockstep: r.spec.lockstep,
            lifecycle: Some((&r.spec.lifecycle).into()),
            forbidden_regions: m.forbidden.iter().map(region).collect(),
            leftovers: r.leftovers.iter().map(leftover).collect(),
            given_segmentation: m.given_segmentation,
        }
    }
}

/// The policy catalogue in proto form.
pub fn policies() -> pb::ListPoliciesResponse {
    pb::ListPoliciesResponse {
        policies: catalogue()
            .iter()
            .filter_map(|d| PolicyConfig::default_for(d.name).ok().map(|config| (d, config.build())))
            .map(|(d, policy)| pb::PolicyInfo {
                name: d.name.to_owned(),
                uses_bids: policy.uses_bids(),
                keeps_segmentation: policy.keeps_segmentation(),
                description: d.description.to_owned(),
                params: d
                    .params
                    .iter()
                    .map(|p| pb::ParameterInfo {
                        name: p.name.to_owned(),
                        description: p.description.to_owned(),
                        default_value: p.default,
                        min: p.min,
                        max: p.max,
                    })
                    .collect(),
            })
            .collect(),
    }
}

fn capabilities(c: &Capabilities) -> pb::RobotCapabilities {
    pb::RobotCapabilities {
        sensor_range_m: c.sensor_range_m,
        field_of_view_rad: c.field_of_view_rad,
        speed_mps: c.speed_mps,
        footprint_radius_m: c.footprint_radius_m,
    }
}

fn robot_state(s: RobotState) -> pb::RobotState {
    match s {
        RobotState::Idle => pb::RobotState::Idle,
        RobotState::Moving => pb::RobotState::Moving,
        RobotState::Arrived => pb::RobotState::Arrived,
        RobotState::Failed => pb::RobotState::Failed,
    }
}

impl From<&RobotSummary> for pb::Robot {
    fn from(s: &RobotSummary) -> Self {
        let r = &s.record;
        Self {
            id: r.id,
            mission_id: r.mission_id,
            name: r.name.clone(),
            capabilities: Some(capabilities(&r.capabilities)),
            state: robot_state(r.state) as i32,
            pose: Some(pb::Pose { x: r.pose.position.x, y: r.pose.position.y, theta: r.pose.heading }),
            task_id: r.current_task.unwrap_or(0),
            last_map_seq: r.last_map_seq,
            last_seen: Some(timestamp(r.last_seen)),
            distance_m: r.distance_m,
            target: s.target.map(|t| pb::Point { x: t.x, y: t.y }),
            lost: r.lost,
            task_kind: s.task_kind.map_or(pb::TaskKind::Unspecified, task_kind) as i32,
            home: Some(pb::Point { x: r.home.x, y: r.home.y }),
            blacklisted: s.blacklisted as u32,
        }
    }
}

impl From<&Assignment> for pb::Assignment {
    fn from(a: &Assignment) -> Self {
        Self {
            robot_id: a.robot_id,
            version: a.version,
            task_id: a.task.map_or(0, |t| t.id),
            target: a.task.map(|t| pb::Point { x: t.target.x, y: t.target.y }),
            policy: a.policy.to_owned(),
            utility: a.task.map_or(0.0, |t| t.utility),
            path_cost: a.task.map_or(0.0, |t| t.path_cost),
            mission_state: mission_state(a.mission_state, a.paused) as i32,
            gain_region: a.task.and_then(|t| t.gain_region).map(|(low, high)| rect(low, high)),
            kind: a.task.map_or(pb::TaskKind::Unspecified, |t| task_kind(t.kind)) as i32,
        }
    }
}

fn rect(low: Point2, high: Point2) -> pb::Rect {
    pb::Rect { min_x: low.x, min_y: low.y, max_x: high.x, max_y: high.y }
}

/// A mission event in proto form.
pub fn event(e: &MissionEvent) -> pb::MissionEvent {
    pb::MissionEvent {
        id: e.id,
        mission_id: e.mission_id,
        at: Some(timestamp(e.at)),
        kind: e.kind.clone(),
        detail: e.detail.clone(),
        actor: e.actor.clone(),
    }
}

/// A segmentation in proto form; `labels` only when asked for.
pub fn segmentation(
    mission_id: u64,
    frame: &GridFrame,
    stored: Option<&StoredSegmentation>,
    include_labels: bool,
) -> pb::Segmentation {
    let Some(stored) = stored else {
        return pb::Segmentation { mission_id, frame: Some(frame_to_proto(frame)), ..pb::Segmentation::default() };
    };
    let s = &stored.segmentation;
    let corner = |x: i32, y: i32| {
        Point2::new(frame.origin.x + f64::from(x) * frame.resolution, frame.origin.y + f64::from(y) * frame.resolution)
    };
    pb::Segmentation {
        mission_id,
        frame: Some(frame_to_proto(frame)),
        computed_at: Some(timestamp(stored.computed_at)),
        segments: s
            .segments
            .iter()
            .map(|seg| pb::SegmentInfo {
                id: seg.id,
                cells: seg.cells as u64,
                area_m2: seg.cells as f64 * frame.resolution * frame.resolution,
                bounds: Some(rect(corner(seg.bounds.x, seg.bounds.y), corner(seg.bounds.x_end(), seg.bounds.y_end()))),
                frontier_cells: seg.frontier.len() as u64,
            })
            .collect(),
        critical_points: s
            .critical_points
            .iter()
            .map(|p| {
                let at = frame.world_from_cell(p.cell);
                pb::CriticalPoint {
                    position: Some(pb::Point { x: at.x, y: at.y }),
                    clearance_m: p.clearance * frame.resolution,
                }
            })
            .collect(),
        labels: if include_labels { s.labels.iter().flat_map(|l| l.to_le_bytes()).collect() } else { Vec::new() },
    }
}

fn task_state(s: TaskState) -> pb::TaskState {
    match s {
        TaskState::Assigned => pb::TaskState::Assigned,
        TaskState::Active => pb::TaskState::Active,
        TaskState::Reached => pb::TaskState::Reached,
        TaskState::Preempted => pb::TaskState::Preempted,
        TaskState::Overridden => pb::TaskState::Overridden,
        TaskState::Failed => pb::TaskState::Failed,
        TaskState::Released => pb::TaskState::Released,
        TaskState::Cancelled => pb::TaskState::Cancelled,
    }
}

fn actor(a: Actor) -> String {
    a.as_str().to_owned()
}

impl From<&Transition> for pb::TaskTransition {
    fn from(t: &Transition) -> Self {
        Self {
            from: t.from.map_or(pb::TaskState::Unspecified, task_state) as i32,
            to: task_state(t.to) as i32,
            at: Some(timestamp(t.at)),
            cause: t.cause.clone(),
            actor: actor(t.actor),
            by: t.by.clone(),
        }
    }
}

impl From<&TaskRecord> for pb::Task {
    fn from(t: &TaskRecord) -> Self {
        Self {
            id: t.id,
            mission_id: t.mission_id,
            robot_id: t.robot_id,
            target: Some(pb::Point { x: t.target.x, y: t.target.y }),
            state: task_state(t.state) as i32,
            policy: t.policy.clone(),
            utility: t.utility,
            path_cost: t.path_cost,
            created_at: Some(timestamp(t.created_at)),
            updated_at: Some(timestamp(t.updated_at)),
            transitions: t.transitions.iter().map(Into::into).collect(),
            kind: task_kind(t.kind) as i32,
            created_by: t.created_by.clone(),
            note: t.note.clone(),
        }
    }
}
