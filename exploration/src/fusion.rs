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

mod patch;

pub use patch::{Patch, PatchError, UNKNOWN_PERCENT};

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

/// `row`, starting at column `x`, cut where it crosses from one tile into
/// the next: each run with the column it starts at.
fn runs_within_tiles(row: &[f32], x: usize) -> impl Iterator<Item = (usize, &[f32])> {
    let mut rest = row;
    let mut x = x;
    std::iter::from_fn(move || {
        if rest.is_empty() {
            return None;
        }
        let (run, tail) = rest.split_at((TILE - (x & (TILE - 1))).min(rest.len()));
        let start = x;
        rest = tail;
        x += run.len();
        Some((start, run))
    })
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
        let (width, patch_width) = (self.frame.width as usize, rect.width as usize);
        let mut change = FusionChange::default();
        let mut changed_rect: Option<CellRect> = None;
        for (y, row) in (rect.y as usize..).zip(patch.log_odds().chunks_exact(patch_width)) {
            // Row by row, one tile's run of cells at a time: the tile is
            // looked up once per run, not per cell.
            for (run_x, run) in runs_within_tiles(row, rect.x as usize) {
                let tile_index = (y >> TILE_SHIFT) * tiles_x + (run_x >> TILE_SHIFT);
                let first = (y & (TILE - 1)) * TILE + (run_x & (TILE - 1));
                let tile = &mut layer.tiles[tile_index];
                // A tile is made only for a known cell.
                if tile.is_none() && run.iter().all(|v| v.is_nan()) {
                    continue;
                }
                let tile = tile.get_or_insert_with(|| vec![f32::NAN; TILE * TILE].into_boxed_slice());
                for (k, (slot, &new)) in tile[first..first + run.len()].iter_mut().zip(run).enumerate() {
                    if new.is_nan() || *slot == new {
                        continue;
                    }
                    let old = std::mem::replace(slot, new);
                    let i = y * width + run_x + k;
                    replace_in_sum(&mut self.sum[i], &mut self.observers[i], old, new);
                    let fused = fused_percent(self.sum[i]);
                    let before = self.grid.value_at(i);
                    if before != fused {
                        let cell = crate::grid::Cell::new((run_x + k) as i32, y as i32);
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

/// One layer of a [`MapFusion`] as plain data: the robot's known cells, as
/// square patches of the tiles it reported in (NaN where it knows nothing).
#[derive(Debug, Clone)]
pub struct LayerParts {
    /// Whose layer.
    pub id: LayerId,
    /// Its tiles, each clipped to the grid.
    pub tiles: Vec<Patch>,
}

/// Everything a [`MapFusion`] holds, as plain data, so that a store can
/// keep the fused map instead of every patch that made it (a compacted
/// patch log). The sums are kept as they are, bit for bit: rebuilding them
/// from the layers would add the same numbers in another order, and a fused
/// map restored from its parts must equal the one they were taken from.
#[derive(Debug, Clone)]
pub struct FusionParts {
    /// Σ of the layers' log-odds per cell, row-major.
    pub sum: Vec<f32>,
    /// The layers, by robot.
    pub layers: Vec<LayerParts>,
}

/// Why parts do not make a fusion of a grid.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum PartsError {
    /// The sums are not one per cell.
    #[error("{got} sums for a grid of {expected} cells")]
    SumCount {
        /// Cells of the grid.
        expected: usize,
        /// Sums given.
        got: usize,
    },
    /// A sum is NaN or infinite, or set on a cell no layer knows.
    #[error("the sum of cell {index} is {value}, which its layers cannot add up to")]
    BadSum {
        /// Row-major cell index.
        index: usize,
        /// The value.
        value: f32,
    },
    /// A layer's patch is not one whole tile of the grid.
    #[error("layer {layer}: {rect:?} is not a tile of the grid")]
    NotATile {
        /// The layer.
        layer: LayerId,
        /// The patch's rectangle.
        rect: CellRect,
    },
    /// A layer appears twice, or a tile twice in one layer.
    #[error("layer {0} or one of its tiles is given twice")]
    Repeated(LayerId),
    /// More layers know a cell than a cell can count.
    #[error("cell {0} is known by more layers than the executive counts")]
    TooManyObservers(usize),
}

impl MapFusion {
    /// The fusion as plain data (see [`FusionParts`]).
    pub fn parts(&self) -> FusionParts {
        let layers = self
            .layers
            .iter()
            .map(|(&id, layer)| LayerParts {
                id,
                tiles: layer
                    .tiles
                    .iter()
                    .enumerate()
                    .filter_map(|(t, tile)| tile.as_ref().map(|tile| self.tile_patch(t, tile)))
                    .collect(),
            })
            .collect();
        FusionParts { sum: self.sum.clone(), layers }
    }

    /// The fusion the parts were taken from, checked against `frame`: the
    /// same layers, sums, observers and fused grid.
    pub fn from_parts(frame: GridFrame, parts: FusionParts) -> Result<Self, PartsError> {
        let mut fusion = Self::new(frame);
        if parts.sum.len() != frame.len() {
            return Err(PartsError::SumCount { expected: frame.len(), got: parts.sum.len() });
        }
        for layer in parts.layers {
            let mut tiles = vec![None; fusion.tiles_x * fusion.tiles_y];
            for patch in layer.tiles {
                let t = fusion.tile_of(&patch).ok_or(PartsError::NotATile { layer: layer.id, rect: patch.rect() })?;
                if tiles[t].is_some() {
                    return Err(PartsError::Repeated(layer.id));
                }
                let mut tile = vec![f32::NAN; TILE * TILE].into_boxed_slice();
                let rect = patch.rect();
                for (k, &value) in patch.log_odds().iter().enumerate() {
                    let (dx, dy) = (k % rect.width as usize, k / rect.width as usize);
                    tile[dy * TILE + dx] = value;
                    if !value.is_nan() {
                        let i = (rect.y as usize + dy) * frame.width as usize + rect.x as usize + dx;
                        fusion.observers[i] =
                            fusion.observers[i].checked_add(1).ok_or(PartsError::TooManyObservers(i))?;
                    }
                }
                tiles[t] = Some(tile);
            }
            if fusion.layers.insert(layer.id, Layer { tiles }).is_some() {
                return Err(PartsError::Repeated(layer.id));
            }
        }
        let mut cells = vec![UNKNOWN; frame.len()];
        for (i, (&sum, &observers)) in parts.sum.iter().zip(&fusion.observers).enumerate() {
            if !sum.is_finite() || (observers == 0 && sum != 0.0) {
                return Err(PartsError::BadSum { index: i, value: sum });
            }
            if observers > 0 {
                cells[i] = fused_percent(sum);
            }
        }
        fusion.sum = parts.sum;
        fusion.grid = OccupancyGrid::from_cells(frame, cells);
        Ok(fusion)
    }

    /// Tile `t` of a layer as a patch, clipped to the grid.
    fn tile_patch(&self, t: usize, tile: &[f32]) -> Patch {
        let (x, y) = ((t % self.tiles_x) * TILE, (t / self.tiles_x) * TILE);
        let width = TILE.min(self.frame.width as usize - x);
        let height = TILE.min(self.frame.height as usize - y);
        let log_odds = (0..height).flat_map(|dy| tile[dy * TILE..dy * TILE + width].iter().copied()).collect();
        Patch::of_layer(CellRect::new(x as i32, y as i32, width as u32, height as u32), log_odds)
    }

    /// Which tile a patch covers exactly, clipped to the grid, if any.
    fn tile_of(&self, patch: &Patch) -> Option<usize> {
        let rect = patch.rect();
        let (x, y) = (usize::try_from(rect.x).ok()?, usize::try_from(rect.y).ok()?);
        if x % TILE != 0 || y % TILE != 0 || !self.frame.contains_rect(&rect) {
            return None;
        }
        let whole = |start: usize, side: u32, grid: u32| side as usize == TILE.min(grid as usize - start);
        let t = (y / TILE) * self.tiles_x + x / TILE;
        (whole(x, rect.width, self.frame.width) && whole(y, rect.height, self.frame.height)).then_some(t)
    }
}

/// A layer's value of a cell goes from `old` (NaN: the layer did not know
/// it) to `new`, in the cell's sum over the layers and its count of them.
fn replace_in_sum(sum: &mut f32, observers: &mut u16, old: f32, new: f32) {
    if old.is_nan() {
        *observers += 1;
        *sum += new;
    } else {
        *sum += new - old;
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
    fn a_patch_outside_the_grid_changes_nothing() {
        let mut fusion = MapFusion::new(frame());
        let outside = patch(CellRect::new(69, 39, 2, 1), 0.5);
        assert!(matches!(fusion.apply(1, &outside), Err(PatchError::OutsideGrid { .. })));
        assert_eq!(fusion.grid().known_cells(), 0);
    }

    /// A layer's tiles, bit for bit.
    type LayerBits = (LayerId, Vec<(CellRect, Vec<u32>)>);

    /// A fusion's state, bit for bit (NaN compares equal to NaN): sums,
    /// observers, fused grid and layers.
    fn state(fusion: &MapFusion) -> (Vec<u32>, Vec<u16>, Vec<u8>, Vec<LayerBits>) {
        let parts = fusion.parts();
        let layers = parts
            .layers
            .iter()
            .map(|l| {
                (l.id, l.tiles.iter().map(|t| (t.rect(), t.log_odds().iter().map(|v| v.to_bits()).collect())).collect())
            })
            .collect();
        (
            parts.sum.iter().map(|v| v.to_bits()).collect(),
            fusion.observers.clone(),
            fusion.grid().cells().to_vec(),
            layers,
        )
    }

    /// A random patch of a random robot, some cells unknown.
    fn random_patch(rng: &mut crate::rng::SplitMix64, frame: &GridFrame) -> (LayerId, Patch) {
        let (w, h) = (1 + rng.below(20) as u32, 1 + rng.below(20) as u32);
        let x = rng.below(u64::from(frame.width - w + 1)) as i32;
        let y = rng.below(u64::from(frame.height - h + 1)) as i32;
        let rect = CellRect::new(x, y, w, h);
        let values: Vec<f32> = (0..rect.area()).map(|_| rng.below(1001) as f32 / 1000.0).collect();
        let unknown: Vec<bool> = (0..rect.area()).map(|_| rng.below(4) == 0).collect();
        (1 + rng.below(5), Patch::from_probabilities(rect, &values, &unknown).unwrap())
    }

    proptest::proptest! {
        #![proptest_config(crate::testing::seeded_proptest(64))]
        /// A fusion rebuilt from its parts is the same fusion, and stays the
        /// same as the original under the patches that follow: what a
        /// compacted patch log relies on.
        #[test]
        fn a_fusion_rebuilt_from_its_parts_goes_on_as_the_original(seed in 0u64..u64::MAX, before in 1usize..60) {
            let frame = frame();
            let mut rng = crate::rng::SplitMix64::new(seed);
            let mut original = MapFusion::new(frame);
            for _ in 0..before {
                let (layer, patch) = random_patch(&mut rng, &frame);
                original.apply(layer, &patch).unwrap();
            }
            let mut rebuilt = MapFusion::from_parts(frame, original.parts()).unwrap();
            proptest::prop_assert_eq!(state(&rebuilt), state(&original));
            for _ in 0..20 {
                let (layer, patch) = random_patch(&mut rng, &frame);
                proptest::prop_assert_eq!(rebuilt.apply(layer, &patch).unwrap(), original.apply(layer, &patch).unwrap());
            }
            proptest::prop_assert_eq!(state(&rebuilt), state(&original));
        }

        /// Applying a patch a tile's run at a time does what applying it
        /// cell by cell does, bit for bit, and makes a layer's tile only
        /// where the layer was sent a known cell.
        #[test]
        fn runs_within_tiles_fuse_as_cell_by_cell(seed in 0u64..u64::MAX, patches in 1usize..80) {
            let frame = frame();
            let mut rng = crate::rng::SplitMix64::new(seed);
            let (mut fusion, mut model) = (MapFusion::new(frame), CellByCell::new(&frame));
            for _ in 0..patches {
                let (layer, patch) = random_patch(&mut rng, &frame);
                proptest::prop_assert_eq!(fusion.apply(layer, &patch).unwrap(), model.apply(layer, &patch));
            }
            let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
            proptest::prop_assert_eq!(bits(&fusion.sum), bits(&model.sum));
            proptest::prop_assert_eq!(&fusion.observers, &model.observers);
            proptest::prop_assert_eq!(fusion.grid().cells(), &model.grid[..]);
            for (id, layer) in &fusion.layers {
                let made: std::collections::BTreeSet<(usize, usize)> = layer
                    .tiles
                    .iter()
                    .enumerate()
                    .filter(|(_, t)| t.is_some())
                    .map(|(t, _)| (t % fusion.tiles_x, t / fusion.tiles_x))
                    .collect();
                proptest::prop_assert_eq!(made, model.tiles.get(id).cloned().unwrap_or_default());
            }
        }
    }

    /// Fusion written out cell by cell over a dense copy of each layer: the
    /// model [`MapFusion::apply`]'s runs within tiles must agree with.
    struct CellByCell {
        width: usize,
        layers: BTreeMap<LayerId, Vec<f32>>,
        sum: Vec<f32>,
        observers: Vec<u16>,
        grid: Vec<u8>,
        /// The tiles each layer has had a known cell in.
        tiles: BTreeMap<LayerId, std::collections::BTreeSet<(usize, usize)>>,
    }

    impl CellByCell {
        fn new(frame: &GridFrame) -> Self {
            let cells = frame.len();
            Self {
                width: frame.width as usize,
                layers: BTreeMap::new(),
                sum: vec![0.0; cells],
                observers: vec![0; cells],
                grid: vec![UNKNOWN; cells],
                tiles: BTreeMap::new(),
            }
        }

        fn apply(&mut self, layer: LayerId, patch: &Patch) -> FusionChange {
            let cells = self.sum.len();
            let values = self.layers.entry(layer).or_insert_with(|| vec![f32::NAN; cells]);
            let rect = patch.rect();
            let mut change = FusionChange::default();
            let mut new_values = patch.log_odds().iter();
            for y in rect.y..rect.y_end() {
                for x in rect.x..rect.x_end() {
                    let new = *new_values.next().unwrap();
                    let (x, y) = (x as usize, y as usize);
                    let i = y * self.width + x;
                    if new.is_nan() {
                        continue;
                    }
                    self.tiles.entry(layer).or_default().insert((x / TILE, y / TILE));
                    let old = values[i];
                    if old == new {
                        continue;
                    }
                    values[i] = new;
                    replace_in_sum(&mut self.sum[i], &mut self.observers[i], old, new);
                    let fused = fused_percent(self.sum[i]);
                    if self.grid[i] != fused {
                        let cell = Cell::new(x as i32, y as i32);
                        change.changed_cells += 1;
                        change.newly_known += u64::from(self.grid[i] == UNKNOWN);
                        change.changed =
                            Some(change.changed.map_or(CellRect::new(cell.x, cell.y, 1, 1), |r| r.including(cell)));
                        self.grid[i] = fused;
                    }
                }
            }
            change
        }
    }

    #[test]
    fn parts_that_no_fusion_has_are_refused() {
        let frame = frame();
        let mut fusion = MapFusion::new(frame);
        fusion.apply(7, &patch(CellRect::new(30, 30, 5, 5), 0.9)).unwrap();
        let good = fusion.parts();
        assert!(MapFusion::from_parts(frame, good.clone()).is_ok());

        let mut short = good.clone();
        short.sum.pop();
        assert!(matches!(MapFusion::from_parts(frame, short), Err(PartsError::SumCount { .. })));

        let mut unknown_with_a_sum = good.clone();
        unknown_with_a_sum.sum[0] = 1.0;
        assert!(matches!(MapFusion::from_parts(frame, unknown_with_a_sum), Err(PartsError::BadSum { index: 0, .. })));

        let mut infinite = good.clone();
        infinite.sum[30 * 70 + 30] = f32::INFINITY;
        assert!(matches!(MapFusion::from_parts(frame, infinite), Err(PartsError::BadSum { .. })));

        let mut twice = good.clone();
        twice.layers.push(twice.layers[0].clone());
        assert!(matches!(MapFusion::from_parts(frame, twice), Err(PartsError::Repeated(7))));

        let mut misplaced = good;
        misplaced.layers[0].tiles[0] = patch(CellRect::new(1, 0, 32, 32), 0.5);
        assert!(matches!(MapFusion::from_parts(frame, misplaced), Err(PartsError::NotATile { layer: 7, .. })));
    }
}
