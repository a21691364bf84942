//! What a robot sends: a rectangle of its own map, checked cell by cell
//! and turned into log-odds, whichever of the three forms it came in
//! (probabilities, log-odds, or ROS's occupancy bytes).

use super::{LOG_ODDS_MAX, LOG_ODDS_MIN, log_odds_from_probability};
use crate::grid::{CellRect, GridFrame};

/// Why a patch cannot be applied.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum PatchError {
    /// Width or height is zero.
    #[error("the patch rectangle is empty ({width}×{height} cells); width and height must be at least 1")]
    Empty {
        /// Columns given.
        width: u32,
        /// Rows given.
        height: u32,
    },
    /// The rectangle leaves the grid.
    #[error(
        "the patch covers cells x {x}..{x_end}, y {y}..{y_end}, outside the {grid_width}×{grid_height} mission grid"
    )]
    OutsideGrid {
        /// Leftmost column of the patch.
        x: i64,
        /// One past its rightmost column.
        x_end: i64,
        /// Bottom row of the patch.
        y: i64,
        /// One past its top row.
        y_end: i64,
        /// Columns of the grid.
        grid_width: u32,
        /// Rows of the grid.
        grid_height: u32,
    },
    /// The number of values is not width × height.
    #[error("the patch is {width}×{height} = {expected} cells but carries {got} values")]
    ValueCount {
        /// Columns.
        width: u32,
        /// Rows.
        height: u32,
        /// width × height.
        expected: u64,
        /// Values present.
        got: usize,
    },
    /// The unknown mask is neither empty nor one byte per cell.
    #[error("the unknown mask has {got} bytes; send none, or one per cell ({expected})")]
    UnknownMaskLength {
        /// width × height.
        expected: u64,
        /// Bytes present.
        got: usize,
    },
    /// A known cell's value is NaN or infinite.
    #[error("value {index} of the patch is {value}, which is not a finite number")]
    NotFinite {
        /// Row-major position inside the patch.
        index: usize,
        /// The offending value.
        value: f32,
    },
    /// A stored log-odds value outside the clamp range.
    #[error("stored value {index} of the patch is {value}, outside the log-odds range the executive writes")]
    StoredOutOfRange {
        /// Row-major position inside the patch.
        index: usize,
        /// The offending value.
        value: f32,
    },
    /// A probability outside [0, 1].
    #[error("value {index} of the patch is {value}, outside the probability range [0, 1]")]
    ProbabilityOutOfRange {
        /// Row-major position inside the patch.
        index: usize,
        /// The offending value.
        value: f32,
    },
    /// An occupancy byte that is neither a percentage nor unknown.
    #[error("occupancy byte {index} of the patch is {value}; send 0 to 100 (percent), or 255 (-1) for unknown")]
    PercentOutOfRange {
        /// Row-major position inside the patch.
        index: usize,
        /// The offending byte.
        value: u8,
    },
}

/// The occupancy byte of a cell the robot does not know (ROS's -1).
pub const UNKNOWN_PERCENT: u8 = 255;

/// The log-odds of each occupancy byte: for a percentage, those of the
/// probability `percent / 100`, clamped as every patch is, so that a cell
/// sent as a percentage fuses exactly as the same probability sent as a
/// float; NaN for [`UNKNOWN_PERCENT`] (and for the bytes that are neither,
/// which [`Patch::from_occupancy_percent`] refuses before reading it).
static LOG_ODDS_OF_BYTE: std::sync::LazyLock<[f32; 256]> = std::sync::LazyLock::new(|| {
    std::array::from_fn(|b| match b {
        0..=100 => log_odds_from_probability(b as f32 / 100.0).clamp(LOG_ODDS_MIN, LOG_ODDS_MAX),
        _ => f32::NAN,
    })
});

/// A validated rectangle of one robot's map, in log-odds.
#[derive(Debug, Clone, PartialEq)]
pub struct Patch {
    rect: CellRect,
    /// Log-odds per cell; NaN marks a cell the robot does not know.
    log_odds: Vec<f32>,
    /// The occupancy bytes the patch was made from, when it came as ROS
    /// sends a map: they make it again exactly, in a quarter of the space.
    occupancy_percent: Option<Vec<u8>>,
}

impl Patch {
    /// A patch of occupancy probabilities; `unknown` is empty or one flag per cell.
    pub fn from_probabilities(rect: CellRect, values: &[f32], unknown: &[bool]) -> Result<Self, PatchError> {
        Self::build(rect, values, unknown, |index, value| {
            if !value.is_finite() {
                Err(PatchError::NotFinite { index, value })
            } else if !(0.0..=1.0).contains(&value) {
                Err(PatchError::ProbabilityOutOfRange { index, value })
            } else {
                Ok(log_odds_from_probability(value))
            }
        })
    }

    /// A patch of occupancy percentages, one byte per cell as ROS's
    /// `nav_msgs/OccupancyGrid` holds them: 0 to 100, or [`UNKNOWN_PERCENT`].
    /// A table lookup per cell, where probabilities take a logarithm.
    /// The patch keeps `occupancy` (see [`Self::occupancy_percent`]), so it
    /// is taken, not copied.
    pub fn from_occupancy_percent(rect: CellRect, occupancy: Vec<u8>) -> Result<Self, PatchError> {
        Self::check_count(rect, occupancy.len())?;
        if let Some(index) = occupancy.iter().position(|&v| v > 100 && v != UNKNOWN_PERCENT) {
            return Err(PatchError::PercentOutOfRange { index, value: occupancy[index] });
        }
        // Every byte valid, the lookup needs no branch, and the vector is
        // sized once.
        let table = &*LOG_ODDS_OF_BYTE;
        let log_odds = occupancy.iter().map(|&v| table[usize::from(v)]).collect();
        Ok(Self { rect, log_odds, occupancy_percent: Some(occupancy) })
    }

    /// A patch of log-odds; `unknown` is empty or one flag per cell.
    pub fn from_log_odds(rect: CellRect, values: &[f32], unknown: &[bool]) -> Result<Self, PatchError> {
        Self::build(rect, values, unknown, |index, value| {
            if value.is_finite() { Ok(value) } else { Err(PatchError::NotFinite { index, value }) }
        })
    }

    /// Rebuilds a patch from its stored log-odds (NaN = unknown), as written by
    /// [`Patch::log_odds`]. Each value must be unknown or within the clamp
    /// range, as written.
    pub fn from_stored(rect: CellRect, log_odds: Vec<f32>) -> Result<Self, PatchError> {
        if let Some((index, &value)) =
            log_odds.iter().enumerate().find(|(_, v)| !v.is_nan() && !(LOG_ODDS_MIN..=LOG_ODDS_MAX).contains(*v))
        {
            return Err(PatchError::StoredOutOfRange { index, value });
        }
        Self::check_count(rect, log_odds.len())?;
        Ok(Self { rect, log_odds, occupancy_percent: None })
    }

    /// Cells of a layer the fusion holds: checked and clamped when they came in.
    pub(super) fn of_layer(rect: CellRect, log_odds: Vec<f32>) -> Self {
        Self { rect, log_odds, occupancy_percent: None }
    }

    fn build(
        rect: CellRect,
        values: &[f32],
        unknown: &[bool],
        convert: impl Fn(usize, f32) -> Result<f32, PatchError>,
    ) -> Result<Self, PatchError> {
        Self::check_count(rect, values.len())?;
        let expected = rect.area();
        if !unknown.is_empty() && unknown.len() as u64 != expected {
            return Err(PatchError::UnknownMaskLength { expected, got: unknown.len() });
        }
        let mut log_odds = Vec::with_capacity(values.len());
        for (index, &value) in values.iter().enumerate() {
            log_odds.push(if unknown.get(index).copied().unwrap_or(false) {
                f32::NAN
            } else {
                convert(index, value)?.clamp(LOG_ODDS_MIN, LOG_ODDS_MAX)
            });
        }
        Ok(Self { rect, log_odds, occupancy_percent: None })
    }

    /// Checks that `rect` is not empty and that `got` values cover it.
    fn check_count(rect: CellRect, got: usize) -> Result<(), PatchError> {
        if rect.width == 0 || rect.height == 0 {
            return Err(PatchError::Empty { width: rect.width, height: rect.height });
        }
        let expected = rect.area();
        if got as u64 != expected {
            return Err(PatchError::ValueCount { width: rect.width, height: rect.height, expected, got });
        }
        Ok(())
    }

    /// The rectangle of the mission grid this patch covers.
    pub fn rect(&self) -> CellRect {
        self.rect
    }

    /// Log-odds per cell, row-major; NaN where the robot does not know the cell.
    pub fn log_odds(&self) -> &[f32] {
        &self.log_odds
    }

    /// The ROS occupancy bytes (0 to 100, [`UNKNOWN_PERCENT`]) the patch was
    /// made from, if it was: [`Self::from_occupancy_percent`] on them gives
    /// this patch again, bit for bit.
    pub fn occupancy_percent(&self) -> Option<&[u8]> {
        self.occupancy_percent.as_deref()
    }

    /// Number of cells the robot knows.
    pub fn known_cells(&self) -> usize {
        self.log_odds.iter().filter(|l| !l.is_nan()).count()
    }

    /// Checks that the patch lies inside `frame`.
    pub fn check_inside(&self, frame: &GridFrame) -> Result<(), PatchError> {
        if frame.contains_rect(&self.rect) {
            Ok(())
        } else {
            Err(PatchError::OutsideGrid {
                x: i64::from(self.rect.x),
                x_end: i64::from(self.rect.x) + i64::from(self.rect.width),
                y: i64::from(self.rect.y),
                y_end: i64::from(self.rect.y) + i64::from(self.rect.height),
                grid_width: frame.width,
                grid_height: frame.height,
            })
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Every percentage fuses bit for bit as the probability `p / 100`
    /// sent as a float, and 255 as a cell under the unknown mask.
    #[test]
    fn occupancy_bytes_are_the_probabilities_they_name() {
        let rect = CellRect::new(3, 4, 102, 1);
        let bytes: Vec<u8> = (0..=100).chain([UNKNOWN_PERCENT]).collect();
        let floats: Vec<f32> = (0..=100).map(|p| p as f32 / 100.0).chain([0.0]).collect();
        let mut unknown = vec![false; 102];
        unknown[101] = true;
        let from_bytes = Patch::from_occupancy_percent(rect, bytes.clone()).unwrap();
        let from_floats = Patch::from_probabilities(rect, &floats, &unknown).unwrap();
        assert_eq!(from_bytes.rect(), from_floats.rect());
        for (i, (a, b)) in from_bytes.log_odds().iter().zip(from_floats.log_odds()).enumerate() {
            assert_eq!(a.to_bits(), b.to_bits(), "byte {i}: {a} against {b}");
        }
        assert_eq!(from_bytes.known_cells(), 101);
        // The bytes are kept, so that a store can keep them instead.
        assert_eq!(from_bytes.occupancy_percent(), Some(&bytes[..]));
        assert_eq!(from_floats.occupancy_percent(), None);
    }

    #[test]
    fn occupancy_bytes_that_are_no_percentage_are_refused() {
        let rect = CellRect::new(0, 0, 2, 2);
        assert_eq!(
            Patch::from_occupancy_percent(rect, vec![0, 100, 101, 255]),
            Err(PatchError::PercentOutOfRange { index: 2, value: 101 })
        );
        assert_eq!(
            Patch::from_occupancy_percent(rect, vec![0, 254, 0, 0]),
            Err(PatchError::PercentOutOfRange { index: 1, value: 254 })
        );
        assert!(matches!(
            Patch::from_occupancy_percent(rect, vec![0; 3]),
            Err(PatchError::ValueCount { expected: 4, got: 3, .. })
        ));
        assert!(matches!(
            Patch::from_occupancy_percent(CellRect::new(0, 0, 2, 0), vec![]),
            Err(PatchError::Empty { .. })
        ));
    }

    #[test]
    fn invalid_patches_are_refused_with_the_reason() {
        let rect = CellRect::new(0, 0, 2, 2);
        assert!(matches!(
            Patch::from_probabilities(rect, &[0.5; 3], &[]),
            Err(PatchError::ValueCount { expected: 4, got: 3, .. })
        ));
        assert!(matches!(
            Patch::from_probabilities(rect, &[0.5, f32::NAN, 0.5, 0.5], &[]),
            Err(PatchError::NotFinite { index: 1, .. })
        ));
        assert!(matches!(
            Patch::from_probabilities(rect, &[0.5, 0.5, 1.5, 0.5], &[]),
            Err(PatchError::ProbabilityOutOfRange { index: 2, .. })
        ));
        assert!(matches!(
            Patch::from_log_odds(rect, &[0.5, 0.5, 0.5, f32::INFINITY], &[]),
            Err(PatchError::NotFinite { index: 3, .. })
        ));
        assert!(matches!(
            Patch::from_probabilities(rect, &[0.5; 4], &[true]),
            Err(PatchError::UnknownMaskLength { .. })
        ));
        assert!(matches!(
            Patch::from_probabilities(CellRect::new(0, 0, 0, 2), &[], &[]),
            Err(PatchError::Empty { .. })
        ));
        // A NaN under the unknown mask is ignored.
        assert!(Patch::from_probabilities(rect, &[0.5, f32::NAN, 0.5, 0.5], &[false, true, false, false]).is_ok());
    }
}
