//! Proto ↔ domain conversions. Requests are validated here, field by field,
//! with messages that name the field and say what is allowed; nothing past
//! this module sees a proto type. [`answers`] turns what the executive
//! holds into the answers' messages.

mod answers;

pub use answers::{LabelForm, MissionPage, event, frame_to_proto, policies, policy_to_proto, region, segmentation};

use std::collections::BTreeMap;
use std::time::Duration;

use exploration::fusion::Patch;
use exploration::grid::{CellRect, GridFrame};
use exploration::math::Point2;
use exploration::policy::{Capabilities, PolicyConfig};
use exploration_proto::v1 as pb;

use crate::auth::Caller;
use crate::domain::{
    Bid, Heartbeat, LifecycleSettings, MapUpdate, MissionSpec, OperatorNote, Override, Pose, ReplanSettings, RobotSpec,
    RobotState, TaskKind,
};
use crate::error::Error;
use crate::validate;
use crate::validate::Place;

/// Most patches in one map update.
pub const MAX_PATCHES: usize = 4_096;
/// Most bids in one submission.
pub const MAX_BIDS: usize = 10_000;
/// Most peers a robot may report (no mission holds more robots).
pub const MAX_PEERS: usize = 10_000;

pub use crate::validate::{MAX_GRID_CELLS, MAX_GRID_SIDE, MAX_NAME_CHARS};

fn invalid(message: impl Into<String>) -> Error {
    Error::InvalidArgument(message.into())
}

fn finite(value: f64, field: &str) -> Result<f64, Error> {
    Ok(validate::finite(value, field)?)
}

fn in_range(value: f64, field: &str, min: f64, max: f64, unit: &str) -> Result<f64, Error> {
    Ok(validate::in_range(value, field, min, max, unit)?)
}

/// Checks a name: present, not too long, printable.
pub fn name(value: String, field: &str) -> Result<String, Error> {
    Ok(validate::name(&value, field)?)
}

/// A point from its proto form.
pub fn point(p: Option<pb::Point>, field: &str) -> Result<Point2, Error> {
    let p = p.ok_or_else(|| invalid(format!("{field} is required")))?;
    Ok(Point2::new(finite(p.x, &format!("{field}.x"))?, finite(p.y, &format!("{field}.y"))?))
}

/// A pose from its proto form.
pub fn pose(p: Option<pb::Pose>, field: &str) -> Result<Pose, Error> {
    let p = p.ok_or_else(|| invalid(format!("{field} is required")))?;
    Ok(Pose {
        position: Point2::new(finite(p.x, &format!("{field}.x"))?, finite(p.y, &format!("{field}.y"))?),
        heading: exploration::math::normalize_angle(finite(p.theta, &format!("{field}.theta"))?),
    })
}

/// A grid frame from its proto form.
pub fn frame(f: pb::MapFrame) -> Result<GridFrame, Error> {
    let origin = match f.origin {
        Some(_) => point(f.origin, "frame.origin")?,
        None => Point2::origin(),
    };
    Ok(validate::frame(f.resolution, origin, i64::from(f.width), i64::from(f.height), "frame.")?)
}

/// A policy choice; an absent or nameless spec means the default policy.
pub fn policy(spec: Option<pb::PolicySpec>) -> Result<PolicyConfig, Error> {
    let spec = spec.unwrap_or_default();
    let name = if spec.name.trim().is_empty() { "burgard".to_owned() } else { spec.name.trim().to_owned() };
    let overrides: BTreeMap<String, f64> = spec.params.into_iter().collect();
    Ok(PolicyConfig::new(&name, &overrides)?)
}

/// Replanning settings; zero fields take the defaults.
pub fn replan(settings: Option<pb::ReplanSettings>) -> Result<ReplanSettings, Error> {
    let defaults = ReplanSettings::default();
    let Some(s) = settings else {
        return Ok(defaults);
    };
    let or_default = |v: f64, d: f64| if v == 0.0 { d } else { v };
    Ok(ReplanSettings {
        distance_m: in_range(
            or_default(s.distance_m, defaults.distance_m),
            "replan.distance_m",
            validate::REPLAN_DISTANCE_M.0,
            validate::REPLAN_DISTANCE_M.1,
            "metres",
        )?,
        interval: validate::seconds(
            or_default(s.interval_s, defaults.interval.as_secs_f64()),
            "replan.interval_s",
            validate::REPLAN_INTERVAL_S.0,
            validate::REPLAN_INTERVAL_S.1,
        )?,
        frontier_change: in_range(
            or_default(s.frontier_change, defaults.frontier_change),
            "replan.frontier_change",
            0.0,
            1.0,
            "",
        )?,
    })
}

/// Lifecycle settings; zero fields take the defaults.
pub fn lifecycle(settings: Option<pb::LifecycleSettings>, frame: &GridFrame) -> Result<LifecycleSettings, Error> {
    let defaults = LifecycleSettings::default();
    let Some(s) = settings else {
        return Ok(defaults);
    };
    let seconds = |v: f64, d: Duration, field: &str| -> Result<Duration, Error> {
        let (min, max) = validate::LIFECYCLE_S;
        if v == 0.0 { Ok(d) } else { Ok(validate::seconds(v, field, min, max)?) }
    };
    let rendezvous = match s.rendezvous {
        Some(_) => Some(validate::on_map(point(s.rendezvous, "lifecycle.rendezvous")?, frame, "lifecycle.rendezvous")?),
        None => None,
    };
    Ok(LifecycleSettings {
        lease: seconds(s.lease_s, defaults.lease, "lifecycle.lease_s")?,
        stall: seconds(s.stall_s, defaults.stall, "lifecycle.stall_s")?,
        rendezvous,
    })
}

impl TryFrom<pb::CreateMissionRequest> for MissionSpec {
    type Error = Error;

    fn try_from(r: pb::CreateMissionRequest) -> Result<Self, Error> {
        let frame = frame(r.frame.ok_or_else(|| invalid("frame is required"))?)?;
        Ok(Self {
            name: name(r.name, "name")?,
            lifecycle: lifecycle(r.lifecycle, &frame)?,
            frame,
            policy: policy(r.policy)?,
            replan: replan(r.replan)?,
            scoped_by_communication: r.scoped_by_communication,
            lockstep: r.lockstep,
        })
    }
}

/// Who asks, and why. The actor is the name of the caller's token; only on
/// an open executive is it the name the request gives ("operator" when none).
pub fn operator_note(caller: &Caller, actor: String, reason: String) -> Result<OperatorNote, Error> {
    let claimed = actor.trim();
    let claimed = if claimed.is_empty() { "operator".to_owned() } else { name(claimed.to_owned(), "actor")? };
    Ok(OperatorNote { actor: caller.actor(&claimed), reason: validate::free_text(&reason) })
}

/// A rectangle from its proto form: finite, min below max.
pub fn area(r: Option<pb::Rect>, field: &str) -> Result<(Point2, Point2), Error> {
    let r = r.ok_or_else(|| invalid(format!("{field} is required")))?;
    let min = Point2::new(finite(r.min_x, &format!("{field}.min_x"))?, finite(r.min_y, &format!("{field}.min_y"))?);
    let max = Point2::new(finite(r.max_x, &format!("{field}.max_x"))?, finite(r.max_y, &format!("{field}.max_y"))?);
    if min.x >= max.x || min.y >= max.y {
        return Err(invalid(format!(
            "{field} runs from {} to {}; min must lie below max on both axes",
            Place(min),
            Place(max)
        )));
    }
    Ok((min, max))
}

impl TryFrom<Option<pb::override_robot_request::Action>> for OverrideInput {
    type Error = Error;

    fn try_from(action: Option<pb::override_robot_request::Action>) -> Result<Self, Error> {
        use pb::override_robot_request::Action;
        Ok(Self(match action {
            None => {
                return Err(invalid(
                    "action is required: one of goto, explore_region, hold, home, pin_frontier, release, cancel",
                ));
            }
            Some(Action::Goto(p)) => Override::Goto(point(Some(p), "goto")?),
            Some(Action::ExploreRegion(r)) => {
                let (min, max) = area(Some(r), "explore_region")?;
                Override::ExploreRegion(min, max)
            }
            Some(Action::Hold(_)) => Override::Hold,
            Some(Action::Home(_)) => Override::Home,
            Some(Action::PinFrontier(p)) => Override::PinFrontier(point(Some(p), "pin_frontier")?),
            Some(Action::Release(_)) => Override::Release,
            Some(Action::Cancel(_)) => Override::Cancel,
        }))
    }
}

/// A validated override (a newtype so the conversion can live here).
#[derive(Debug, Clone, Copy)]
pub struct OverrideInput(pub Override);

/// A task kind filter; unspecified means any.
pub fn task_kind_filter(kind: i32) -> Result<Option<TaskKind>, Error> {
    Ok(match pb::TaskKind::try_from(kind) {
        Ok(pb::TaskKind::Unspecified) => None,
        Ok(pb::TaskKind::Explore) => Some(TaskKind::Explore),
        Ok(pb::TaskKind::Goto) => Some(TaskKind::Goto),
        Ok(pb::TaskKind::Hold) => Some(TaskKind::Hold),
        Ok(pb::TaskKind::Home) => Some(TaskKind::Home),
        Ok(pb::TaskKind::Pin) => Some(TaskKind::Pin),
        Err(_) => return Err(invalid(format!("kind {kind} is not a task kind"))),
    })
}

impl TryFrom<Option<pb::RobotCapabilities>> for CapabilitiesInput {
    type Error = Error;

    fn try_from(c: Option<pb::RobotCapabilities>) -> Result<Self, Error> {
        let c = c.ok_or_else(|| invalid("capabilities are required"))?;
        let c = Capabilities {
            sensor_range_m: c.sensor_range_m,
            field_of_view_rad: c.field_of_view_rad,
            speed_mps: c.speed_mps,
            footprint_radius_m: c.footprint_radius_m,
        };
        Ok(Self(validate::capabilities(c, "capabilities.")?))
    }
}

/// Validated capabilities (a newtype so the conversion can live here).
#[derive(Debug, Clone, Copy)]
pub struct CapabilitiesInput(pub Capabilities);

impl TryFrom<pb::RegisterRobotRequest> for RobotSpec {
    type Error = Error;

    fn try_from(r: pb::RegisterRobotRequest) -> Result<Self, Error> {
        Ok(Self {
            name: name(r.name, "name")?,
            capabilities: CapabilitiesInput::try_from(r.capabilities)?.0,
            pose: pose(r.pose, "pose")?,
        })
    }
}

impl TryFrom<pb::HeartbeatRequest> for Heartbeat {
    type Error = Error;

    fn try_from(r: pb::HeartbeatRequest) -> Result<Self, Error> {
        let state = match pb::RobotState::try_from(r.state) {
            Ok(pb::RobotState::Idle) => RobotState::Idle,
            Ok(pb::RobotState::Moving) => RobotState::Moving,
            Ok(pb::RobotState::Arrived) => RobotState::Arrived,
            Ok(pb::RobotState::Failed) => RobotState::Failed,
            Ok(pb::RobotState::Unspecified) | Err(_) => {
                return Err(invalid(format!(
                    "state {} is not a robot state; send IDLE, MOVING, ARRIVED or FAILED",
                    r.state
                )));
            }
        };
        let task_id = (r.task_id != 0).then_some(r.task_id);
        if matches!(state, RobotState::Arrived | RobotState::Failed) && task_id.is_none() {
            return Err(invalid("ARRIVED and FAILED must name the task they refer to in task_id"));
        }
        Ok(Self {
            pose: pose(r.pose, "pose")?,
            state,
            task_id,
            reason: validate::free_text(&r.reason),
            peers: peers(r.peers_reported, r.peers)?,
        })
    }
}

impl TryFrom<pb::MapPatch> for PatchInput {
    type Error = Error;

    fn try_from(p: pb::MapPatch) -> Result<Self, Error> {
        let (Ok(x), Ok(y)) = (i32::try_from(p.x), i32::try_from(p.y)) else {
            return Err(invalid(format!("patch corner ({}, {}) lies outside any mission grid", p.x, p.y)));
        };
        let rect = CellRect::new(x, y, p.width, p.height);
        let patch = match pb::CellEncoding::try_from(p.encoding) {
            Ok(pb::CellEncoding::OccupancyPercent) => {
                if !p.values.is_empty() || !p.unknown.is_empty() {
                    return Err(invalid(
                        "an OCCUPANCY_PERCENT patch carries its cells in `occupancy`; leave `values` and `unknown` empty",
                    ));
                }
                Patch::from_occupancy_percent(rect, p.occupancy)?
            }
            Ok(pb::CellEncoding::Probability | pb::CellEncoding::LogOdds) if !p.occupancy.is_empty() => {
                return Err(invalid(
                    "`occupancy` is for OCCUPANCY_PERCENT patches; PROBABILITY and LOG_ODDS carry their cells in `values`",
                ));
            }
            Ok(pb::CellEncoding::Probability) => Patch::from_probabilities(rect, &p.values, &unknown_mask(&p.unknown))?,
            Ok(pb::CellEncoding::LogOdds) => Patch::from_log_odds(rect, &p.values, &unknown_mask(&p.unknown))?,
            Ok(pb::CellEncoding::Unspecified) | Err(_) => {
                return Err(invalid(format!(
                    "encoding {} is not a cell encoding; send PROBABILITY, LOG_ODDS or OCCUPANCY_PERCENT",
                    p.encoding
                )));
            }
        };
        Ok(Self(patch))
    }
}

/// The `unknown` bytes of a patch as flags: non-zero is unknown.
fn unknown_mask(bytes: &[u8]) -> Vec<bool> {
    bytes.iter().map(|&b| b != 0).collect()
}

/// A validated patch (a newtype so the conversion can live here).
#[derive(Debug, Clone)]
pub struct PatchInput(pub Patch);

impl TryFrom<pb::UpdateMapRequest> for MapUpdate {
    type Error = Error;

    fn try_from(r: pb::UpdateMapRequest) -> Result<Self, Error> {
        if r.patches.len() > MAX_PATCHES {
            return Err(invalid(format!(
                "{} patches in one update; send at most {MAX_PATCHES} (merge them or split the update)",
                r.patches.len()
            )));
        }
        let patches = r
            .patches
            .into_iter()
            .enumerate()
            .map(|(i, p)| PatchInput::try_from(p).map(|p| p.0).map_err(|e| invalid(format!("patch {i}: {e}"))))
            .collect::<Result<Vec<_>, _>>()?;
        Ok(Self { seq: r.seq, pose: pose(r.pose, "pose")?, patches, peers: peers(r.peers_reported, r.peers)? })
    }
}

/// The peers a robot reported, when it reported them: bounded, without repeats.
fn peers(reported: bool, mut peers: Vec<u64>) -> Result<Option<Vec<u64>>, Error> {
    if !reported {
        return Ok(None);
    }
    if peers.len() > MAX_PEERS {
        return Err(invalid(format!("peers lists {} robots; at most {MAX_PEERS} are allowed", peers.len())));
    }
    peers.sort_unstable();
    peers.dedup();
    Ok(Some(peers))
}

/// Bids from their proto form.
pub fn bids(bids: Vec<pb::Bid>) -> Result<Vec<Bid>, Error> {
    if bids.len() > MAX_BIDS {
        return Err(Error::ResourceExhausted(format!(
            "{} bids in one submission; at most {MAX_BIDS} are kept per robot",
            bids.len()
        )));
    }
    bids.into_iter()
        .enumerate()
        .map(|(i, b)| {
            let region = b.gain_region.ok_or_else(|| invalid(format!("bids[{i}].gain_region is required")))?;
            let min = Point2::new(
                finite(region.min_x, &format!("bids[{i}].gain_region.min_x"))?,
                finite(region.min_y, &format!("bids[{i}].gain_region.min_y"))?,
            );
            let max = Point2::new(
                finite(region.max_x, &format!("bids[{i}].gain_region.max_x"))?,
                finite(region.max_y, &format!("bids[{i}].gain_region.max_y"))?,
            );
            if min.x > max.x || min.y > max.y {
                return Err(invalid(format!("bids[{i}].gain_region has min above max")));
            }
            Ok(Bid {
                target: point(b.target, &format!("bids[{i}].target"))?,
                path_cost: in_range(b.path_cost, &format!("bids[{i}].path_cost"), 0.0, f64::MAX, "")?,
                information_gain: in_range(
                    b.information_gain,
                    &format!("bids[{i}].information_gain"),
                    0.0,
                    f64::MAX,
                    "",
                )?,
                gain_region: (min, max),
            })
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn pb_frame(resolution: f64, width: u32, height: u32) -> pb::MapFrame {
        pb::MapFrame { resolution, origin: Some(pb::Point { x: 1.0, y: 2.0 }), width, height }
    }

    #[test]
    fn frames_reject_zero_absurd_and_non_finite_sizes() {
        assert!(frame(pb_frame(0.05, 100, 80)).is_ok());
        for bad in [
            pb_frame(0.05, 0, 80),
            pb_frame(0.05, 100, 0),
            pb_frame(0.05, 20_001, 10),
            pb_frame(0.05, 20_000, 20_000),
            pb_frame(0.0, 10, 10),
            pb_frame(f64::NAN, 10, 10),
            pb_frame(100.0, 10, 10),
        ] {
            let err = frame(bad).unwrap_err();
            assert!(matches!(err, Error::InvalidArgument(_)), "{bad:?}: {err}");
        }
        let mut nan_origin = pb_frame(0.05, 10, 10);
        nan_origin.origin = Some(pb::Point { x: f64::NAN, y: 0.0 });
        assert!(frame(nan_origin).is_err());
    }

    #[test]
    fn patches_name_the_broken_part() {
        let patch = |encoding: pb::CellEncoding, values: Vec<f32>| pb::MapPatch {
            x: 0,
            y: 0,
            width: 2,
            height: 1,
            encoding: encoding as i32,
            values,
            unknown: vec![],
            occupancy: vec![],
        };
        assert!(PatchInput::try_from(patch(pb::CellEncoding::Probability, vec![0.1, 0.9])).is_ok());
        let err = PatchInput::try_from(patch(pb::CellEncoding::Unspecified, vec![0.1, 0.9])).unwrap_err();
        assert!(err.to_string().contains("PROBABILITY"), "{err}");
        let err = PatchInput::try_from(patch(pb::CellEncoding::Probability, vec![0.1])).unwrap_err();
        assert!(err.to_string().contains("carries 1 values"), "{err}");
        let err = PatchInput::try_from(patch(pb::CellEncoding::Probability, vec![0.1, f32::NAN])).unwrap_err();
        assert!(err.to_string().contains("not a finite number"), "{err}");
        let err = PatchInput::try_from(patch(pb::CellEncoding::Probability, vec![0.1, -0.5])).unwrap_err();
        assert!(err.to_string().contains("[0, 1]"), "{err}");
        let mut far = patch(pb::CellEncoding::LogOdds, vec![0.1, 0.2]);
        far.x = u32::MAX;
        assert!(PatchInput::try_from(far).is_err());
    }

    #[test]
    fn occupancy_patches_carry_their_cells_in_occupancy_only() {
        let patch = |occupancy: Vec<u8>| pb::MapPatch {
            width: 2,
            height: 1,
            encoding: pb::CellEncoding::OccupancyPercent as i32,
            occupancy,
            ..Default::default()
        };
        let accepted = PatchInput::try_from(patch(vec![100, 255])).unwrap().0;
        assert_eq!(accepted.known_cells(), 1);
        let err = PatchInput::try_from(patch(vec![100, 128])).unwrap_err();
        assert!(matches!(err, Error::InvalidArgument(_)) && err.to_string().contains("byte 1"), "{err}");
        let err = PatchInput::try_from(patch(vec![100])).unwrap_err();
        assert!(err.to_string().contains("carries 1 values"), "{err}");
        let mut mixed = patch(vec![0, 0]);
        mixed.values = vec![0.1, 0.2];
        let err = PatchInput::try_from(mixed).unwrap_err();
        assert!(err.to_string().contains("leave `values` and `unknown` empty"), "{err}");
        let mut mixed = patch(vec![0, 0]);
        mixed.encoding = pb::CellEncoding::Probability as i32;
        mixed.values = vec![0.1, 0.2];
        let err = PatchInput::try_from(mixed).unwrap_err();
        assert!(err.to_string().contains("`occupancy` is for OCCUPANCY_PERCENT"), "{err}");
    }

    #[test]
    fn heartbeats_must_name_the_task_they_end() {
        let request = pb::HeartbeatRequest {
            robot_id: 1,
            pose: Some(pb::Pose::default()),
            state: pb::RobotState::Arrived as i32,
            task_id: 0,
            reason: String::new(),
            ..Default::default()
        };
        assert!(Heartbeat::try_from(request.clone()).is_err());
        assert!(Heartbeat::try_from(pb::HeartbeatRequest { task_id: 3, ..request.clone() }).is_ok());
        assert!(Heartbeat::try_from(pb::HeartbeatRequest { state: 42, ..request }).is_err());
    }
}
