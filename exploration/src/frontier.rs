//! Frontier cells and their clusters.
//!
//! A frontier cell is a known free cell that is an immediate neighbour of an
//! unknown cell (Yamauchi 1998; Burgard et al. 2005, §II: "each already
//! explored cell that is an immediate neighbor of an unknown, unexplored
//! cell"). The planners count the four edge neighbours: a robot standing on
//! such a cell always sees the unknown one next to it, so visiting a
//! frontier always resolves it. With the eight-neighbourhood, a free cell
//! diagonal to the inside of a thick wall's corner would stay a frontier
//! forever, since no beam reaches that corner. The eight-neighbourhood is
//! kept for comparison with scipy's `binary_dilation` (the benchmarks).
//! Cells beyond the grid's edge are walls, not unknown. Clusters are the
//! 8-connected components of frontier cells (Yamauchi's frontier regions;
//! Bautin et al. 2011's frontiers F_j).

use crate::grid::{Cell, CellClass, CellRect, FREE_BELOW_PERCENT, GridFrame, NEIGHBOURS_8, OccupancyGrid, UNKNOWN};

/// Which neighbours of a free cell make it a frontier cell when unknown.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Adjacency {
    /// The four edge neighbours (the planners' choice).
    #[default]
    Edges,
    /// All eight neighbours.
    EdgesAndCorners,
}

impl Adjacency {
    fn offsets(self) -> &'static [(i32, i32)] {
        match self {
            Self::Edges => &NEIGHBOURS_8[..4],
            Self::EdgesAndCorners => &NEIGHBOURS_8,
        }
    }
}

/// Whether an on-grid cell is a frontier cell (edge adjacency).
pub fn is_frontier(grid: &OccupancyGrid, cell: Cell) -> bool {
    is_frontier_with(grid, cell, Adjacency::Edges)
}

/// Whether an on-grid cell is a frontier cell under `adjacency`.
pub fn is_frontier_with(grid: &OccupancyGrid, cell: Cell, adjacency: Adjacency) -> bool {
    grid.class(cell) == CellClass::Free
        && adjacency.offsets().iter().any(|&(dx, dy)| {
            let n = Cell::new(cell.x + dx, cell.y + dy);
            grid.frame().contains(n) && grid.value(n) == UNKNOWN
        })
}

/// The frontier of a grid as a mask, kept up to date cell by cell as patches
/// arrive so that the executive never rescans the whole grid per update.
#[derive(Debug, Clone)]
pub struct FrontierMap {
    frame: GridFrame,
    adjacency: Adjacency,
    mask: Vec<bool>,
    count: usize,
}

/// How an update moved the frontier.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct FrontierDelta {
    /// Cells that became frontier.
    pub added: usize,
    /// Cells that stopped being frontier.
    pub removed: usize,
}

impl FrontierMap {
    /// The frontier of `grid`, by one pass over every cell.
    ///
    /// Complexity: O(W·H).
    pub fn detect(grid: &OccupancyGrid) -> Self {
        Self::detect_with(grid, Adjacency::Edges)
    }

    /// The frontier of `grid` under `adjacency`, by one pass over every cell.
    ///
    /// Complexity: O(W·H).
    pub fn detect_with(grid: &OccupancyGrid, adjacency: Adjacency) -> Self {
        let frame = *grid.frame();
        let mask = frontier_mask_with(grid, adjacency);
        let count = mask.iter().filter(|&&f| f).count();
        Self { frame, adjacency, mask, count }
    }

    /// Recomputes the cells around `changed` (grown by one, since a cell's
    /// status depends on its neighbours) after the grid changed there.
    ///
    /// Complexity: O(area of `changed`).
    pub fn update(&mut self, grid: &OccupancyGrid, changed: CellRect) -> FrontierDelta {
        let mut delta = FrontierDelta::default();
        let Some(rect) = self.frame.clip(&changed.grown(1)) else {
            return delta;
        };
        for cell in rect.cells() {
            let i = self.frame.index(cell);
            let now = is_frontier_with(grid, cell, self.adjacency);
            if now != self.mask[i] {
                self.mask[i] = now;
                if now {
                    delta.added += 1;
                    self.count += 1;
                } else {
                    delta.removed += 1;
                    self.count -= 1;
                }
            }
        }
        delta
    }

    /// Number of frontier cells.
    pub fn len(&self) -> usize {
        self.count
    }

    /// Whether there is no frontier cell.
    pub fn is_empty(&self) -> bool {
        self.count == 0
    }

    /// Whether the cell at a row-major index is a frontier cell.
    pub fn contains_index(&self, index: usize) -> bool {
        self.mask[index]
    }

    /// Whether an on-grid cell is a frontier cell.
    pub fn contains(&self, cell: Cell) -> bool {
        self.frame.contains(cell) && self.mask[self.frame.index(cell)]
    }

    /// The mask, row-major.
    pub fn mask(&self) -> &[bool] {
        &self.mask
    }

    /// Every frontier cell, in row-major order.
    pub fn cells(&self) -> Vec<Cell> {
        self.cells_in_row_order().collect()
    }

    /// The frontier cells in row-major order, one at a time: for a reader
    /// that wants only the first few.
    pub fn cells_in_row_order(&self) -> impl Iterator<Item = Cell> + '_ {
        self.mask.iter().enumerate().filter(|(_, f)| **f).map(|(i, _)| self.frame.cell(i))
    }
}

/// The frontier mask of a grid (edge adjacency), row-major.
///
/// Complexity: O(W·H); interior cells take a branch-light path.
pub fn frontier_mask(grid: &OccupancyGrid) -> Vec<bool> {
    frontier_mask_with(grid, Adjacency::Edges)
}

/// The frontier mask of a grid under `adjacency`, row-major.
///
/// One pass over the rows; each interior row compares its cells and their
/// neighbours as shifted slices, which the compiler vectorizes.
///
/// Complexity: O(W·H).
pub fn frontier_mask_with(grid: &OccupancyGrid, adjacency: Adjacency) -> Vec<bool> {
    let frame = grid.frame();
    let (w, h) = (frame.width as usize, frame.height as usize);
    let cells = grid.cells();
    let mut mask = vec![false; cells.len()];
    if w < 3 || h < 3 {
        for (i, m) in mask.iter_mut().enumerate() {
            *m = is_frontier_with(grid, frame.cell(i), adjacency);
        }
        return mask;
    }
    let corners = adjacency == Adjacency::EdgesAndCorners;
    for y in 1..h - 1 {
        let here = &cells[y * w..(y + 1) * w];
        let up = &cells[(y + 1) * w..(y + 2) * w];
        let down = &cells[(y - 1) * w..y * w];
        let out = &mut mask[y * w + 1..(y + 1) * w - 1];
        let u = |v: u8| v == UNKNOWN;
        if corners {
            for (i, o) in out.iter_mut().enumerate() {
                let near = u(here[i])
                    | u(here[i + 2])
                    | u(up[i])
                    | u(up[i + 1])
                    | u(up[i + 2])
                    | u(down[i])
                    | u(down[i + 1])
                    | u(down[i + 2]);
                *o = near & (here[i + 1] < FREE_BELOW_PERCENT);
            }
        } else {
            for (i, o) in out.iter_mut().enumerate() {
                let near = u(here[i]) | u(here[i + 2]) | u(up[i + 1]) | u(down[i + 1]);
                *o = near & (here[i + 1] < FREE_BELOW_PERCENT);
            }
        }
    }
    // The border rows and columns, cell by cell.
    let border = (0..w)
        .flat_map(|x| [Cell::new(x as i32, 0), Cell::new(x as i32, h as i32 - 1)])
        .chain((1..h - 1).flat_map(|y| [Cell::new(0, y as i32), Cell::new(w as i32 - 1, y as i32)]));
    for cell in border {
        mask[frame.index(cell)] = is_frontier_with(grid, cell, adjacency);
    }
    mask
}

/// An 8-connected group of frontier cells.
#[derive(Debug, Clone, PartialEq)]
pub struct FrontierCluster {
    /// Its cells, in the order the flood fill met them.
    pub cells: Vec<Cell>,
    /// Mean cell position (cell units).
    pub centroid: (f64, f64),
    /// The member cell closest to the centroid: a target a robot can stand
    /// on (the centroid of a curved frontier may lie in unknown space).
    pub representative: Cell,
}

impl FrontierCluster {
    /// Number of cells.
    pub fn len(&self) -> usize {
        self.cells.len()
    }

    /// Whether the cluster has no cell.
    pub fn is_empty(&self) -> bool {
        self.cells.is_empty()
    }

    /// The cluster restricted to the cells `keep` accepts, its centroid and
    /// representative recomputed; `None` when no cell is kept. The executive
    /// takes out cells an operator forbade before a policy sees the frontier
    /// (Simmons et al. 2000, §4.2: operators steer the exploration).
    pub fn retain(&self, keep: impl Fn(Cell) -> bool) -> Option<Self> {
        let cells: Vec<Cell> = self.cells.iter().copied().filter(|c| keep(*c)).collect();
        if cells.len() == self.cells.len() {
            Some(self.clone())
        } else if cells.is_empty() {
            None
        } else {
            Some(cluster_from_cells(cells))
        }
    }
}

/// Groups frontier cells into 8-connected clusters, dropping clusters of
/// fewer than `min_size` cells (spurious single-cell frontiers behind sensor
/// noise). Clusters come out in row-major order of their first cell.
///
/// Complexity: O(W·H) for the scan plus O(frontier) for the flood fills.
pub fn clusters(frontier: &FrontierMap, min_size: usize) -> Vec<FrontierCluster> {
    let frame = frontier.frame;
    let mut seen = vec![false; frame.len()];
    let mut out = Vec::new();
    let mut stack = Vec::new();
    for (start, &is_frontier) in frontier.mask.iter().enumerate() {
        if !is_frontier || seen[start] {
            continue;
        }
        seen[start] = true;
        stack.push(start);
        let mut cells = Vec::new();
        while let Some(i) = stack.pop() {
            let cell = frame.cell(i);
            cells.push(cell);
            for (dx, dy) in NEIGHBOURS_8 {
                let n = Cell::new(cell.x + dx, cell.y + dy);
                if frame.contains(n) {
                    let j = frame.index(n);
                    if frontier.mask[j] && !seen[j] {
                        seen[j] = true;
                        stack.push(j);
                    }
                }
            }
        }
        if cells.len() >= min_size.max(1) {
            out.push(cluster_from_cells(cells));
        }
    }
    out
}

fn cluster_from_cells(cells: Vec<Cell>) -> FrontierCluster {
    let n = cells.len() as f64;
    let (sx, sy) = cells.iter().fold((0.0, 0.0), |(sx, sy), c| (sx + f64::from(c.x), sy + f64::from(c.y)));
    let centroid = (sx / n, sy / n);
    let representative = *cells
        .iter()
        .min_by(|a, b| {
            let da = (f64::from(a.x) - centroid.0).powi(2) + (f64::from(a.y) - centroid.1).powi(2);
            let db = (f64::from(b.x) - centroid.0).powi(2) + (f64::from(b.y) - centroid.1).powi(2);
            da.total_cmp(&db).then(a.cmp(b))
        })
        .unwrap_or(&cells[0]);
    FrontierCluster { cells, centroid, representative }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::grid::testing::grid_from_picture;

    #[test]
    fn frontier_cells_touch_unknown_space_and_the_border_is_not_unknown() {
        let grid = grid_from_picture(&[
            "....??", //
            "....??", //
            "##..##", //
            "......", //
        ]);
        let frontier = FrontierMap::detect(&grid);
        let cells = frontier.cells();
        // (3,3) and (3,2) touch unknown cells at their right edge.
        assert_eq!(cells, vec![Cell::new(3, 2), Cell::new(3, 3)]);
        assert!(!cells.contains(&Cell::new(0, 3)), "the grid edge is a wall, not unknown");
        // (3,1) touches unknown (4,2) only at a corner.
        let with_corners = frontier_mask_with(&grid, Adjacency::EdgesAndCorners);
        assert!(with_corners[grid.frame().index(Cell::new(3, 1))]);
        assert_eq!(with_corners.iter().filter(|&&f| f).count(), 3);
        assert_eq!(frontier_mask(&grid).iter().filter(|&&f| f).count(), 2);
    }

    #[test]
    fn the_unseeable_inside_of_a_wall_corner_is_no_frontier() {
        // (1,1) is free; the wall's inside cell (2,2) is unknown forever,
        // since the beams stop at the wall cells (2,1) and (1,2) around it.
        let grid = grid_from_picture(&[
            "####", //
            "##?#", //
            "#.##", //
            "####", //
        ]);
        assert!(!is_frontier(&grid, Cell::new(1, 1)));
        assert!(is_frontier_with(&grid, Cell::new(1, 1), Adjacency::EdgesAndCorners));
    }

    proptest::proptest! {
        #![proptest_config(crate::testing::seeded_proptest(128))]
        /// The row-sliced mask agrees with the definition, cell by cell.
        #[test]
        fn the_fast_mask_matches_the_definition(
            width in 1u32..30,
            height in 1u32..30,
            seed in 0u64..1_000_000,
            corners in proptest::bool::ANY,
        ) {
            let frame = GridFrame::new(1.0, crate::math::Point2::origin(), width, height);
            let mut rng = crate::rng::SplitMix64::new(seed);
            let cells = (0..frame.len())
                .map(|_| match rng.below(4) { 0 => UNKNOWN, 1 => 95, 2 => 50, _ => 10 })
                .collect();
            let grid = OccupancyGrid::from_cells(frame, cells);
            let adjacency = if corners { Adjacency::EdgesAndCorners } else { Adjacency::Edges };
            let mask = frontier_mask_with(&grid, adjacency);
            for cell in frame.bounds().cells() {
                proptest::prop_assert_eq!(mask[frame.index(cell)], is_frontier_with(&grid, cell, adjacency), "{:?}", cell);
            }
        }
    }

    #[test]
    fn incremental_update_matches_a_full_scan() {
        let mut grid = grid_from_picture(&[
            "????????", //
            "?......?", //
            "?......?", //
            "????????", //
        ]);
        let mut frontier = FrontierMap::detect(&grid);
        assert_eq!(frontier.len(), 12);
        // Reveal the bottom row as wall: the cells above it stop being
        // frontier, except those still next to unknown corners.
        for x in 0..8 {
            grid.set(Cell::new(x, 0), 95);
        }
        let delta = frontier.update(&grid, CellRect::new(0, 0, 8, 1));
        let full = FrontierMap::detect(&grid);
        assert_eq!(frontier.mask(), full.mask());
        assert_eq!(frontier.len(), full.len());
        assert_eq!(delta.removed, 4);
        assert_eq!(delta.added, 0);
    }

    #[test]
    fn clusters_are_eight_connected_and_small_ones_are_dropped() {
        let grid = grid_from_picture(&[
            "?.....?", //
            "?.....?", //
            "#######", //
            "?#.....", //
        ]);
        let frontier = FrontierMap::detect(&grid);
        let all = clusters(&frontier, 1);
        // The left pair (1,3),(1,2) and the right pair (5,3),(5,2); (2,0)
        // touches no unknown cell: (0,0) is two cells away.
        assert_eq!(all.len(), 2, "{all:?}");
        assert!(all.iter().all(|c| c.len() == 2));
        assert!(clusters(&frontier, 3).is_empty());
        let left = &all[0];
        assert!(left.cells.contains(&left.representative));
    }
}
