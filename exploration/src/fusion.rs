//! Fusing robots' occupancy-grid patches into one mission grid.
//!
//! Robots send patches of their *own* maps, which already accumulate their
//! past measurements. Adding every patch into one grid would integrate the
//! same measurement again each time a robot resends a cell, the mistake
//! Burgard et al. 2005, §III warn against. So the fusion keeps one layer per
//! robot, where a new patch *replaces* that robot's earlier values, and the
//! fused value of a cell is the sum of the layers' log-odds (independent
//! opinions pooled, the alternative Burgard et al. §III describe: "each robot
//! maintains an individual map for each other robot ... combined to a joint
//! map"). Log-odds are clamped to [logit 0.12, logit 0.97] as in OctoMap
//! (Hornung et al. 2013), so that no cell becomes too certain to change.

use std::collections::BTreeMap;

use crate::grid::{CellRect, GridFrame, OccupancyGrid, UNKNOWN, percent_from_probability};

/// Which robot a layer belongs to.
pub type LayerId = u64;

/// Lowest log-odds a cell may hold: P(occ) = 0.12.
pub const LOG_ODDS_MIN: f32 = -1.992_430_1;
/// Highest log-odds a cell may hold: P(occ) = 0.97.
pub const LOG_ODDS_MAX: f32 = 3.476_099_6;

/// ln(p / (1 - p)).
pub fn log_odds_from_probability(p: f32) -> f32 {
    let p = p.clamp(1e-6, 1.0 - 1e-6);
    (p / (1.0 - p)).ln()
}

/// 1 / (1 + e^-l).
pub fn probability_from_log_odds(l: f32) -> f32 {
    1.0 / (1.0 + (-l).exp())
}

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
}

/// A validated rectangle of one robot's map, in log-odds.
#[derive(Debug, Clone, PartialEq)]
pub struct Patch {
    rect: CellRect,
    /// Log-odds per cell; NaN marks a cell the robot does not know.
    log_odds: Vec<f32>,
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
        if rect.width == 0 || rect.height == 0 {
            return Err(PatchError::Empty { width: rect.width, height: rect.height });
        }
        if log_odds.len() as u64 != rect.area() {
            return Err(PatchError::ValueCount {
                width: rect.width,
                height: rect.height,
                expected: rect.area(),
                got: log_odds.len(),
            });
        }
        Ok(Self { rect, log_odds })
    }

    fn build(
        rect: CellRect,
        values: &[f32],
        unknown: &[bool],
        convert: impl Fn(usize, f32) -> Result<f32, PatchError>,
    ) -> Result<Self, PatchError> {
        if rect.width == 0 || rect.height == 0 {
            return Err(PatchError::Empty { width: rect.width, height: rect.height });
        }
        let expected = rect.area();
        if values.len() as u64 != expected {
            return Err(PatchError::ValueCount { width: rect.width, height: rect.height, expected, got: values.len() });
        }
        if !unknown.is_empty() && unknown.len() as u64 != expected {
            return Err(PatchError::UnknownMaskLength { expected, got: unknown.len() });
        }
        let log_odds = values
            .iter()
            .enumerate()
            .map(|(index, &value)| {
                if unknown.get(index).copied().unwrap_or(false) {
                    Ok(f32::NAN)
                } else {
                    convert(index, value).map(|l| l.clamp(LOG_ODDS_MIN, LOG_ODDS_MAX))
                }
            })
            .collect::<Result<Vec<_>, _>>()?;
        Ok(Self { rect, log_odds })
    }

    /// The rectangle of the mission grid this patch covers.
    pub fn rect(&self) -> CellRect {
        self.rect
    }

    /// Log-odds per cell, row-major; NaN where the robot does not know the cell.
    pub fn log_odds(&self) -> &[f32] {
        &self.log_odds
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

const TILE_SHIFT: u32 = 5;
const TILE: usize = 1 << TILE_SHIFT;

/// One robot's map as the executive last heard it: sparse square tiles of
/// log-odds, NaN for cells the robot never reported.
#[derive(Debug, Clone, Default)]
struct Layer {
    tiles: Vec<Option<Box<[f32]>>>,
}

/// What applying a patch changed in the fused grid.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct FusionChange {
    /// Bounding rectangle of the cells whose fused value changed.
    pub changed: Option<CellRect>,
    /// Cells whose fused value changed.
    pub changed_cells: u64,
    /// Cells that were unknown before.
    pub newly_known: u64,
}

/// The mission's fused grid and every robot's layer behind it.
#[derive(Debug, Clone)]
pub struct MapFusion {
    frame: GridFrame,
    tiles_x: usize,
    tiles_y: usize,
    /// Σ of the layers' log-odds per cell.
    sum: Vec<f32>,
    /// How many layers know each cell.
    observers: Vec<u16>,
    layers: BTreeMap<LayerId, Layer>,
    grid: OccupancyGrid,
}

impl MapFusion {
    /// An empty fusion: every cell unknown.
    pub fn new(frame: GridFrame) -> Self {
        let tiles_x = (frame.width as usize).div_ceil(TILE);
        let tiles_y = (frame.height as usize).div_ceil(TILE);
        Self {
            frame,
            tiles_x,
            tiles_y,
            sum: vec![0.0; frame.len()],
            observers: vec![0; frame.len()],
            layers: BTreeMap::new(),
            grid: OccupancyGrid::unknown(frame),
        }
    }

    /// The grid frame.
    pub fn frame(&self) -> &GridFrame {
        &self.frame
    }

    /// The fused grid.
    pub fn grid(&self) -> &OccupancyGrid {
        &self.grid
    }

    /// Replaces `layer`'s values in the patch's rectangle by the patch's known
    /// cells, and updates the fused grid. Cells the patch marks unknown keep
    /// the layer's earlier value: "unknown" means "no news", never "forget".
    pub fn apply(&mut self, layer: LayerId, patch: &Patch) -> Result<FusionChange, PatchError> {
        patch.check_inside(&self.frame)?;
        let (tiles_x, tiles_y) = (self.tiles_x, self.tiles_y);
        let layer = self.layers.entry(layer).or_insert_with(|| Layer { tiles: vec![None; tiles_x * tiles_y] });
        let rect = patch.rect();
        let width = self.frame.width as usize;
        let mut change = FusionChange::default();
        let mut changed_rect: Option<CellRect> = None;
        let mut values = patch.log_odds().iter();
        for y in rect.y..rect.y_end() {
            for x in rect.x..rect.x_end() {
                let Some(&new) = values.next() else { unreachable!("a validated patch has one value per cell") };
                if new.is_nan() {
                    continue;
                }
                let (x, y) = (x as usize, y as usize);
                let tile_index = (y >> TILE_SHIFT) * tiles_x + (x >> TILE_SHIFT);
                let tile =
                    layer.tiles[tile_index].get_or_insert_with(|| vec![f32::NAN; TILE * TILE].into_boxed_slice());
                let slot = &mut tile[(y & (TILE - 1)) * TILE + (x & (TILE - 1))];
                let old = *slot;
                if old == new {
                    continue;
                }
                *slot = new;
                let i = y * width + x;
                if old.is_nan() {
                    self.observers[i] += 1;
                    self.sum[i] += new;
                } else {
                    self.sum[i] += new - old;
                }
                let fused = fused_percent(self.sum[i]);
                let before = self.grid.value_at(i);
                if before != fused {
                    let cell = crate::grid::Cell::new(x as i32, y as i32);
                    self.grid.set(cell, fused);
                    change.changed_cells += 1;
                    if before == UNKNOWN {
                        change.newly_known += 1;
                    }
                    changed_rect = Some(match changed_rect {
                        Some(r) => r.including(cell),
                        None => CellRect::new(cell.x, cell.y, 1, 1),
                    });
                }
            }
        }
        change.changed = changed_rect;
        Ok(change)
    }

    /// The grid as the given layers alone know it: per cell, the value of
    /// the most confident of them. Used when robots send their whole
    /// knowledge (their own measurements and what peers told them), where
    /// summing layers would count a shared measurement once per robot that
    /// holds it (Burgard et al. 2005, §III).
    ///
    /// Complexity: O(cells of the layers' tiles).
    pub fn grid_of(&self, layers: &[LayerId]) -> OccupancyGrid {
        let mut best = vec![f32::NAN; self.frame.len()];
        let width = self.frame.width as usize;
        for id in layers {
            let Some(layer) = self.layers.get(id) else { continue };
            for (t, tile) in layer.tiles.iter().enumerate() {
                let Some(tile) = tile else { continue };
                let (tx, ty) = ((t % self.tiles_x) * TILE, (t / self.tiles_x) * TILE);
                for (k, &v) in tile.iter().enumerate() {
                    if v.is_nan() {
                        continue;
                    }
                    let (x, y) = (tx + (k & (TILE - 1)), ty + (k >> TILE_SHIFT));
                    if x >= width || y >= self.frame.height as usize {
                        continue;
                    }
                    let slot = &mut best[y * width + x];
                    if slot.is_nan() || v.abs() > slot.abs() {
                        *slot = v;
                    }
                }
            }
        }
        let cells = best.iter().map(|&v| if v.is_nan() { UNKNOWN } else { fused_percent(v) }).collect();
        OccupancyGrid::from_cells(self.frame, cells)
    }

    /// Number of layers (robots that sent at least one patch).
    pub fn layer_count(&self) -> usize {
        self.layers.len()
    }

    /// How many robots know a cell.
    pub fn observers(&self, index: usize) -> u16 {
        self.observers[index]
    }
}

/// The stored value of a cell with log-odds sum `sum`.
fn fused_percent(sum: f32) -> u8 {
    percent_from_probability(probability_from_log_odds(sum.clamp(LOG_ODDS_MIN, LOG_ODDS_MAX)))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::grid::{Cell, CellClass};
    use crate::math::Point2;

    fn frame() -> GridFrame {
        GridFrame::new(0.1, Point2::origin(), 70, 40)
    }

    fn patch(rect: CellRect, p: f32) -> Patch {
        Patch::from_probabilities(rect, &vec![p; rect.area() as usize], &[]).unwrap()
    }

    #[test]
    fn resending_the_same_cells_does_not_double_count() {
        let mut fusion = MapFusion::new(frame());
        let p = patch(CellRect::new(0, 0, 3, 3), 0.9);
        let first = fusion.apply(1, &p).unwrap();
        assert_eq!(first.newly_known, 9);
        let value = fusion.grid().value(Cell::new(1, 1));
        let again = fusion.apply(1, &p).unwrap();
        assert_eq!(again.changed_cells, 0);
        assert_eq!(fusion.grid().value(Cell::new(1, 1)), value);
        assert_eq!(value, 90);
    }

    #[test]
    fn two_robots_pool_their_evidence_and_a_robot_can_change_its_mind() {
        let mut fusion = MapFusion::new(frame());
        let rect = CellRect::new(40, 30, 2, 2);
        fusion.apply(1, &patch(rect, 0.7)).unwrap();
        assert_eq!(fusion.grid().value(Cell::new(40, 30)), 70);
        fusion.apply(2, &patch(rect, 0.7)).unwrap();
        // 0.7 ⊕ 0.7 = 0.845 in log-odds.
        assert_eq!(fusion.grid().value(Cell::new(40, 30)), 84);
        fusion.apply(1, &patch(rect, 0.3)).unwrap();
        // 0.3 ⊕ 0.7 cancel out.
        assert_eq!(fusion.grid().value(Cell::new(40, 30)), 50);
        assert_eq!(fusion.observers(fusion.frame().index(Cell::new(40, 30))), 2);
        assert_eq!(fusion.grid().class(Cell::new(40, 30)), CellClass::Uncertain);
    }

    #[test]
    fn free_cells_are_clamped_and_unknown_means_no_news() {
        let mut fusion = MapFusion::new(frame());
        let rect = CellRect::new(0, 0, 2, 1);
        fusion.apply(1, &patch(rect, 0.0)).unwrap();
        assert_eq!(fusion.grid().value(Cell::new(0, 0)), 12);
        let half_unknown = Patch::from_probabilities(rect, &[1.0, 1.0], &[true, false]).unwrap();
        let change = fusion.apply(1, &half_unknown).unwrap();
        assert_eq!(fusion.grid().value(Cell::new(0, 0)), 12);
        assert_eq!(fusion.grid().value(Cell::new(1, 0)), 97);
        assert_eq!(change.changed, Some(CellRect::new(1, 0, 1, 1)));
    }

    #[test]
    fn a_grid_of_some_layers_takes_the_most_confident_value() {
        let mut fusion = MapFusion::new(frame());
        fusion.apply(1, &patch(CellRect::new(0, 0, 2, 1), 0.3)).unwrap();
        fusion.apply(2, &patch(CellRect::new(1, 0, 2, 1), 0.95)).unwrap();
        let only_one = fusion.grid_of(&[1]);
        assert_eq!(only_one.value(Cell::new(2, 0)), UNKNOWN);
        assert_eq!(only_one.value(Cell::new(1, 0)), 30);
        let both = fusion.grid_of(&[1, 2]);
        assert_eq!(both.value(Cell::new(1, 0)), 95, "the more confident layer wins, no double count");
        assert_eq!(both.value(Cell::new(0, 0)), 30);
        assert_eq!(fusion.grid_of(&[]).known_cells(), 0);
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
        let mut fusion = MapFusion::new(frame());
        let outside = patch(CellRect::new(69, 39, 2, 1), 0.5);
        assert!(matches!(fusion.apply(1, &outside), Err(PatchError::OutsideGrid { .. })));
        assert_eq!(fusion.grid().known_cells(), 0);
    }
}
