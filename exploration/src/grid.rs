//! Occupancy grids and their frame in the world.
//!
//! Every map in the system is a grid of square cells laid over the mission's
//! world frame (ROS map_server convention: x right, y up, cell (0, 0) at the
//! lower left). An [`OccupancyGrid`] stores P(occ) per cell in percent, or
//! "unknown" for cells no sensor beam has touched yet, which is the binary
//! notion of "explored" of Burgard et al. 2005, §II.

use crate::math::Point2;

/// Integer coordinates of one cell: column `x`, row `y`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct Cell {
    /// Column, 0 at the left.
    pub x: i32,
    /// Row, 0 at the bottom.
    pub y: i32,
}

impl Cell {
    /// The cell at column `x`, row `y`.
    pub const fn new(x: i32, y: i32) -> Self {
        Self { x, y }
    }

    /// Euclidean distance to `other`, in cells.
    pub fn distance(self, other: Cell) -> f64 {
        let dx = f64::from(self.x - other.x);
        let dy = f64::from(self.y - other.y);
        dx.hypot(dy)
    }

    /// Squared Euclidean distance to `other`, in cells².
    pub fn distance_squared(self, other: Cell) -> i64 {
        let dx = i64::from(self.x - other.x);
        let dy = i64::from(self.y - other.y);
        dx * dx + dy * dy
    }
}

/// The eight neighbour offsets, orthogonal ones first.
pub const NEIGHBOURS_8: [(i32, i32); 8] = [(1, 0), (-1, 0), (0, 1), (0, -1), (1, 1), (-1, 1), (1, -1), (-1, -1)];

/// An axis-aligned rectangle of cells, `x .. x + width` by `y .. y + height`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct CellRect {
    /// Leftmost column.
    pub x: i32,
    /// Bottom row.
    pub y: i32,
    /// Number of columns (>= 1 for a non-empty rectangle).
    pub width: u32,
    /// Number of rows (>= 1 for a non-empty rectangle).
    pub height: u32,
}

impl CellRect {
    /// The rectangle with lower-left cell `(x, y)` and the given size.
    pub const fn new(x: i32, y: i32, width: u32, height: u32) -> Self {
        Self { x, y, width, height }
    }

    /// The smallest rectangle holding both corner cells (its sides saturate
    /// at `u32::MAX` cells: a span of 2³² cells cannot be represented).
    pub fn spanning(a: Cell, b: Cell) -> Self {
        let (x0, x1) = (a.x.min(b.x), a.x.max(b.x));
        let (y0, y1) = (a.y.min(b.y), a.y.max(b.y));
        Self::new(x0, y0, side(i64::from(x0), i64::from(x1) + 1), side(i64::from(y0), i64::from(y1) + 1))
    }

    /// Number of cells.
    pub fn area(&self) -> u64 {
        u64::from(self.width) * u64::from(self.height)
    }

    /// One past the rightmost column (saturating at `i32::MAX`, so that a
    /// rectangle from any input never wraps around).
    pub fn x_end(&self) -> i32 {
        saturate(i64::from(self.x) + i64::from(self.width))
    }

    /// One past the top row (saturating at `i32::MAX`).
    pub fn y_end(&self) -> i32 {
        saturate(i64::from(self.y) + i64::from(self.height))
    }

    /// Whether `cell` lies inside.
    pub fn contains(&self, cell: Cell) -> bool {
        cell.x >= self.x && cell.x < self.x_end() && cell.y >= self.y && cell.y < self.y_end()
    }

    /// The smallest rectangle holding `self` and `cell`.
    pub fn including(&self, cell: Cell) -> Self {
        let x0 = self.x.min(cell.x);
        let y0 = self.y.min(cell.y);
        let x1 = i64::from(self.x_end()).max(i64::from(cell.x) + 1);
        let y1 = i64::from(self.y_end()).max(i64::from(cell.y) + 1);
        Self::new(x0, y0, side(i64::from(x0), x1), side(i64::from(y0), y1))
    }

    /// The smallest rectangle holding both.
    pub fn union(&self, other: &CellRect) -> Self {
        let x0 = self.x.min(other.x);
        let y0 = self.y.min(other.y);
        let x1 = self.x_end().max(other.x_end());
        let y1 = self.y_end().max(other.y_end());
        Self::new(x0, y0, side(i64::from(x0), i64::from(x1)), side(i64::from(y0), i64::from(y1)))
    }

    /// The overlap of both, if any cell is shared.
    pub fn intersection(&self, other: &CellRect) -> Option<Self> {
        let x0 = self.x.max(other.x);
        let y0 = self.y.max(other.y);
        let x1 = self.x_end().min(other.x_end());
        let y1 = self.y_end().min(other.y_end());
        (x1 > x0 && y1 > y0)
            .then(|| Self::new(x0, y0, side(i64::from(x0), i64::from(x1)), side(i64::from(y0), i64::from(y1))))
    }

    /// Grown by `margin` cells on every side (saturating at the ends of `i32`).
    pub fn grown(&self, margin: u32) -> Self {
        let m = i64::from(margin);
        let (x0, y0) = (saturate(i64::from(self.x) - m), saturate(i64::from(self.y) - m));
        let (x1, y1) = (saturate(i64::from(self.x_end()) + m), saturate(i64::from(self.y_end()) + m));
        Self::new(x0, y0, side(i64::from(x0), i64::from(x1)), side(i64::from(y0), i64::from(y1)))
    }

    /// Every cell, row by row from the bottom.
    pub fn cells(&self) -> impl Iterator<Item = Cell> + '_ {
        (self.y..self.y_end()).flat_map(move |y| (self.x..self.x_end()).map(move |x| Cell::new(x, y)))
    }
}

/// A coordinate clamped into `i32`.
fn saturate(v: i64) -> i32 {
    v.clamp(i64::from(i32::MIN), i64::from(i32::MAX)) as i32
}

/// The length of `start..end`, clamped into `u32`.
fn side(start: i64, end: i64) -> u32 {
    (end - start).clamp(0, i64::from(u32::MAX)) as u32
}

/// How a grid sits in the world: cell size, where cell (0, 0) is, and size.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GridFrame {
    /// Edge length of a cell, metres.
    pub resolution: f64,
    /// World position of the lower-left corner of cell (0, 0).
    pub origin: Point2,
    /// Columns.
    pub width: u32,
    /// Rows.
    pub height: u32,
}

impl GridFrame {
    /// A frame of `width` × `height` cells of `resolution` metres whose lower-left
    /// corner is at `origin`.
    pub fn new(resolution: f64, origin: Point2, width: u32, height: u32) -> Self {
        Self { resolution, origin, width, height }
    }

    /// Number of cells.
    pub fn len(&self) -> usize {
        self.width as usize * self.height as usize
    }

    /// Whether the grid has no cell.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The whole grid as a rectangle.
    pub fn bounds(&self) -> CellRect {
        CellRect::new(0, 0, self.width, self.height)
    }

    /// Whether `cell` lies on the grid.
    pub fn contains(&self, cell: Cell) -> bool {
        cell.x >= 0 && cell.y >= 0 && (cell.x as u32) < self.width && (cell.y as u32) < self.height
    }

    /// Whether every cell of `rect` lies on the grid.
    pub fn contains_rect(&self, rect: &CellRect) -> bool {
        rect.width > 0
            && rect.height > 0
            && rect.x >= 0
            && rect.y >= 0
            && i64::from(rect.x) + i64::from(rect.width) <= i64::from(self.width)
            && i64::from(rect.y) + i64::from(rect.height) <= i64::from(self.height)
    }

    /// `rect` clipped to the grid.
    pub fn clip(&self, rect: &CellRect) -> Option<CellRect> {
        rect.intersection(&self.bounds())
    }

    /// Row-major index of an on-grid cell.
    #[inline]
    pub fn index(&self, cell: Cell) -> usize {
        debug_assert!(self.contains(cell), "{cell:?} is off the grid");
        cell.y as usize * self.width as usize + cell.x as usize
    }

    /// The cell of a row-major index.
    #[inline]
    pub fn cell(&self, index: usize) -> Cell {
        let w = self.width as usize;
        Cell::new((index % w) as i32, (index / w) as i32)
    }

    /// The cell holding a world point, if it is on the grid.
    pub fn cell_from_world(&self, point_in_world: &Point2) -> Option<Cell> {
        let cell = self.cell_from_world_unchecked(point_in_world);
        self.contains(cell).then_some(cell)
    }

    /// The cells of the grid that a world rectangle (`min` to `max`, in
    /// metres) touches, or `None` when it misses the grid. Clipped in world
    /// coordinates first, so any finite or infinite corner is safe.
    pub fn rect_from_world(&self, min: &Point2, max: &Point2) -> Option<CellRect> {
        let to_cells = |v: f64, origin: f64, cells: u32| {
            let c = ((v - origin) / self.resolution).floor();
            if c.is_nan() { None } else { Some(c.clamp(-1.0, f64::from(cells)) as i64) }
        };
        let (x0, x1) = (to_cells(min.x, self.origin.x, self.width)?, to_cells(max.x, self.origin.x, self.width)?);
        let (y0, y1) = (to_cells(min.y, self.origin.y, self.height)?, to_cells(max.y, self.origin.y, self.height)?);
        let (x0, x1) = (x0.min(x1).max(0), x0.max(x1).min(i64::from(self.width) - 1));
        let (y0, y1) = (y0.min(y1).max(0), y0.max(y1).min(i64::from(self.height) - 1));
        (x0 <= x1 && y0 <= y1).then(|| CellRect::new(x0 as i32, y0 as i32, side(x0, x1 + 1), side(y0, y1 + 1)))
    }

    /// The cell holding a world point, which may be off the grid.
    pub fn cell_from_world_unchecked(&self, point_in_world: &Point2) -> Cell {
        let local = point_in_world - self.origin;
        Cell::new((local.x / self.resolution).floor() as i32, (local.y / self.resolution).floor() as i32)
    }

    /// The world position of a cell's centre.
    pub fn world_from_cell(&self, cell: Cell) -> Point2 {
        Point2::new(
            self.origin.x + (f64::from(cell.x) + 0.5) * self.resolution,
            self.origin.y + (f64::from(cell.y) + 0.5) * self.resolution,
        )
    }

    /// A length in metres expressed in cells.
    pub fn cells_from_metres(&self, metres: f64) -> f64 {
        metres / self.resolution
    }
}

/// The value stored for a cell nobody has observed.
pub const UNKNOWN: u8 = 255;
/// Cells with P(occ) below this percentage are free ("clear", Simmons et al. 2000 §4.1).
pub const FREE_BELOW_PERCENT: u8 = 25;
/// Cells with P(occ) above this percentage are obstacles.
pub const OCCUPIED_ABOVE_PERCENT: u8 = 65;

/// The class of a cell for frontier detection and planning.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum CellClass {
    /// Never observed.
    Unknown,
    /// Observed, P(occ) below [`FREE_BELOW_PERCENT`].
    Free,
    /// Observed, P(occ) above [`OCCUPIED_ABOVE_PERCENT`].
    Occupied,
    /// Observed, but the evidence is inconclusive.
    Uncertain,
}

/// Classifies a stored cell value.
#[inline]
pub fn classify(value: u8) -> CellClass {
    match value {
        UNKNOWN => CellClass::Unknown,
        v if v < FREE_BELOW_PERCENT => CellClass::Free,
        v if v > OCCUPIED_ABOVE_PERCENT => CellClass::Occupied,
        _ => CellClass::Uncertain,
    }
}

/// A grid of occupancy probabilities in percent (0 ..= 100), or [`UNKNOWN`].
///
/// One byte per cell keeps the planners' working set small; a percent is
/// finer than any threshold the policies use.
#[derive(Debug, Clone, PartialEq)]
pub struct OccupancyGrid {
    frame: GridFrame,
    cells: Vec<u8>,
}

impl OccupancyGrid {
    /// A grid where every cell is unknown.
    pub fn unknown(frame: GridFrame) -> Self {
        Self { cells: vec![UNKNOWN; frame.len()], frame }
    }

    /// A grid from row-major values (percent or [`UNKNOWN`]).
    ///
    /// # Panics
    /// If `cells` does not hold one value per cell, or a value is neither a
    /// percentage nor [`UNKNOWN`].
    pub fn from_cells(frame: GridFrame, cells: Vec<u8>) -> Self {
        assert_eq!(cells.len(), frame.len(), "one value per cell");
        assert!(cells.iter().all(|&v| v <= 100 || v == UNKNOWN), "values are percentages or UNKNOWN");
        Self { frame, cells }
    }

    /// Where the grid sits.
    pub fn frame(&self) -> &GridFrame {
        &self.frame
    }

    /// Row-major values.
    pub fn cells(&self) -> &[u8] {
        &self.cells
    }

    /// The stored value of an on-grid cell.
    #[inline]
    pub fn value(&self, cell: Cell) -> u8 {
        self.cells[self.frame.index(cell)]
    }

    /// The stored value at a row-major index.
    #[inline]
    pub fn value_at(&self, index: usize) -> u8 {
        self.cells[index]
    }

    /// Sets an on-grid cell's value.
    #[inline]
    pub fn set(&mut self, cell: Cell, value: u8) {
        debug_assert!(value <= 100 || value == UNKNOWN);
        let i = self.frame.index(cell);
        self.cells[i] = value;
    }

    /// The class of an on-grid cell.
    #[inline]
    pub fn class(&self, cell: Cell) -> CellClass {
        classify(self.value(cell))
    }

    /// The class of a cell, with cells off the grid counted as occupied
    /// (the map's border is a wall).
    #[inline]
    pub fn class_or_wall(&self, cell: Cell) -> CellClass {
        if self.frame.contains(cell) { self.class(cell) } else { CellClass::Occupied }
    }

    /// P(occ) of an on-grid cell, or `None` when unknown.
    pub fn probability(&self, cell: Cell) -> Option<f32> {
        match self.value(cell) {
            UNKNOWN => None,
            v => Some(f32::from(v) / 100.0),
        }
    }

    /// Number of known (observed) cells.
    pub fn known_cells(&self) -> usize {
        self.cells.iter().filter(|&&v| v != UNKNOWN).count()
    }
}

/// Converts an occupancy probability to a stored percent value.
#[inline]
pub fn percent_from_probability(p: f32) -> u8 {
    (p.clamp(0.0, 1.0) * 100.0).round() as u8
}

#[cfg(test)]
pub(crate) mod testing {
    //! Grids drawn as pictures, for tests.
    use super::*;

    /// Parses a picture, top row first: `.` free, `#` occupied, `?` unknown.
    pub(crate) fn grid_from_picture(rows: &[&str]) -> OccupancyGrid {
        let height = rows.len() as u32;
        let width = rows[0].len() as u32;
        let frame = GridFrame::new(1.0, Point2::origin(), width, height);
        let mut grid = OccupancyGrid::unknown(frame);
        for (r, row) in rows.iter().enumerate() {
            for (x, ch) in row.chars().enumerate() {
                let cell = Cell::new(x as i32, (height as usize - 1 - r) as i32);
                match ch {
                    '.' => grid.set(cell, 10),
                    '#' => grid.set(cell, 95),
                    '?' => {}
                    other => panic!("unexpected {other:?} in picture"),
                }
            }
        }
        grid
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn frame() -> GridFrame {
        GridFrame::new(0.5, Point2::new(-2.0, 1.0), 10, 6)
    }

    #[test]
    fn world_and_cell_round_trip_through_cell_centres() {
        let f = frame();
        for cell in f.bounds().cells() {
            let centre = f.world_from_cell(cell);
            assert_eq!(f.cell_from_world(&centre), Some(cell));
            assert_eq!(f.cell(f.index(cell)), cell);
        }
        // The origin is the lower-left corner of cell (0, 0).
        assert_eq!(f.cell_from_world(&Point2::new(-2.0, 1.0)), Some(Cell::new(0, 0)));
        assert_eq!(f.cell_from_world(&Point2::new(-2.01, 1.0)), None);
        assert_eq!(f.cell_from_world(&Point2::new(2.99, 3.99)), Some(Cell::new(9, 5)));
        assert_eq!(f.cell_from_world(&Point2::new(3.0, 3.0)), None);
    }

    #[test]
    fn rectangles_must_lie_inside_the_grid() {
        let f = frame();
        assert!(f.contains_rect(&CellRect::new(0, 0, 10, 6)));
        assert!(!f.contains_rect(&CellRect::new(1, 0, 10, 6)));
        assert!(!f.contains_rect(&CellRect::new(-1, 0, 2, 2)));
        assert!(!f.contains_rect(&CellRect::new(0, 0, 0, 2)));
        assert_eq!(f.clip(&CellRect::new(8, 4, 5, 5)), Some(CellRect::new(8, 4, 2, 2)));
        assert_eq!(f.clip(&CellRect::new(20, 4, 5, 5)), None);
    }

    #[test]
    fn world_rectangles_of_any_size_clip_to_the_grid() {
        let f = frame();
        let whole = Some(f.bounds());
        // A rectangle spanning 2³² cells and more, and infinite corners, clip
        // to the grid instead of wrapping around.
        assert_eq!(f.rect_from_world(&Point2::new(-1e6, -1e6), &Point2::new(1e6, 1e6)), whole);
        assert_eq!(f.rect_from_world(&Point2::new(-1e300, -1e300), &Point2::new(1e300, 1e300)), whole);
        let inf = f64::INFINITY;
        assert_eq!(f.rect_from_world(&Point2::new(-inf, -inf), &Point2::new(inf, inf)), whole);
        assert_eq!(f.rect_from_world(&Point2::new(f64::NAN, 0.0), &Point2::new(1.0, 1.0)), None);
        // Corners in either order; a rectangle off the grid touches nothing.
        assert_eq!(f.rect_from_world(&Point2::new(0.6, 1.1), &Point2::new(-0.4, 0.1)), Some(CellRect::new(3, 0, 3, 1)));
        assert_eq!(f.rect_from_world(&Point2::new(10.0, 10.0), &Point2::new(20.0, 20.0)), None);
        assert_eq!(f.rect_from_world(&Point2::new(-9.0, 0.0), &Point2::new(-8.0, 1.0)), None);
        // Cell arithmetic saturates instead of overflowing.
        let huge = CellRect::spanning(Cell::new(i32::MIN, i32::MIN), Cell::new(i32::MAX, i32::MAX));
        assert_eq!((huge.width, huge.height), (u32::MAX, u32::MAX));
        assert_eq!(huge.x_end(), i32::MAX);
        assert_eq!(huge.intersection(&f.bounds()), whole);
        assert_eq!(CellRect::new(i32::MAX - 1, 0, 5, 5).grown(10).x_end(), i32::MAX);
    }

    #[test]
    fn rectangle_set_operations() {
        let a = CellRect::new(0, 0, 4, 4);
        let b = CellRect::new(2, 3, 4, 4);
        assert_eq!(a.intersection(&b), Some(CellRect::new(2, 3, 2, 1)));
        assert_eq!(a.union(&b), CellRect::new(0, 0, 6, 7));
        assert_eq!(a.including(Cell::new(-1, 5)), CellRect::new(-1, 0, 5, 6));
        assert_eq!(CellRect::spanning(Cell::new(3, 1), Cell::new(1, 2)), CellRect::new(1, 1, 3, 2));
        assert_eq!(a.cells().count() as u64, a.area());
        assert_eq!(CellRect::new(0, 0, 2, 2).intersection(&CellRect::new(2, 0, 2, 2)), None);
    }

    #[test]
    fn classification_thresholds() {
        assert_eq!(classify(UNKNOWN), CellClass::Unknown);
        assert_eq!(classify(12), CellClass::Free);
        assert_eq!(classify(25), CellClass::Uncertain);
        assert_eq!(classify(65), CellClass::Uncertain);
        assert_eq!(classify(66), CellClass::Occupied);
        let g = OccupancyGrid::unknown(frame());
        assert_eq!(g.class_or_wall(Cell::new(-1, 0)), CellClass::Occupied);
        assert_eq!(g.class_or_wall(Cell::new(0, 0)), CellClass::Unknown);
    }
}
