//! Rows read back into records, checked like input from the network.
//!
//! A database file can be edited, restored from an old backup or damaged; a
//! value that would make the executive panic, wrap around or allocate without
//! bound later is refused here, with an error naming the table, the row and
//! the column, so that a bad row stops the start instead.

use std::collections::BTreeMap;
use std::sync::Arc;

use super::statement::{Columns, Value};

use crate::domain::{
    Actor, Bid, BlacklistEntry, Leftover, LeftoverReason, Leftovers, LifecycleSettings, MissionEvent, MissionRecord,
    MissionSpec, MissionState, Pose, Region, ReplanSettings, RobotId, RobotRecord, RobotState, Rooms,
    StoredSegmentation, TaskId, TaskKind, TaskRecord, TaskState, Timestamp, Transition,
};
use crate::store::{Lease, LoggedPatch, MapSnapshot, Share, StoreError};
use crate::validate::{self, Invalid};
use exploration::fusion::Patch;
use exploration::grid::{Cell, CellRect, GridFrame};
use exploration::math::Point2;
use exploration::policy::{Capabilities, PolicyConfig};
use exploration::segment::{CriticalPoint, Segment, Segmentation};

/// Where a value came from: its table and row, for the error.
#[derive(Debug, Clone, Copy)]
pub(super) struct At<'a> {
    table: &'a str,
    id: i64,
}

impl<'a> At<'a> {
    /// The row of `table` whose identity is in column `key`.
    pub(super) fn row(table: &'a str, row: &impl Columns, key: &str) -> Result<Self, StoreError> {
        let id = row
            .value::<i64>(key)
            .map_err(|e| StoreError::Corrupt(format!("{table}: a row without a valid {key}: {e}")))?;
        Ok(Self { table, id })
    }

    /// An error about this row.
    pub(super) fn bad(self, what: impl std::fmt::Display) -> StoreError {
        StoreError::Corrupt(format!("{} row {}: {what}", self.table, self.id))
    }

    fn invalid(self, e: Invalid) -> StoreError {
        self.bad(e)
    }

    /// A column of the expected type.
    pub(super) fn get<T: Value>(self, row: &impl Columns, column: &str) -> Result<T, StoreError> {
        row.value(column).map_err(|e| self.bad(format!("{column}: {e}")))
    }

    fn finite(self, row: &impl Columns, column: &str) -> Result<f64, StoreError> {
        validate::finite(self.get(row, column)?, column).map_err(|e| self.invalid(e))
    }

    fn in_range(self, row: &impl Columns, column: &str, min: f64, max: f64) -> Result<f64, StoreError> {
        validate::in_range(self.get(row, column)?, column, min, max, "").map_err(|e| self.invalid(e))
    }

    fn count(self, row: &impl Columns, column: &str) -> Result<u64, StoreError> {
        validate::count(self.get(row, column)?, column).map_err(|e| self.invalid(e))
    }

    fn id_column(self, row: &impl Columns, column: &str) -> Result<u64, StoreError> {
        match self.count(row, column)? {
            0 => Err(self.bad(format!("{column} is 0; identities start at 1"))),
            id => Ok(id),
        }
    }

    fn flag(self, row: &impl Columns, column: &str) -> Result<bool, StoreError> {
        match self.get::<i64>(row, column)? {
            0 => Ok(false),
            1 => Ok(true),
            v => Err(self.bad(format!("{column} is {v}; it must be 0 or 1"))),
        }
    }

    fn cell(self, row: &impl Columns, x: &str, y: &str) -> Result<Cell, StoreError> {
        let coordinate = |column: &str| {
            let v: i64 = self.get(row, column)?;
            i32::try_from(v).map_err(|_| self.bad(format!("{column} is {v}, not a cell coordinate")))
        };
        Ok(Cell::new(coordinate(x)?, coordinate(y)?))
    }

    fn point(self, row: &impl Columns, x: &str, y: &str) -> Result<Point2, StoreError> {
        // Finite is enough: every use clips world points to the grid in f64.
        Ok(Point2::new(self.finite(row, x)?, self.finite(row, y)?))
    }

    fn on_map(self, row: &impl Columns, x: &str, y: &str, frame: &GridFrame) -> Result<Point2, StoreError> {
        let point = Point2::new(self.finite(row, x)?, self.finite(row, y)?);
        validate::on_map(point, frame, &format!("({x}, {y})")).map_err(|e| self.invalid(e))
    }

    fn timestamp(self, row: &impl Columns, column: &str) -> Result<Timestamp, StoreError> {
        Ok(Timestamp(self.get(row, column)?))
    }

    fn parse<T>(self, row: &impl Columns, column: &str, parse: impl Fn(&str) -> Option<T>) -> Result<T, StoreError> {
        let text: String = self.get(row, column)?;
        parse(&text).ok_or_else(|| self.bad(format!("{column} {text:?} is not a known value")))
    }

    fn name(self, row: &impl Columns, column: &str) -> Result<String, StoreError> {
        validate::name(&self.get::<String>(row, column)?, column).map_err(|e| self.invalid(e))
    }
}

/// The leftovers as JSON: an array of clusters, or, when some were not
/// listed, `{"listed": [...], "unlisted_clusters": n, "unlisted_cells": m}`.
pub(super) fn leftovers_json(leftovers: &Leftovers) -> String {
    let listed: Vec<serde_json::Value> = leftovers
        .listed
        .iter()
        .map(|l| {
            serde_json::json!({
                "reason": l.reason.as_str(), "cells": l.cells, "x": l.position.x, "y": l.position.y,
            })
        })
        .collect();
    if leftovers.unlisted_clusters == 0 {
        return serde_json::Value::Array(listed).to_string();
    }
    serde_json::json!({
        "listed": listed,
        "unlisted_clusters": leftovers.unlisted_clusters,
        "unlisted_cells": leftovers.unlisted_cells,
    })
    .to_string()
}

/// Leftovers from either JSON form. A row written before they were bounded
/// may list any number: they are bounded as they are read.
fn leftovers_from_json(at: At<'_>, json: &str) -> Result<Leftovers, StoreError> {
    let bad = |what: &str| at.bad(format!("leftovers: {what}"));
    let value: serde_json::Value = serde_json::from_str(json).map_err(|e| bad(&e.to_string()))?;
    let count = |key: &str| value.get(key).map_or(Ok(0), |v| v.as_u64().ok_or_else(|| bad(key)));
    let (unlisted_clusters, unlisted_cells) = (count("unlisted_clusters")?, count("unlisted_cells")?);
    let listed = value
        .as_array()
        .or_else(|| value.get("listed").and_then(serde_json::Value::as_array))
        .ok_or_else(|| bad("neither a list nor an object with one"))?
        .iter()
        .map(|l| {
            let reason = l["reason"].as_str().and_then(LeftoverReason::parse).ok_or_else(|| bad("reason"))?;
            let coordinate = |key: &str| {
                let v = l[key].as_f64().ok_or_else(|| bad(key))?;
                validate::finite(v, &format!("leftovers.{key}")).map_err(|e| at.invalid(e))
            };
            Ok(Leftover {
                reason,
                cells: usize::try_from(l["cells"].as_u64().ok_or_else(|| bad("cells"))?).map_err(|_| bad("cells"))?,
                position: Point2::new(coordinate("x")?, coordinate("y")?),
            })
        })
        .collect::<Result<Vec<_>, StoreError>>()?;
    let mut leftovers = Leftovers::keep_largest(listed);
    leftovers.unlisted_clusters = leftovers.unlisted_clusters.saturating_add(unlisted_clusters);
    leftovers.unlisted_cells = leftovers.unlisted_cells.saturating_add(unlisted_cells);
    Ok(leftovers)
}

/// The grid frame of a `missions` row.
pub(super) fn frame_from_row(at: At<'_>, row: &impl Columns) -> Result<GridFrame, StoreError> {
    validate::frame(
        at.get(row, "resolution")?,
        Point2::new(at.get(row, "origin_x")?, at.get(row, "origin_y")?),
        at.get(row, "width")?,
        at.get(row, "height")?,
        "",
    )
    .map_err(|e| at.invalid(e))
}

pub(super) fn mission_from_row(row: &impl Columns) -> Result<MissionRecord, StoreError> {
    let at = At::row("missions", row, "id")?;
    let id = at.id_column(row, "id")?;
    let params_json: String = at.get(row, "policy_params")?;
    let params: BTreeMap<String, f64> =
        serde_json::from_str(&params_json).map_err(|e| at.bad(format!("policy_params: {e}")))?;
    let policy = PolicyConfig::new(&at.get::<String>(row, "policy")?, &params).map_err(|e| at.bad(e))?;
    let frame = frame_from_row(at, row)?;
    let seconds = |column: &str, (min, max): (f64, f64)| {
        validate::seconds(at.get(row, column)?, column, min, max).map_err(|e| at.invalid(e))
    };
    let rendezvous = match (at.get::<Option<f64>>(row, "rendezvous_x")?, at.get::<Option<f64>>(row, "rendezvous_y")?) {
        (Some(_), Some(_)) => Some(at.on_map(row, "rendezvous_x", "rendezvous_y", &frame)?),
        (None, None) => None,
        _ => return Err(at.bad("rendezvous_x and rendezvous_y must both be set or both be NULL")),
    };
    Ok(MissionRecord {
        id,
        spec: MissionSpec {
            name: at.name(row, "name")?,
            frame,
            policy,
            replan: ReplanSettings {
                distance_m: at.in_range(
                    row,
                    "replan_distance_m",
                    validate::REPLAN_DISTANCE_M.0,
                    validate::REPLAN_DISTANCE_M.1,
                )?,
                interval: seconds("replan_interval_s", validate::REPLAN_INTERVAL_S)?,
                frontier_change: at.in_range(row, "replan_frontier_change", 0.0, 1.0)?,
            },
            scoped_by_communication: at.flag(row, "scoped_by_communication")?,
            lockstep: at.flag(row, "lockstep")?,
            lifecycle: LifecycleSettings {
                lease: seconds("lease_s", validate::LIFECYCLE_S)?,
                stall: seconds("stall_s", validate::LIFECYCLE_S)?,
                rendezvous,
            },
        },
        state: at.parse(row, "state", MissionState::parse)?,
        replans: at.count(row, "replans")?,
        map_updates: at.count(row, "map_updates")?,
        paused: at.flag(row, "paused")?,
        leftovers: leftovers_from_json(at, &at.get::<String>(row, "leftovers")?)?,
        created_at: at.timestamp(row, "created_at")?,
    })
}

/// A robot of the mission whose grid is `frame`.
pub(super) fn robot_from_row(row: &impl Columns, frame: &GridFrame) -> Result<RobotRecord, StoreError> {
    let at = At::row("robots", row, "id")?;
    let capabilities = Capabilities {
        sensor_range_m: at.get(row, "sensor_range_m")?,
        field_of_view_rad: at.get(row, "field_of_view_rad")?,
        speed_mps: at.get(row, "speed_mps")?,
        footprint_radius_m: at.get(row, "footprint_radius_m")?,
    };
    Ok(RobotRecord {
        id: at.id_column(row, "id")?,
        mission_id: at.id_column(row, "mission_id")?,
        name: at.name(row, "name")?,
        capabilities: validate::capabilities(capabilities, "").map_err(|e| at.invalid(e))?,
        state: at.parse(row, "state", RobotState::parse)?,
        pose: Pose {
            position: at.on_map(row, "pose_x", "pose_y", frame)?,
            heading: exploration::math::normalize_angle(at.finite(row, "pose_theta")?),
        },
        last_map_seq: at.count(row, "last_map_seq")?,
        distance_m: at.in_range(row, "distance_m", 0.0, f64::MAX)?,
        assignment_version: at.count(row, "assignment_version")?,
        assigned_distance_m: at.in_range(row, "assigned_distance_m", 0.0, f64::MAX)?,
        current_task: match at.get::<Option<i64>>(row, "current_task_id")? {
            Some(_) => Some(at.id_column(row, "current_task_id")?),
            None => None,
        },
        last_seen: at.timestamp(row, "last_seen")?,
        lost: at.flag(row, "lost")?,
        home: at.on_map(row, "home_x", "home_y", frame)?,
    })
}

pub(super) fn task_from_row(row: &impl Columns) -> Result<TaskRecord, StoreError> {
    let at = At::row("tasks", row, "id")?;
    let gain_region = match (
        at.get::<Option<i64>>(row, "gain_x")?,
        at.get::<Option<i64>>(row, "gain_y")?,
        at.get::<Option<i64>>(row, "gain_width")?,
        at.get::<Option<i64>>(row, "gain_height")?,
    ) {
        (Some(x), Some(y), Some(w), Some(h)) => {
            let fits = |v: i64| i32::try_from(v).is_ok();
            let side = |v: i64| u32::try_from(v).ok().filter(|&s| s > 0 && s <= validate::MAX_GRID_SIDE);
            match (fits(x) && fits(y), side(w), side(h)) {
                (true, Some(w), Some(h)) => Some(CellRect::new(x as i32, y as i32, w, h)),
                _ => return Err(at.bad(format!("gain region {x}, {y}, {w}×{h} is not a rectangle of the grid"))),
            }
        }
        (None, None, None, None) => None,
        _ => return Err(at.bad("gain_x, gain_y, gain_width and gain_height must all be set or all be NULL")),
    };
    Ok(TaskRecord {
        id: at.id_column(row, "id")?,
        mission_id: at.id_column(row, "mission_id")?,
        robot_id: at.id_column(row, "robot_id")?,
        kind: at.parse(row, "kind", TaskKind::parse)?,
        target: at.point(row, "target_x", "target_y")?,
        state: at.parse(row, "state", TaskState::parse)?,
        policy: at.get(row, "policy")?,
        utility: at.get(row, "utility")?,
        path_cost: at.get(row, "path_cost")?,
        gain_region,
        created_by: at.get(row, "created_by")?,
        note: at.get(row, "note")?,
        created_at: at.timestamp(row, "created_at")?,
        updated_at: at.timestamp(row, "updated_at")?,
        transitions: Vec::new(),
    })
}

pub(super) fn transition_from_row(row: &impl Columns) -> Result<(TaskId, Transition), StoreError> {
    let at = At::row("task_transitions", row, "id")?;
    let from = match at.get::<Option<String>>(row, "from_state")? {
        Some(_) => Some(at.parse(row, "from_state", TaskState::parse)?),
        None => None,
    };
    Ok((
        at.id_column(row, "task_id")?,
        Transition {
            from,
            to: at.parse(row, "to_state", TaskState::parse)?,
            at: at.timestamp(row, "at")?,
            cause: at.get(row, "cause")?,
            actor: at.parse(row, "actor", Actor::parse)?,
            by: at.get(row, "by_name")?,
        },
    ))
}

/// A logged patch of the mission whose grid is `frame`, with its log position.
pub(super) fn patch_from_row(row: &impl Columns, frame: &GridFrame) -> Result<(u64, LoggedPatch), StoreError> {
    let at = At::row("map_patches", row, "id")?;
    let side = |column: &str| {
        let v: i64 = at.get(row, column)?;
        u32::try_from(v).ok().filter(|&s| s > 0).ok_or_else(|| at.bad(format!("{column} is {v} cells")))
    };
    let corner = at.cell(row, "x", "y")?;
    let rect = CellRect::new(corner.x, corner.y, side("width")?, side("height")?);
    if !frame.contains_rect(&rect) {
        return Err(at.bad(format!("the patch {rect:?} leaves the {}×{} mission grid", frame.width, frame.height)));
    }
    let stored: Vec<u8> = at.get(row, "cells")?;
    let format: i64 = at.get(row, "cells_format")?;
    let patch = decode_cells(&at, rect, stored, format)?;
    let logged =
        LoggedPatch { robot_id: at.id_column(row, "robot_id")?, seq: at.count(row, "seq")?, patch: Arc::new(patch) };
    Ok((at.id_column(row, "id")?, logged))
}

/// A mission's map snapshot, its bytes unchecked until they are decoded
/// (see [`crate::store::StoredMap::fuse`]).
pub(super) fn snapshot_from_row(row: &impl Columns) -> Result<MapSnapshot, StoreError> {
    let at = At::row("map_snapshots", row, "mission_id")?;
    Ok(MapSnapshot {
        mission_id: at.id_column(row, "mission_id")?,
        through_patch_id: at.id_column(row, "through_patch_id")?,
        folded: at.count(row, "folded")?,
        bytes: at.get(row, "state")?,
        raw_bytes: at.count(row, "raw_bytes")?,
    })
}

pub(super) fn bid_from_row(row: &impl Columns) -> Result<Bid, StoreError> {
    let at = At::row("bids", row, "robot_id")?;
    Ok(Bid {
        target: at.point(row, "target_x", "target_y")?,
        path_cost: at.in_range(row, "path_cost", 0.0, f64::MAX)?,
        information_gain: at.in_range(row, "information_gain", 0.0, f64::MAX)?,
        gain_region: (
            Point2::new(at.finite(row, "region_min_x")?, at.finite(row, "region_min_y")?),
            Point2::new(at.finite(row, "region_max_x")?, at.finite(row, "region_max_y")?),
        ),
    })
}

pub(super) fn blacklist_from_row(row: &impl Columns) -> Result<BlacklistEntry, StoreError> {
    let at = At::row("blacklist", row, "robot_id")?;
    Ok(BlacklistEntry {
        robot_id: at.id_column(row, "robot_id")?,
        cell: at.cell(row, "cell_x", "cell_y")?,
        cause: at.get(row, "cause")?,
        created_at: at.timestamp(row, "created_at")?,
    })
}

pub(super) fn region_from_row(row: &impl Columns) -> Result<Region, StoreError> {
    let at = At::row("forbidden_regions", row, "id")?;
    let (min, max) = (at.point(row, "min_x", "min_y")?, at.point(row, "max_x", "max_y")?);
    if min.x >= max.x || min.y >= max.y {
        return Err(at.bad("min_x, min_y must lie below max_x, max_y"));
    }
    Ok(Region {
        id: at.id_column(row, "id")?,
        mission_id: at.id_column(row, "mission_id")?,
        min,
        max,
        actor: at.get(row, "actor")?,
        reason: at.get(row, "reason")?,
        created_at: at.timestamp(row, "created_at")?,
    })
}

pub(super) fn event_from_row(row: &impl Columns) -> Result<MissionEvent, StoreError> {
    let at = At::row("mission_events", row, "id")?;
    Ok(MissionEvent {
        id: at.id_column(row, "id")?,
        mission_id: at.id_column(row, "mission_id")?,
        at: at.timestamp(row, "at")?,
        kind: at.get(row, "kind")?,
        detail: at.get(row, "detail")?,
        actor: at.get(row, "actor")?,
    })
}

/// Run-length encoding of labels: (label, run) pairs of little-endian u32.
/// The labels of `len` cells; runs that add up to anything else are refused
/// before anything is allocated for them.
fn decode_labels(at: At<'_>, bytes: &[u8], len: usize) -> Result<Vec<u32>, StoreError> {
    exploration_proto::label_runs::decode(bytes, len).map_err(|e| at.bad(format!("labels {e}")))
}

pub(super) fn rooms_from_row(row: &impl Columns, frame: GridFrame) -> Result<Rooms, StoreError> {
    let at = At::row("given_segmentations", row, "mission_id")?;
    Ok(decode_labels(at, &at.get::<Vec<u8>>(row, "label_runs")?, frame.len())?.into())
}

pub(super) fn segments_json(segmentation: &Segmentation) -> String {
    let segments: Vec<serde_json::Value> = segmentation
        .segments
        .iter()
        .map(|s| {
            serde_json::json!({
                "id": s.id,
                "cells": s.cells,
                "bounds": [s.bounds.x, s.bounds.y, s.bounds.width, s.bounds.height],
                "frontier": s.frontier.iter().map(|c| [c.x, c.y]).collect::<Vec<_>>(),
            })
        })
        .collect();
    serde_json::Value::Array(segments).to_string()
}

pub(super) fn critical_points_json(segmentation: &Segmentation) -> String {
    let points: Vec<serde_json::Value> =
        segmentation.critical_points.iter().map(|p| serde_json::json!([p.cell.x, p.cell.y, p.clearance])).collect();
    serde_json::Value::Array(points).to_string()
}

/// The segmentation of the mission whose grid is `frame`.
pub(super) fn segmentation_from_row(row: &impl Columns, frame: GridFrame) -> Result<StoredSegmentation, StoreError> {
    let at = At::row("segmentations", row, "mission_id")?;
    let bad = |what: &str| at.bad(what);
    let labels = decode_labels(at, &at.get::<Vec<u8>>(row, "labels")?, frame.len())?;
    let segments: serde_json::Value =
        serde_json::from_str(&at.get::<String>(row, "segments")?).map_err(|e| bad(&format!("segments: {e}")))?;
    let points: serde_json::Value = serde_json::from_str(&at.get::<String>(row, "critical_points")?)
        .map_err(|e| bad(&format!("critical_points: {e}")))?;
    let int = |v: &serde_json::Value, what: &str| v.as_i64().ok_or_else(|| bad(&format!("{what} is not an integer")));
    let small = |v: &serde_json::Value, what: &str| {
        i32::try_from(int(v, what)?).map_err(|_| bad(&format!("{what} is not a cell coordinate")))
    };
    let cell = |c: &serde_json::Value, what: &str| -> Result<Cell, StoreError> {
        let cell = Cell::new(small(&c[0], what)?, small(&c[1], what)?);
        if frame.contains(cell) { Ok(cell) } else { Err(bad(&format!("{what} {cell:?} is off the grid"))) }
    };
    let segments = segments
        .as_array()
        .ok_or_else(|| bad("segments is not an array"))?
        .iter()
        .map(|s| {
            let b = s["bounds"].as_array().filter(|b| b.len() == 4).ok_or_else(|| bad("segment bounds"))?;
            let side = |v: &serde_json::Value| {
                u32::try_from(int(v, "segment bounds")?).map_err(|_| bad("segment bounds are negative"))
            };
            let bounds = CellRect::new(
                small(&b[0], "segment bounds")?,
                small(&b[1], "segment bounds")?,
                side(&b[2])?,
                side(&b[3])?,
            );
            Ok(Segment {
                id: u32::try_from(int(&s["id"], "segment id")?).map_err(|_| bad("segment id"))?,
                cells: usize::try_from(int(&s["cells"], "segment cells")?).map_err(|_| bad("segment cells"))?,
                bounds: Some(bounds)
                    .filter(|b| frame.contains_rect(b))
                    .ok_or_else(|| bad("segment bounds leave the grid"))?,
                frontier: s["frontier"]
                    .as_array()
                    .ok_or_else(|| bad("segment frontier"))?
                    .iter()
                    .map(|c| cell(c, "segment frontier cell"))
                    .collect::<Result<_, StoreError>>()?,
            })
        })
        .collect::<Result<Vec<_>, StoreError>>()?;
    let critical_points = points
        .as_array()
        .ok_or_else(|| bad("critical_points is not an array"))?
        .iter()
        .map(|p| {
            Ok(CriticalPoint {
                cell: cell(p, "critical point")?,
                clearance: p[2].as_f64().filter(|c| c.is_finite()).ok_or_else(|| bad("critical point clearance"))?,
            })
        })
        .collect::<Result<Vec<_>, StoreError>>()?;
    Ok(StoredSegmentation {
        computed_at: at.timestamp(row, "computed_at")?,
        segmentation: Segmentation { frame, labels, segments, critical_points },
    })
}

/// `map_patches.cells_format`: little-endian f32 log-odds per cell, NaN for unknown.
const CELLS_RAW: i64 = 0;
/// `map_patches.cells_format`: [`CELLS_RAW`]'s bytes as one LZ4 block.
const CELLS_LZ4: i64 = 1;
/// `map_patches.cells_format`: the occupancy bytes the patch came as (ROS's
/// 0 to 100, 255 for unknown; see [`Patch::occupancy_percent`]) as one LZ4
/// block: a quarter of [`CELLS_RAW`] before compression, and they make the
/// same log-odds again.
const CELLS_PERCENT_LZ4: i64 = 2;

/// A patch's cells as written now, and their `cells_format`: the bytes the
/// patch came as when it came as bytes ([`CELLS_PERCENT_LZ4`]), its
/// log-odds otherwise ([`CELLS_LZ4`]).
pub(super) fn encode_cells(patch: &Patch) -> (Vec<u8>, i64) {
    if let Some(occupancy) = patch.occupancy_percent() {
        return (lz4_flex::block::compress(occupancy), CELLS_PERCENT_LZ4);
    }
    // Sized once and filled value by value: collecting a flat_map of the
    // four bytes grew the vector as it went (1 % of a map update's CPU).
    let mut raw = Vec::with_capacity(patch.log_odds().len() * 4);
    for v in patch.log_odds() {
        raw.extend_from_slice(&v.to_le_bytes());
    }
    (lz4_flex::block::compress(&raw), CELLS_LZ4)
}

/// The patch over `rect` whose cells are `stored` bytes in `format`.
fn decode_cells(at: &At, rect: CellRect, stored: Vec<u8>, format: i64) -> Result<Patch, StoreError> {
    let count = rect.area();
    let bytes_per_cell = if format == CELLS_PERCENT_LZ4 { 1 } else { 4 };
    let expected =
        usize::try_from(count * bytes_per_cell).map_err(|_| at.bad(format!("{count} cells do not fit in memory")))?;
    let raw = match format {
        CELLS_RAW => stored,
        CELLS_LZ4 | CELLS_PERCENT_LZ4 => {
            let mut raw = vec![0; expected];
            let written =
                lz4_flex::block::decompress_into(&stored, &mut raw).map_err(|e| at.bad(format!("cells: {e}")))?;
            raw.truncate(written);
            raw
        }
        other => {
            return Err(at.bad(format!(
                "cells_format {other} is none of {CELLS_RAW} (raw), {CELLS_LZ4} (LZ4) or {CELLS_PERCENT_LZ4} (occupancy bytes, LZ4)"
            )));
        }
    };
    if raw.len() != expected {
        return Err(at.bad(format!("cells holds {} bytes, not {bytes_per_cell} per cell of {count} cells", raw.len())));
    }
    let patch = if format == CELLS_PERCENT_LZ4 {
        Patch::from_occupancy_percent(rect, raw)
    } else {
        Patch::from_stored(rect, raw.chunks_exact(4).map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]])).collect())
    };
    patch.map_err(|e| at.bad(e))
}

/// An identity (1 and up) in column `column` of a row of `table`.
pub(super) fn identity(row: &impl Columns, table: &str, column: &str) -> Result<u64, StoreError> {
    At::row(table, row, column)?.id_column(row, column)
}

/// How many replicas are alive and how many missions they share.
pub(super) fn share_from_row(row: &impl Columns) -> Result<Share, StoreError> {
    let at = At { table: "replicas", id: 0 };
    Ok(Share { replicas: at.count(row, "replicas")?, missions: at.count(row, "missions")? })
}

/// A mission's lease.
pub(super) fn lease_from_row(row: &impl Columns) -> Result<Lease, StoreError> {
    let at = At::row("mission_leases", row, "mission_id")?;
    Ok(Lease {
        mission_id: at.id_column(row, "mission_id")?,
        owner: at.get(row, "owner")?,
        address: at.get(row, "address")?,
        token: at.id_column(row, "token")?,
        expires_at: at.timestamp(row, "expires_at")?,
    })
}

/// Every robot's token hash: 64 lower-case hex digits.
pub(super) fn token_from_row(row: &impl Columns) -> Result<(RobotId, String), StoreError> {
    let at = At::row("robots", row, "id")?;
    let hash: String = at.get(row, "token_sha256")?;
    if hash.len() != 64 || !hash.bytes().all(|b| b.is_ascii_digit() || (b'a'..=b'f').contains(&b)) {
        return Err(at.bad("token_sha256 is not a SHA-256 in hex"));
    }
    Ok((at.id_column(row, "id")?, hash))
}
