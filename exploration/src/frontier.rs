//! Frontier cells and their clusters.
//!
//! A frontier cell is a known free cell with at least one unknown cell among
//! its eight neighbours (Yamauchi 1998; Burgard et al. 2005, §II: "each
//! already explored cell that is an immediate neighbor of an unknown,
//! unexplored cell"). Cells beyond the grid's edge are walls, not unknown.
//! Clusters are the 8-connected components of frontier cells (Yamauchi's
//! frontier regions; Bautin et al. 2011's frontiers F_j).

use crate::grid::{
    Cell, CellClass, CellRect, GridFrame, NEIGHBOURS_8, OccupancyGrid, UNKNOWN, classify,
};

/// Whether an on-grid cell is a frontier cell.
pub fn is_frontier(grid: &OccupancyGrid, cell: Cell) -> bool {
    grid.class(cell) == CellClass::Free
        && NEIGHBOURS_8.iter().any(|&(dx, dy)| {
            let n = Cell::new(cell.x + dx, cell.y + dy);
            grid.frame().contains(n) && grid.value(n) == UNKNOWN
        })
}

/// The frontier of a grid as a mask, kept up to date cell by cell as patches
/// arrive so that the executive never rescans the whole grid per update.
#[derive(Debug, Clone)]
pub struct FrontierMap {
    frame: GridFrame,
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
        let frame = *grid.frame();
        let mask = frontier_mask(grid);
        let count = mask.iter().filter(|&&f| f).count();
        Self { frame, mask, count }
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
            let now = is_frontier(grid, cell);
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
        self.mask
            .iter()
            .enumerate()
            .filter(|(_, f)| **f)
            .map(|(i, _)| self.frame.cell(i))
            .collect()
    }
}

/// The frontier mask of a grid, row-major.
///
/// Complexity: O(W·H); interior cells take a branch-light path.
pub fn frontier_mask(grid: &OccupancyGrid) -> Vec<bool> {
    let frame = grid.frame();
    let (w, h) = (frame.width as usize, frame.height as usize);
    let cells = grid.cells();
    let mut mask = vec![false; cells.len()];
    for y in 0..h {
        let row = y * w;
        for x in 0..w {
            let i = row + x;
            if classify(cells[i]) != CellClass::Free {
                continue;
            }
            let interior = x > 0 && y > 0 && x + 1 < w && y + 1 < h;
            mask[i] = if interior {
                let up = i + w;
                let down = i - w;
                cells[i - 1] == UNKNOWN
                    || cells[i + 1] == UNKNOWN
                    || cells[up] == UNKNOWN
                    || cells[down] == UNKNOWN
                    || cells[up - 1] == UNKNOWN
                    || cells[up + 1] == UNKNOWN
                    || cells[down - 1] == UNKNOWN
                    || cells[down + 1] == UNKNOWN
            } else {
                is_frontier(grid, Cell::new(x as i32, y as i32))
            };
        }
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
    let (sx, sy) = cells.iter().fold((0.0, 0.0), |(sx, sy), c| {
        (sx + f64::from(c.x), sy + f64::from(c.y))
    });
    let centroid = (sx / n, sy / n);
    let representative = *cells
        .iter()
        .min_by(|a, b| {
            let da = (f64::from(a.x) - centroid.0).powi(2) + (f64::from(a.y) - centroid.1).powi(2);
            let db = (f64::from(b.x) - centroid.0).powi(2) + (f64::from(b.y) - centroid.1).powi(2);
            da.total_cmp(&db).then(a.cmp(b))
        })
        .unwrap_or(&cells[0]);
    FrontierCluster {
        cells,
        centroid,
        representative,
    }
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
        // Row 3 (top): x=3 touches '?' at x=4. Row 2: x=3 touches (4,3) and (4,2).
        // Row 1: x=2,3 touch (?) diagonally? (3,1) neighbours (4,2) which is '?'.
        assert!(cells.contains(&Cell::new(3, 3)));
        assert!(cells.contains(&Cell::new(3, 2)));
        assert!(cells.contains(&Cell::new(3, 1)));
        assert!(
            !cells.contains(&Cell::new(0, 3)),
            "the grid edge is a wall, not unknown"
        );
        assert!(!cells.contains(&Cell::new(2, 1)));
        assert_eq!(cells.len(), 3);
        assert_eq!(frontier_mask(&grid).iter().filter(|&&f| f).count(), 3);
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
            "#.....#", //
            "#######", //
            "?#.....", //
        ]);
        let frontier = FrontierMap::detect(&grid);
        let all = clusters(&frontier, 1);
        // Top-left pair (1,3),(1,2) touch '?' (0,3); top-right pair; bottom (2,0) touches (0,0)? no:
        // (2,0) neighbours (1,1)# ,(1,0)#; not unknown.
        assert_eq!(all.len(), 2, "{all:?}");
        assert!(all.iter().all(|c| c.len() == 2));
        assert!(clusters(&frontier, 3).is_empty());
        let left = &all[0];
        assert!(left.cells.contains(&left.representative));
    }
}
