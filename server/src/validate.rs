//! The limits every value must meet, wherever it comes from.
//!
//! A value is checked the same way whether it arrives in a request or is read
//! back from the database: the service turns an [`Invalid`] into
//! INVALID_ARGUMENT naming the field, the store into an error naming the
//! table, the row and the field, so that a bad row stops the start instead of
//! panicking (or allocating a petabyte) later.

use std::time::Duration;

use exploration::grid::GridFrame;
use exploration::math::{Point2, ShortNumber};
use exploration::policy::Capabilities;

/// Longest side of a mission grid, cells.
pub const MAX_GRID_SIDE: u32 = 20_000;
/// Most cells in one mission grid.
pub const MAX_GRID_CELLS: u64 = 25_000_000;
/// Longest robot, mission or operator name, characters.
pub const MAX_NAME_CHARS: usize = 128;
/// Longest free-text reason or note, characters (longer ones are cut).
pub const MAX_REASON_CHARS: usize = 500;
/// Most forbidden regions one mission holds: every replanning checks each
/// frontier cell against each region, and every answer about the mission
/// lists them.
pub const MAX_FORBIDDEN_REGIONS: usize = 1_000;
/// Farthest a map's origin may lie from the world's, metres (UTM northings
/// reach 10⁷ m; beyond 10⁸ m a cell of 1 cm cannot be told apart in f64).
pub const MAX_COORDINATE_M: f64 = 1e8;

/// A value outside its limits: which field, and what is wrong with it.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{field} {problem}")]
pub struct Invalid {
    /// The field, as the client or the database names it.
    pub field: String,
    /// What is wrong and what is allowed.
    pub problem: String,
}

impl Invalid {
    /// `field` is wrong because of `problem`.
    pub fn new(field: impl Into<String>, problem: impl Into<String>) -> Self {
        Self { field: field.into(), problem: problem.into() }
    }
}

/// A finite number.
pub fn finite(value: f64, field: &str) -> Result<f64, Invalid> {
    if value.is_finite() {
        Ok(value)
    } else {
        Err(Invalid::new(field, format!("is {}; it must be a finite number", ShortNumber(value))))
    }
}

/// A number in `[min, max]` (NaN is not).
pub fn in_range(value: f64, field: &str, min: f64, max: f64, unit: &str) -> Result<f64, Invalid> {
    if value >= min && value <= max {
        Ok(value)
    } else {
        let unit = if unit.is_empty() { String::new() } else { format!(" {unit}") };
        let (value, min, max) = (ShortNumber(value), ShortNumber(min), ShortNumber(max));
        Err(Invalid::new(field, format!("is {value}; it must lie in [{min}, {max}]{unit}")))
    }
}

/// A world coordinate, metres.
pub fn coordinate(value: f64, field: &str) -> Result<f64, Invalid> {
    in_range(finite(value, field)?, field, -MAX_COORDINATE_M, MAX_COORDINATE_M, "metres")
}

/// A count read back as a signed integer.
pub fn count(value: i64, field: &str) -> Result<u64, Invalid> {
    u64::try_from(value).map_err(|_| Invalid::new(field, format!("is {value}; it must not be negative")))
}

/// A duration in seconds within `[min, max]`.
pub fn seconds(value: f64, field: &str, min: f64, max: f64) -> Result<Duration, Invalid> {
    Ok(Duration::from_secs_f64(in_range(value, field, min, max, "seconds")?))
}

/// A name: trimmed, 1 to [`MAX_NAME_CHARS`] characters, no control
/// characters (a newline in a name would forge lines in a text log).
pub fn name(value: &str, field: &str) -> Result<String, Invalid> {
    let trimmed = value.trim();
    if trimmed.is_empty() {
        return Err(Invalid::new(field, format!("is empty; give a name of 1 to {MAX_NAME_CHARS} characters")));
    }
    if trimmed.chars().count() > MAX_NAME_CHARS {
        return Err(Invalid::new(field, format!("is longer than {MAX_NAME_CHARS} characters")));
    }
    if let Some(c) = trimmed.chars().find(|c| c.is_control()) {
        return Err(Invalid::new(field, format!("contains the control character {c:?}; names are printable text")));
    }
    Ok(trimmed.to_owned())
}

/// Free text (a reason, a note): trimmed, control characters but tabs
/// replaced by spaces, cut to [`MAX_REASON_CHARS`] characters.
pub fn free_text(value: &str) -> String {
    value.trim().chars().take(MAX_REASON_CHARS).map(|c| if c.is_control() { ' ' } else { c }).collect()
}

/// A grid size side read back from a wide integer.
fn side(value: i64, field: &str) -> Result<u32, Invalid> {
    match u32::try_from(value) {
        Ok(v) if (1..=MAX_GRID_SIDE).contains(&v) => Ok(v),
        _ => Err(Invalid::new(field, format!("is {value} cells; it must lie in [1, {MAX_GRID_SIDE}]"))),
    }
}

/// A mission's grid frame; `prefix` names the message or table it is part of.
pub fn frame(resolution: f64, origin: Point2, width: i64, height: i64, prefix: &str) -> Result<GridFrame, Invalid> {
    let resolution = in_range(resolution, &format!("{prefix}resolution"), 0.01, 10.0, "metres per cell")?;
    let origin = Point2::new(
        coordinate(origin.x, &format!("{prefix}origin.x"))?,
        coordinate(origin.y, &format!("{prefix}origin.y"))?,
    );
    let width = side(width, &format!("{prefix}width"))?;
    let height = side(height, &format!("{prefix}height"))?;
    let cells = u64::from(width) * u64::from(height);
    if cells > MAX_GRID_CELLS {
        return Err(Invalid::new(
            format!("{prefix}width × {prefix}height"),
            format!("is {width}×{height} = {cells} cells; at most {MAX_GRID_CELLS} are allowed (use coarser cells)"),
        ));
    }
    Ok(GridFrame::new(resolution, origin, width, height))
}

/// A point on a mission's map.
pub fn on_map(point: Point2, frame: &GridFrame, field: &str) -> Result<Point2, Invalid> {
    let point = Point2::new(finite(point.x, &format!("{field}.x"))?, finite(point.y, &format!("{field}.y"))?);
    if frame.cell_from_world(&point).is_none() {
        return Err(Invalid::new(field, outside_map(point, frame)));
    }
    Ok(point)
}

/// Why `point` is refused: it lies off `frame`, which spans what it spans.
pub fn outside_map(point: Point2, frame: &GridFrame) -> String {
    let spans = |origin: f64, cells: u32| (Metres(origin), Metres(origin + f64::from(cells) * frame.resolution));
    let ((x0, x1), (y0, y1)) = (spans(frame.origin.x, frame.width), spans(frame.origin.y, frame.height));
    format!("{} lies outside the mission map, which spans x {x0}..{x1}, y {y0}..{y1}", Place(point))
}

/// Metres for a message: three decimals, or scientific notation where a
/// careless client's 1e308 would take three hundred digits.
#[derive(Debug, Clone, Copy)]
pub struct Metres(pub f64);

impl std::fmt::Display for Metres {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        if self.0.abs() < 1e9 { write!(f, "{:.3}", self.0) } else { write!(f, "{:e}", self.0) }
    }
}

/// A point for a message, `(x, y)` in [`Metres`].
#[derive(Debug, Clone, Copy)]
pub struct Place(pub Point2);

impl std::fmt::Display for Place {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "({}, {})", Metres(self.0.x), Metres(self.0.y))
    }
}

/// A robot's capabilities; `prefix` names the message or table.
pub fn capabilities(c: Capabilities, prefix: &str) -> Result<Capabilities, Invalid> {
    let positive = |v: f64, field: &str, max: f64, unit: &str| {
        if v > 0.0 && v <= max {
            Ok(v)
        } else {
            Err(Invalid::new(
                format!("{prefix}{field}"),
                format!("is {}; it must lie in (0, {max}] {unit}", ShortNumber(v)),
            ))
        }
    };
    Ok(Capabilities {
        sensor_range_m: positive(c.sensor_range_m, "sensor_range_m", 100.0, "metres")?,
        field_of_view_rad: positive(c.field_of_view_rad, "field_of_view_rad", std::f64::consts::TAU, "radians")?,
        speed_mps: positive(c.speed_mps, "speed_mps", 100.0, "metres per second")?,
        footprint_radius_m: in_range(
            c.footprint_radius_m,
            &format!("{prefix}footprint_radius_m"),
            0.0,
            10.0,
            "metres",
        )?,
    })
}

/// Limits of the replanning settings: (distance m, interval s, frontier share).
pub const REPLAN_DISTANCE_M: (f64, f64) = (0.01, 1e6);
/// See [`REPLAN_DISTANCE_M`].
pub const REPLAN_INTERVAL_S: (f64, f64) = (0.001, 1e6);
/// Limits of lease and stall times, seconds.
pub const LIFECYCLE_S: (f64, f64) = (0.1, 86_400.0);

#[cfg(test)]
mod tests {
    use super::*;

    /// A careless client's 1e308 m is named in a dozen characters, not three
    /// hundred digits; ordinary points keep their millimetres.
    #[test]
    fn points_refused_are_named_briefly() {
        let frame = GridFrame::new(0.1, Point2::new(-1.0, 2.0), 30, 40);
        let far = on_map(Point2::new(1e308, 5.0), &frame, "goto").unwrap_err();
        assert_eq!(far.field, "goto");
        assert_eq!(
            far.problem,
            "(1e308, 5.000) lies outside the mission map, which spans x -1.000..2.000, y 2.000..6.000"
        );
        assert_eq!(Place(Point2::new(-0.0625, 12.5)).to_string(), "(-0.062, 12.500)");
        assert_eq!(Metres(-2.5e9).to_string(), "-2.5e9");
    }

    #[test]
    fn names_are_printable_and_bounded() {
        assert_eq!(name("  robot-1 ", "name").unwrap(), "robot-1");
        for bad in ["", "   ", "a\nb", "a\rb", "a\0b", "tab\there", &"x".repeat(129)] {
            let err = name(bad, "name").unwrap_err();
            assert_eq!(err.field, "name", "{bad:?}");
        }
        assert_eq!(name(&"é".repeat(128), "name").unwrap().chars().count(), 128);
        assert_eq!(free_text(" line\nforged\r "), "line forged");
        assert_eq!(free_text(&"y".repeat(10_000)).len(), MAX_REASON_CHARS);
    }

    #[test]
    fn frames_refuse_what_would_wrap_or_exhaust_memory() {
        let at = Point2::new(1.0, 2.0);
        assert!(frame(0.05, at, 100, 80, "frame.").is_ok());
        let cases = [
            (0.05, at, 0, 80, "frame.width"),
            (0.05, at, (1 << 32) + 1, 1, "frame.width"),
            (0.05, at, -3, 1, "frame.width"),
            (0.05, at, 20_000, 20_000, "frame.width × frame.height"),
            (f64::NAN, at, 10, 10, "frame.resolution"),
            (0.0, at, 10, 10, "frame.resolution"),
            (0.05, Point2::new(1e308, 0.0), 10, 10, "frame.origin.x"),
            (0.05, Point2::new(0.0, f64::NEG_INFINITY), 10, 10, "frame.origin.y"),
        ];
        for (resolution, origin, width, height, field) in cases {
            let err = frame(resolution, origin, width, height, "frame.").unwrap_err();
            assert_eq!(err.field, field, "{err}");
        }
    }

    #[test]
    fn durations_and_counts_refuse_what_would_panic() {
        assert!(seconds(-1.0, "lease_s", 0.1, 10.0).is_err());
        // Named in a few characters, not three hundred digits.
        assert_eq!(
            seconds(1e300, "lease_s", 0.1, 10.0).unwrap_err().problem,
            "is 1e300; it must lie in [0.1, 10] seconds"
        );
        let cost = in_range(-1e-300, "bids[0].path_cost", 0.0, f64::MAX, "").unwrap_err();
        assert_eq!(cost.problem, "is -1e-300; it must lie in [0, 1.7976931348623157e308]");
        assert!(seconds(f64::NAN, "lease_s", 0.1, 10.0).is_err());
        assert_eq!(seconds(2.5, "lease_s", 0.1, 10.0).unwrap(), Duration::from_millis(2500));
        assert!(count(-1, "replans").is_err());
        assert_eq!(count(7, "replans").unwrap(), 7);
    }
}
