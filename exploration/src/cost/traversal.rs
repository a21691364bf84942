//! What entering each cell costs: the [`TraversalMap`] a search runs over,
//! confined to the known part of the grid, and the [`TraversalKind`] that
//! names one so that a replanning builds it once.

use super::search::Moves;
use crate::grid::{Cell, CellClass, GridFrame, NEIGHBOURS_8, OccupancyGrid, UNKNOWN, classify};

/// What entering each cell costs, per metre; `f32::INFINITY` where impassable.
///
/// Stored over a [`Window`]: the bounding box of the passable cells with an
/// impassable border two cells wide, so that the cost-map loops need no
/// bounds checks and a search over a partly explored map touches only the
/// part that is known.
#[derive(Debug, Clone, PartialEq)]
pub struct TraversalMap {
    pub(super) frame: GridFrame,
    pub(super) window: Window,
    /// The window's costs, row-major, border infinite.
    pub(super) padded: Vec<f32>,
    /// The same cells' passability as bits: small enough to stay in cache.
    pub(super) passable_bits: Vec<u64>,
    /// Per cell, the steps a robot may take from it without cutting a
    /// corner (bit k for [`Moves::offsets`]' k-th), so that a search reads
    /// one byte per cell instead of twelve passability bits.
    pub(super) moves: Vec<u8>,
    /// Per passable cell, the steps into it that cut no corner (bit k: from
    /// the neighbour at offset k), whether or not that neighbour is passable.
    pub(super) entries: Vec<u8>,
    /// One bit per cell: whether every step out of it (its [`Self::moves`])
    /// enters a cell of exactly its own cost, so that a search can take them as
    /// uniform steps without reading the neighbours' costs. Empty when the
    /// whole map is uniform: its searches never read per-cell costs.
    pub(super) flat: Vec<u64>,
    /// Smallest and largest finite cost per metre.
    pub(super) step_range: (f32, f32),
}

/// The cells a search can touch: the bounding box of the passable cells,
/// grown by two impassable cells on every side, stored row by row. A search
/// may start on the inner ring (a robot just outside the passable cells can
/// still step in); the outer ring keeps every neighbour index in bounds.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) struct Window {
    /// The grid cell at the window's first index.
    pub(super) corner: Cell,
    /// Cells per row, border included.
    pub(super) stride: usize,
    /// Rows, border included.
    pub(super) rows: usize,
}

impl Window {
    /// The bounding box of the cells where `passable` holds (a border
    /// alone when there are none), grown by two.
    fn around(frame: &GridFrame, passable: impl Fn(usize) -> bool) -> Self {
        let (w, h) = (frame.width as usize, frame.height as usize);
        let (mut x0, mut y0, mut x1, mut y1) = (usize::MAX, usize::MAX, 0, 0);
        for y in 0..h {
            let row = y * w;
            let Some(first) = (0..w).find(|&x| passable(row + x)) else { continue };
            let last = (first..w).rev().find(|&x| passable(row + x)).unwrap_or(first);
            (x0, x1, y0, y1) = (x0.min(first), x1.max(last), y0.min(y), y);
        }
        if x0 == usize::MAX {
            return Self { corner: Cell::new(-2, -2), stride: 4, rows: 4 };
        }
        Self { corner: Cell::new(x0 as i32 - 2, y0 as i32 - 2), stride: x1 - x0 + 5, rows: y1 - y0 + 5 }
    }

    pub(super) fn len(&self) -> usize {
        self.stride * self.rows
    }

    /// The index of `cell`, if the window holds it.
    #[inline]
    pub(super) fn index(&self, cell: Cell) -> Option<usize> {
        // In i64: any cell a caller passes, however far off the grid.
        let x = usize::try_from(i64::from(cell.x) - i64::from(self.corner.x)).ok().filter(|&x| x < self.stride)?;
        let y = usize::try_from(i64::from(cell.y) - i64::from(self.corner.y)).ok().filter(|&y| y < self.rows)?;
        Some(y * self.stride + x)
    }

    /// The index of `cell` if a search may start there: off the outer ring.
    #[inline]
    pub(super) fn start_index(&self, cell: Cell) -> Option<usize> {
        let i = self.index(cell)?;
        let (x, y) = (i % self.stride, i / self.stride);
        (x > 0 && y > 0 && x + 1 < self.stride && y + 1 < self.rows).then_some(i)
    }
}

impl TraversalMap {
    /// Over the window around the cells of `cost_per_metre` (one per grid
    /// cell) that are finite.
    fn from_unpadded(frame: GridFrame, cost_per_metre: &[f32]) -> Self {
        let window = Window::around(&frame, |i| cost_per_metre[i].is_finite());
        let mut padded = vec![f32::INFINITY; window.len()];
        let mut passable_bits = vec![0u64; padded.len().div_ceil(64)];
        let mut step_range = (f32::INFINITY, 0.0f32);
        let inner = window.stride - 4;
        for r in 2..window.rows - 2 {
            let y = (window.corner.y + r as i32) as usize;
            let from = y * frame.width as usize + (window.corner.x + 2) as usize;
            let row = &cost_per_metre[from..from + inner];
            for (k, &c) in row.iter().enumerate() {
                let i = r * window.stride + 2 + k;
                padded[i] = c;
                if c.is_finite() {
                    passable_bits[i / 64] |= 1 << (i % 64);
                    step_range = (step_range.0.min(c), step_range.1.max(c));
                }
            }
        }
        let (moves, entries) = Moves::of(&passable_bits, window);
        let mut map = Self { frame, window, padded, passable_bits, moves, entries, flat: Vec::new(), step_range };
        if !map.is_uniform() {
            map.flat = Moves::flat(&map.padded, &map.moves, window);
        }
        map
    }

    /// Known free cells cost 1 per metre; everything else is impassable, and
    /// so is every cell within `footprint_radius_m` of an occupied cell (the
    /// configuration space of a circular robot, Bautin et al. 2011 §IV-B).
    pub fn free_space(grid: &OccupancyGrid, footprint_radius_m: f64) -> Self {
        let frame = *grid.frame();
        let mut cost_per_metre: Vec<f32> =
            grid.cells().iter().map(|&v| if classify(v) == CellClass::Free { 1.0 } else { f32::INFINITY }).collect();
        inflate_obstacles(grid, footprint_radius_m, &mut cost_per_metre);
        Self::from_unpadded(frame, &cost_per_metre)
    }

    /// Burgard et al. 2005, §II-A: a known cell with P(occ) ≤ `occ_max` may be
    /// traversed at a cost proportional to its occupancy probability, taken
    /// from the map smoothed by a Gaussian of `smoothing_sigma_m` (so narrow
    /// passages and cells near walls cost more). Passability is decided on the
    /// unsmoothed map, so smoothing never opens a thin wall. Unknown cells are
    /// impassable and count as P = 0.5 in the smoothing.
    pub fn burgard(grid: &OccupancyGrid, occ_max: f64, smoothing_sigma_m: f64, footprint_radius_m: f64) -> Self {
        let frame = *grid.frame();
        let probabilities: Vec<f32> =
            grid.cells().iter().map(|&v| if v == UNKNOWN { 0.5 } else { f32::from(v) / 100.0 }).collect();
        let sigma_cells = smoothing_sigma_m / frame.resolution;
        let smoothed = gaussian_blur(&probabilities, frame.width as usize, frame.height as usize, sigma_cells);
        let occ_max_percent = (occ_max * 100.0).round().clamp(0.0, 100.0) as u8;
        let mut cost_per_metre: Vec<f32> = grid
            .cells()
            .iter()
            .zip(&smoothed)
            .map(|(&v, &p)| if v == UNKNOWN || v > occ_max_percent { f32::INFINITY } else { p })
            .collect();
        inflate_obstacles(grid, footprint_radius_m, &mut cost_per_metre);
        Self::from_unpadded(frame, &cost_per_metre)
    }

    /// A traversal map from explicit per-cell costs (`f32::INFINITY` = impassable).
    ///
    /// # Panics
    /// If there is not one cost per cell, or a cost is negative or NaN.
    pub fn from_costs(frame: GridFrame, cost_per_metre: Vec<f32>) -> Self {
        assert_eq!(cost_per_metre.len(), frame.len(), "one cost per cell");
        assert!(cost_per_metre.iter().all(|c| *c >= 0.0), "costs are non-negative numbers");
        Self::from_unpadded(frame, &cost_per_metre)
    }

    /// The grid frame.
    pub fn frame(&self) -> &GridFrame {
        &self.frame
    }

    /// Whether a robot may enter a cell (never off the grid).
    #[inline]
    pub fn passable(&self, cell: Cell) -> bool {
        self.window.index(cell).is_some_and(|i| self.padded[i].is_finite())
    }

    /// Cost per metre of entering a cell (infinite where impassable or off the grid).
    pub fn cost_per_metre(&self, cell: Cell) -> f32 {
        self.window.index(cell).map_or(f32::INFINITY, |i| self.padded[i])
    }
}

/// Marks every cell within `radius_m` of an occupied cell impassable.
fn inflate_obstacles(grid: &OccupancyGrid, radius_m: f64, cost: &mut [f32]) {
    let frame = grid.frame();
    let r = radius_m / frame.resolution;
    // A robot whose footprint fits in its cell needs no inflation.
    if r < 0.5 {
        return;
    }
    let reach = r.floor() as i32;
    let r_sq = r * r;
    let offsets: Vec<(i32, i32)> = (-reach..=reach)
        .flat_map(|dy| (-reach..=reach).map(move |dx| (dx, dy)))
        .filter(|&(dx, dy)| f64::from(dx * dx + dy * dy) <= r_sq)
        .collect();
    for (i, &v) in grid.cells().iter().enumerate() {
        if classify(v) != CellClass::Occupied {
            continue;
        }
        let c = frame.cell(i);
        // Only occupied cells bordering a non-occupied one can inflate anything new.
        let on_edge = NEIGHBOURS_8.iter().any(|&(dx, dy)| {
            let n = Cell::new(c.x + dx, c.y + dy);
            frame.contains(n) && classify(grid.value(n)) != CellClass::Occupied
        });
        if !on_edge {
            continue;
        }
        for &(dx, dy) in &offsets {
            let n = Cell::new(c.x + dx, c.y + dy);
            if frame.contains(n) {
                cost[frame.index(n)] = f32::INFINITY;
            }
        }
    }
}

/// Separable Gaussian blur with σ in cells (no blur below σ = 0.1); edges
/// repeat the border value.
pub fn gaussian_blur(values: &[f32], width: usize, height: usize, sigma: f64) -> Vec<f32> {
    if sigma < 0.1 {
        return values.to_vec();
    }
    let radius = (3.0 * sigma).ceil() as isize;
    let kernel: Vec<f32> =
        (-radius..=radius).map(|k| (-((k * k) as f64) / (2.0 * sigma * sigma)).exp() as f32).collect();
    let total: f32 = kernel.iter().sum();
    let kernel: Vec<f32> = kernel.iter().map(|k| k / total).collect();
    let mut tmp = vec![0.0f32; values.len()];
    for y in 0..height {
        let row = &values[y * width..(y + 1) * width];
        for x in 0..width {
            let mut acc = 0.0;
            for (k, w) in kernel.iter().enumerate() {
                let xx = (x as isize + k as isize - radius).clamp(0, width as isize - 1) as usize;
                acc += w * row[xx];
            }
            tmp[y * width + x] = acc;
        }
    }
    let mut out = vec![0.0f32; values.len()];
    for y in 0..height {
        for x in 0..width {
            let mut acc = 0.0;
            for (k, w) in kernel.iter().enumerate() {
                let yy = (y as isize + k as isize - radius).clamp(0, height as isize - 1) as usize;
                acc += w * tmp[yy * width + x];
            }
            out[y * width + x] = acc;
        }
    }
    out
}

impl TraversalMap {
    /// Puts the on-grid `sources` at cost zero (and, when `labels` is not
    /// empty, labels them with their index, the last where a cell is listed
    /// twice). Returns the window indices a search starts from, and the
    /// sources outside the window with their index: those reach only
    /// themselves.
    pub(super) fn seed(
        &self,
        sources: &[Cell],
        cost: &mut [f32],
        labels: &mut [u32],
    ) -> (Vec<usize>, Vec<(Cell, u32)>) {
        let mut starts = Vec::new();
        let mut stranded: Vec<(Cell, u32)> = Vec::new();
        for (k, &s) in sources.iter().enumerate().filter(|(_, s)| self.frame.contains(**s)) {
            match self.window.start_index(s) {
                Some(i) => {
                    cost[i] = 0.0;
                    if !labels.is_empty() {
                        labels[i] = k as u32;
                    }
                    starts.push(i);
                }
                None => match stranded.iter_mut().find(|(c, _)| *c == s) {
                    Some(seen) => seen.1 = k as u32,
                    None => stranded.push((s, k as u32)),
                },
            }
        }
        (starts, stranded)
    }

    /// The window index a search from `cell` starts at, if it starts inside
    /// the window (elsewhere a robot reaches only its own cell).
    pub(super) fn start_index(&self, cell: Cell) -> Option<usize> {
        self.window.start_index(cell).filter(|_| self.frame.contains(cell))
    }

    /// Whether a search from `cell` starts inside the window.
    pub fn starts_inside(&self, cell: Cell) -> bool {
        self.start_index(cell).is_some()
    }

    /// Whether every passable cell costs the same per metre.
    pub(super) fn is_uniform(&self) -> bool {
        self.step_range.0 == self.step_range.1
    }

    /// The cheapest and the dearest single step.
    pub(super) fn step_bounds(&self) -> (f32, f32) {
        let (orthogonal, diagonal) = self.step_lengths();
        (self.step_range.0 * orthogonal, self.step_range.1 * diagonal)
    }

    /// An orthogonal and a diagonal step, in metres.
    pub(super) fn step_lengths(&self) -> (f32, f32) {
        let resolution = self.frame.resolution;
        (resolution as f32, (resolution * std::f64::consts::SQRT_2) as f32)
    }
}

/// Which traversal a cost map was computed over.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum TraversalKind {
    /// [`TraversalMap::free_space`] for a footprint radius in millimetres.
    FreeSpace {
        /// Footprint radius, millimetres.
        footprint_mm: u32,
    },
    /// [`TraversalMap::burgard`] with occ_max in percent, σ and footprint in millimetres.
    Burgard {
        /// occ_max, percent.
        occ_max_percent: u8,
        /// Smoothing σ, millimetres.
        sigma_mm: u32,
        /// Footprint radius, millimetres.
        footprint_mm: u32,
    },
}

impl TraversalKind {
    /// The free-space traversal for a footprint radius in metres.
    pub fn free_space(footprint_radius_m: f64) -> Self {
        Self::FreeSpace { footprint_mm: millimetres(footprint_radius_m) }
    }

    /// Burgard's traversal (see [`TraversalMap::burgard`]).
    pub fn burgard(occ_max: f64, smoothing_sigma_m: f64, footprint_radius_m: f64) -> Self {
        Self::Burgard {
            occ_max_percent: (occ_max * 100.0).round().clamp(0.0, 100.0) as u8,
            sigma_mm: millimetres(smoothing_sigma_m),
            footprint_mm: millimetres(footprint_radius_m),
        }
    }

    pub(super) fn build(self, grid: &OccupancyGrid) -> TraversalMap {
        match self {
            Self::FreeSpace { footprint_mm } => TraversalMap::free_space(grid, metres(footprint_mm)),
            Self::Burgard { occ_max_percent, sigma_mm, footprint_mm } => {
                TraversalMap::burgard(grid, f64::from(occ_max_percent) / 100.0, metres(sigma_mm), metres(footprint_mm))
            }
        }
    }
}

fn millimetres(m: f64) -> u32 {
    (m.max(0.0) * 1000.0).round() as u32
}

fn metres(mm: u32) -> f64 {
    f64::from(mm) / 1000.0
}
