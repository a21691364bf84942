//! What the executive holds, as the answers' messages: missions, robots,
//! tasks and their history, assignments, events, the segmentation, the
//! policy catalogue. Nothing here can fail, the executive's records being
//! valid by construction, but an answer too large for a client to read.

use exploration::grid::GridFrame;
use exploration::math::Point2;
use exploration::policy::{Capabilities, PolicyConfig, catalogue};
use exploration_proto::v1 as pb;

use prost::Message as _;

use crate::MAX_MESSAGE_BYTES;
use crate::domain::{
    Actor, Assignment, Leftover, LeftoverReason, LifecycleSettings, MissionEvent, MissionState, Region, ReplanSettings,
    RobotState, StoredSegmentation, TaskKind, TaskRecord, TaskState, Timestamp, Transition,
};
use crate::error::Error;
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
            leftovers: r.leftovers.listed.iter().map(leftover).collect(),
            unlisted_leftovers: r.leftovers.unlisted_clusters,
            unlisted_leftover_cells: r.leftovers.unlisted_cells,
            given_segmentation: m.given_segmentation,
        }
    }
}

/// The most missions a `ListMissions` page holds, and what `limit = 0` asks.
pub const MOST_MISSIONS_A_PAGE: usize = 1_000;

/// The bytes a `ListMissions` page stays within: gRPC's default message
/// limit (4 MiB), less room for the rest of the answer, so that a client
/// that never raised it reads every page. One mission at its largest (1 000
/// forbidden regions with the longest reason and actor, 1 000 leftovers) is
/// about 2.6 MB, so every page holds at least one.
pub const MISSION_PAGE_BYTES: usize = 4_000_000;

/// A `ListMissions` answer, built one mission at a time: the executive may
/// hold 1 000 missions of up to 2.6 MB each, far past what a client reads
/// in one message.
#[derive(Debug)]
pub struct MissionPage {
    missions: Vec<pb::Mission>,
    bytes: usize,
    limit: usize,
}

impl MissionPage {
    /// An empty page of at most `limit` missions (0: [`MOST_MISSIONS_A_PAGE`]).
    pub fn new(limit: u32) -> Self {
        let limit = match limit as usize {
            0 => MOST_MISSIONS_A_PAGE,
            n => n.min(MOST_MISSIONS_A_PAGE),
        };
        Self { missions: Vec::new(), bytes: 0, limit }
    }

    /// Adds `mission` unless the page is full, in missions or in bytes. The
    /// first mission is always taken, so that every page moves on.
    pub fn take(&mut self, mission: &MissionSummary) -> bool {
        if self.missions.len() >= self.limit {
            return false;
        }
        let mission = pb::Mission::from(mission);
        let bytes = prost::encoding::message::encoded_len(1, &mission);
        if !self.missions.is_empty() && self.bytes + bytes > MISSION_PAGE_BYTES {
            return false;
        }
        self.bytes += bytes;
        self.missions.push(mission);
        true
    }

    /// The answer; `next` is where the next page starts after, if one does.
    pub fn finish(self, next: Option<u64>) -> pb::ListMissionsResponse {
        pb::ListMissionsResponse { missions: self.missions, next_after_id: next.unwrap_or(0) }
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

/// How `GetSegmentation` is asked to send the labels.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LabelForm {
    /// No labels.
    Omitted,
    /// `labels`: four bytes a cell.
    PerCell,
    /// `label_runs`: eight bytes a run.
    Runs,
}

impl LabelForm {
    /// The form a request asks for.
    pub fn asked_by(r: &pb::GetSegmentationRequest) -> Self {
        match (r.include_labels, r.label_runs) {
            (false, _) => Self::Omitted,
            (true, false) => Self::PerCell,
            (true, true) => Self::Runs,
        }
    }

    /// Bytes the labels take in this form on the wire.
    fn wire_bytes(self, labels: &[u32]) -> usize {
        let payload = match self {
            Self::Omitted => 0,
            Self::PerCell => labels.len() * 4,
            Self::Runs => exploration_proto::label_runs::encoded_len(labels),
        };
        // A bytes field: a tag byte and a varint length, or nothing when empty.
        if payload == 0 { 0 } else { 1 + prost::encoding::encoded_len_varint(payload as u64) + payload }
    }

    fn request(self) -> &'static str {
        match self {
            Self::Omitted => "without include_labels",
            Self::PerCell => "with include_labels and without label_runs",
            Self::Runs => "with include_labels and label_runs",
        }
    }
}

/// A segmentation in proto form with its labels in the form asked for;
/// RESOURCE_EXHAUSTED, naming a form that fits if one does, when the answer
/// would pass the [`MAX_MESSAGE_BYTES`] a client reads.
pub fn segmentation(
    mission_id: u64,
    frame: &GridFrame,
    stored: Option<&StoredSegmentation>,
    form: LabelForm,
) -> Result<pb::Segmentation, Error> {
    let Some(stored) = stored else {
        return Ok(pb::Segmentation { mission_id, frame: Some(frame_to_proto(frame)), ..pb::Segmentation::default() });
    };
    let mut answer = segmentation_without_labels(mission_id, frame, stored);
    let labels = &stored.segmentation.labels;
    let size = |form: LabelForm| answer.encoded_len() + form.wire_bytes(labels);
    if size(form) > MAX_MESSAGE_BYTES {
        let fits = [LabelForm::Runs, LabelForm::PerCell, LabelForm::Omitted]
            .into_iter()
            .find(|&other| size(other) <= MAX_MESSAGE_BYTES)
            .map_or_else(
                || {
                    format!(
                        "it has {} segments and {} critical points",
                        answer.segments.len(),
                        answer.critical_points.len()
                    )
                },
                |other| format!("asked {} it takes {} bytes", other.request(), size(other)),
            );
        return Err(Error::ResourceExhausted(format!(
            "the segmentation asked {} would take {} bytes, more than the {MAX_MESSAGE_BYTES} a client reads; {fits}",
            form.request(),
            size(form),
        )));
    }
    match form {
        LabelForm::Omitted => {}
        LabelForm::PerCell => answer.labels = labels.iter().flat_map(|l| l.to_le_bytes()).collect(),
        LabelForm::Runs => answer.label_runs = exploration_proto::label_runs::encode(labels),
    }
    Ok(answer)
}

fn segmentation_without_labels(mission_id: u64, frame: &GridFrame, stored: &StoredSegmentation) -> pb::Segmentation {
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
        ..pb::Segmentation::default()
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

#[cfg(test)]
mod tests {
    use exploration::grid::{Cell, CellRect};
    use exploration::segment::{CriticalPoint, Segment, Segmentation};

    use super::*;

    /// A 20 000 × 1 000 map (the largest allowed is 25 million cells) cut
    /// into rooms of 100 columns: 20 million labels, 80 MB at four bytes a
    /// cell, a few hundred kilobytes as runs.
    fn wide_building() -> (GridFrame, StoredSegmentation) {
        let frame = GridFrame::new(0.05, Point2::new(0.0, 0.0), 20_000, 1_000);
        let labels: Vec<u32> = (0..frame.len()).map(|i| (i % 20_000 / 100) as u32 + 1).collect();
        let segments = (1..=200)
            .map(|id| Segment { id, cells: 100_000, bounds: CellRect::new(0, 0, 100, 1_000), frontier: vec![] })
            .collect();
        let critical_points = vec![CriticalPoint { cell: Cell::new(100, 500), clearance: 3.0 }];
        let segmentation = Segmentation { frame, labels, segments, critical_points };
        (frame, StoredSegmentation { computed_at: Timestamp(1_000), segmentation })
    }

    #[test]
    fn labels_too_large_for_a_client_are_refused_naming_the_runs_that_fit() {
        let (frame, stored) = wide_building();
        let Err(Error::ResourceExhausted(message)) = segmentation(7, &frame, Some(&stored), LabelForm::PerCell) else {
            panic!("80 MB of labels were answered");
        };
        assert!(message.contains("without label_runs would take 800"), "{message}");
        assert!(message.contains("more than the 67108864 a client reads"), "{message}");
        assert!(message.contains("asked with include_labels and label_runs it takes"), "{message}");

        let answer = segmentation(7, &frame, Some(&stored), LabelForm::Runs).unwrap();
        assert!(answer.encoded_len() < 4 << 20, "{} bytes", answer.encoded_len());
        assert!(answer.labels.is_empty());
        assert_eq!(answer.labels_per_cell(frame.len()).unwrap().as_deref(), Some(&stored.segmentation.labels[..]));
        assert_eq!(answer.segments.len(), 200);

        let bare = segmentation(7, &frame, Some(&stored), LabelForm::Omitted).unwrap();
        assert!(bare.labels.is_empty() && bare.label_runs.is_empty());
    }

    #[test]
    fn a_fragmented_segmentation_is_refused_in_every_form_but_without_labels() {
        let (frame, mut stored) = wide_building();
        // A label change at every cell: 8 bytes a cell as runs, 4 per cell.
        stored.segmentation.labels.iter_mut().enumerate().for_each(|(i, l)| *l = (i % 2) as u32);
        for form in [LabelForm::Runs, LabelForm::PerCell] {
            let Err(Error::ResourceExhausted(message)) = segmentation(7, &frame, Some(&stored), form) else {
                panic!("{form:?} was answered");
            };
            assert!(message.contains("asked without include_labels it takes"), "{message}");
        }
        // A small map's labels fit in both forms, and agree.
        let frame = GridFrame::new(0.05, Point2::new(0.0, 0.0), 50, 40);
        stored.segmentation.frame = frame;
        stored.segmentation.labels.truncate(frame.len());
        let runs = segmentation(7, &frame, Some(&stored), LabelForm::Runs).unwrap();
        let per_cell = segmentation(7, &frame, Some(&stored), LabelForm::PerCell).unwrap();
        assert_eq!(per_cell.labels.len(), frame.len() * 4);
        assert_eq!(runs.labels_per_cell(frame.len()).unwrap(), per_cell.labels_per_cell(frame.len()).unwrap());
    }

    /// A mission at its largest: 1 000 forbidden regions whose reason and
    /// actor are as long as kept, in four-byte characters, and 1 000
    /// leftovers.
    fn largest_mission(id: u64) -> MissionSummary {
        use crate::domain::{Leftovers, MOST_LEFTOVERS};
        use crate::validate::{MAX_FORBIDDEN_REGIONS, MAX_NAME_CHARS, MAX_REASON_CHARS};
        let region = |i: usize| Region {
            id: i as u64,
            mission_id: id,
            min: Point2::new(0.0, 0.0),
            max: Point2::new(1.0, 1.0),
            actor: "\u{1F916}".repeat(MAX_NAME_CHARS),
            reason: "\u{1F6A7}".repeat(MAX_REASON_CHARS),
            created_at: Timestamp(i as i64),
        };
        let leftover = Leftover { reason: LeftoverReason::TooSmall, cells: 1, position: Point2::new(1.5, -2.5) };
        let leftovers = Leftovers { listed: vec![leftover; MOST_LEFTOVERS], unlisted_clusters: 9, unlisted_cells: 9 };
        MissionSummary {
            record: crate::domain::MissionRecord {
                id,
                spec: crate::store::suite::spec(),
                state: MissionState::Completed,
                replans: 1,
                map_updates: 1,
                paused: false,
                leftovers,
                created_at: Timestamp(0),
            },
            robots: 1_000,
            known_cells: 1,
            frontier_cells: 1,
            forbidden: (0..MAX_FORBIDDEN_REGIONS).map(region).collect(),
            given_segmentation: true,
        }
    }

    #[test]
    fn a_page_of_missions_stays_within_what_a_client_reads_and_holds_at_least_one() {
        let largest = largest_mission(1);
        let alone = pb::Mission::from(&largest).encoded_len();
        assert!(alone > MISSION_PAGE_BYTES / 2 && alone < MISSION_PAGE_BYTES, "{alone} bytes");

        let mut page = MissionPage::new(0);
        assert!(page.take(&largest));
        assert!(!page.take(&largest_mission(2)), "two of the largest missions fit in one page");
        let answer = page.finish(Some(1));
        assert!(answer.encoded_len() <= 4 << 20, "{} bytes", answer.encoded_len());
        assert_eq!((answer.missions.len(), answer.next_after_id), (1, 1));

        // Small missions fill a page up to its count.
        let mut small = largest_mission(3);
        small.forbidden.clear();
        small.record.leftovers.listed.clear();
        let mut page = MissionPage::new(5_000);
        assert_eq!((0..1_001).filter(|_| page.take(&small)).count(), MOST_MISSIONS_A_PAGE);
        let mut page = MissionPage::new(2);
        assert_eq!((0..3).filter(|_| page.take(&small)).count(), 2);
        assert_eq!(page.finish(None).next_after_id, 0);
    }
}
