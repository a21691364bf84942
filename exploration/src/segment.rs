//! Segmentation of the explored map into rooms and corridors.
//!
//! Wurm, Stachniss & Burgard 2008, §IV: the Voronoi graph of the explored
//! free space is found by skeletonizing its Euclidean distance transform;
//! the graph is cut at critical points, nodes of degree 2 where the
//! clearance (distance to the closest obstacle) is a local minimum, as in
//! doorways (Thrun 1998), keeping only those that lead from known into
//! unknown space; the free space splits into segments between them.
//!
//! Wurm et al. further ask a critical point to neighbour a junction of degree
//! 3. A thinned pixel skeleton loses the short spurs into room corners that
//! make those junctions in a true Voronoi graph (a rectangular room thins to
//! a line), so that test would reject most doors; instead the clearance must
//! rise by a margin on both sides of the point along the skeleton, which
//! rejects the same false positives: the small wiggles of clearance along
//! corridors.
//!
//! - [`distance_transform`]: exact squared Euclidean distance transform
//!   (Felzenszwalb & Huttenlocher 2012), linear time.
//! - [`skeletonize`]: distance-ordered homotopic thinning (Pudney 1998).
//! - [`segment`]: critical points and segments of an occupancy grid.
//! - [`segment_complete`]: the same for a finished map, every passage cut.
//! - [`given`]: the segments of rooms given with the mission.

use std::collections::VecDeque;

use crate::grid::{Cell, CellClass, CellRect, GridFrame, NEIGHBOURS_8, OccupancyGrid};
use crate::math::Point2;

mod skeleton;

pub use skeleton::{distance_transform, padded_skeleton, skeletonize};

/// A cut of the free space at a narrow passage.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CriticalPoint {
    /// The skeleton cell.
    pub cell: Cell,
    /// Its distance to the closest obstacle, cells.
    pub clearance: f64,
}

/// A segment of the explored free space.
#[derive(Debug, Clone, PartialEq)]
pub struct Segment {
    /// Its label in [`Segmentation::labels`] (from 1).
    pub id: u32,
    /// Number of free cells.
    pub cells: usize,
    /// Its bounding rectangle.
    pub bounds: CellRect,
    /// Frontier cells inside it (unexplored space it leads to).
    pub frontier: Vec<Cell>,
}

/// The segments of a map and the critical points between them.
#[derive(Debug, Clone, PartialEq)]
pub struct Segmentation {
    /// The grid it was computed on.
    pub frame: GridFrame,
    /// Per cell, row-major: the segment label, 0 outside the free space.
    pub labels: Vec<u32>,
    /// The segments, by label.
    pub segments: Vec<Segment>,
    /// The cuts kept between segments.
    pub critical_points: Vec<CriticalPoint>,
}

impl Segmentation {
    /// The segment of a cell, if it has one.
    pub fn segment_of(&self, cell: Cell) -> Option<u32> {
        if !self.frame.contains(cell) {
            return None;
        }
        let label = self.labels[self.frame.index(cell)];
        (label != 0).then_some(label)
    }
}

/// Segments the explored free space of `grid` (Wurm et al. 2008, §IV).
///
/// Obstacles, unknown and uncertain cells, and the grid's edge bound the
/// free space. A skeleton cell of degree 2 is a critical point when, along
/// the skeleton on both sides, the clearance rises by at least `min_drop`
/// cells; of nearby critical points the narrowest stays. A critical point
/// cuts the free space with a disc of its clearance; it is kept only if a
/// segment beside it holds frontier cells, i.e. it leads from known into
/// unknown space. Segments smaller than `min_cells` merge into a neighbour.
///
/// Complexity: O(W·H), plus a short walk along the skeleton per local minimum.
pub fn segment(grid: &OccupancyGrid, frontier: &[Cell], min_drop: f64, min_cells: usize) -> Segmentation {
    segment_keeping(grid, frontier, min_drop, min_cells, Cuts::IntoUnknown)
}

/// The `segmentation` policy's default for how far a critical point's
/// clearance lies below both its sides, metres.
pub const DEFAULT_MIN_DROP_M: f64 = 0.2;
/// The `segmentation` policy's default for the smallest segment, square
/// metres (smaller ones merge into a neighbour).
pub const DEFAULT_MIN_SEGMENT_M2: f64 = 1.0;

/// Segments a completely known map: as [`segment`], but every narrow
/// passage cuts, since no frontier tells which ones lead somewhere new. The
/// rooms and corridors of a building whose map is finished, for missions
/// that plan on a given segmentation (Wurm et al. 2008, §VI).
pub fn segment_complete(grid: &OccupancyGrid, min_drop: f64, min_cells: usize) -> Segmentation {
    segment_keeping(grid, &[], min_drop, min_cells, Cuts::All)
}

/// Which critical points cut the free space.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Cuts {
    /// Those beside a segment that holds frontier (the online segmentation).
    IntoUnknown,
    /// All of them (a completely known map).
    All,
}

fn segment_keeping(
    grid: &OccupancyGrid,
    frontier: &[Cell],
    min_drop: f64,
    min_cells: usize,
    cuts: Cuts,
) -> Segmentation {
    let frame = *grid.frame();
    let free: Vec<bool> = grid.cells().iter().map(|&v| crate::grid::classify(v) == CellClass::Free).collect();
    let Some(crop) = Crop::around(&frame, &free) else {
        return Segmentation { frame, labels: vec![0; frame.len()], segments: Vec::new(), critical_points: Vec::new() };
    };
    let frontier: Vec<Cell> = frontier.iter().map(|&c| crop.to_local(c)).collect();
    crop.to_global(segment_free(crop.frame, &crop.cut(&free), &frontier, min_drop, min_cells, cuts))
}

/// The bounding box of the free cells, where segmenting happens: early in
/// a mission most of the grid is unknown (a tenth of `stage_hospital`
/// known: 5 % of its cells in the box, half known: 31 %).
///
/// The segments are exactly those of the whole grid: everything outside the
/// box is background, as the grid's cells there are, and no cell inside is
/// nearer to one of those than to the background ring around the box
/// (clamping a cell into the ring brings it no farther), so the distances
/// are the same; the box keeps the grid's row-major order, so thinning,
/// labelling and the lists run in the same order. Frontier cells off the
/// box are not free and counted nowhere, here as before.
struct Crop {
    /// The box, in the grid's cells.
    rect: CellRect,
    /// The grid's frame, whose cell (0, 0) this is.
    whole: GridFrame,
    /// A frame over the box only, from its lower-left cell.
    frame: GridFrame,
}

impl Crop {
    /// The box around the `true` cells of `mask` (one per cell of `whole`);
    /// `None` when there are none.
    fn around(whole: &GridFrame, mask: &[bool]) -> Option<Self> {
        let w = whole.width as usize;
        let rows: Vec<usize> =
            (0..whole.height as usize).filter(|&y| mask[y * w..(y + 1) * w].contains(&true)).collect();
        let (&bottom, &top) = (rows.first()?, rows.last()?);
        let left = rows.iter().filter_map(|&y| mask[y * w..(y + 1) * w].iter().position(|&m| m)).min()?;
        let right = rows.iter().filter_map(|&y| mask[y * w..(y + 1) * w].iter().rposition(|&m| m)).max()?;
        let rect = CellRect::new(left as i32, bottom as i32, (right - left + 1) as u32, (top - bottom + 1) as u32);
        let corner = Point2::new(
            whole.origin.x + f64::from(rect.x) * whole.resolution,
            whole.origin.y + f64::from(rect.y) * whole.resolution,
        );
        let frame = GridFrame::new(whole.resolution, corner, rect.width, rect.height);
        Some(Self { rect, whole: *whole, frame })
    }

    /// `values`, one per cell of the whole grid, inside the box.
    fn cut<T: Copy>(&self, values: &[T]) -> Vec<T> {
        let (x, w) = (self.rect.x as usize, self.rect.width as usize);
        (self.rect.y..self.rect.y_end())
            .flat_map(|y| {
                let from = y as usize * self.whole.width as usize + x;
                values[from..from + w].iter().copied()
            })
            .collect()
    }

    fn to_local(&self, cell: Cell) -> Cell {
        Cell::new(cell.x - self.rect.x, cell.y - self.rect.y)
    }

    fn to_global_cell(&self, cell: Cell) -> Cell {
        Cell::new(cell.x + self.rect.x, cell.y + self.rect.y)
    }

    /// A segmentation of the box, over the whole grid.
    fn to_global(&self, inside: Segmentation) -> Segmentation {
        let mut labels = vec![0u32; self.whole.len()];
        let w = self.rect.width as usize;
        for (row, local) in inside.labels.chunks_exact(w).enumerate() {
            let from = (self.rect.y as usize + row) * self.whole.width as usize + self.rect.x as usize;
            labels[from..from + w].copy_from_slice(local);
        }
        let segments = inside
            .segments
            .into_iter()
            .map(|s| Segment {
                bounds: CellRect { x: s.bounds.x + self.rect.x, y: s.bounds.y + self.rect.y, ..s.bounds },
                frontier: s.frontier.into_iter().map(|c| self.to_global_cell(c)).collect(),
                ..s
            })
            .collect();
        let critical_points = inside
            .critical_points
            .into_iter()
            .map(|cp| CriticalPoint { cell: self.to_global_cell(cp.cell), ..cp })
            .collect();
        Segmentation { frame: self.whole, labels, segments, critical_points }
    }
}

/// [`segment_keeping`] over `frame`, whose free cells are `free`.
fn segment_free(
    frame: GridFrame,
    free: &[bool],
    frontier: &[Cell],
    min_drop: f64,
    min_cells: usize,
    cuts: Cuts,
) -> Segmentation {
    let (w, h) = (frame.width as usize, frame.height as usize);
    // The grid's edge is a wall: both are padded with a background border.
    let pw = w + 2;
    let (skeleton, squared) = padded_skeleton(free, w, h);
    let clearance = |x: usize, y: usize| f64::from(squared[(y + 1) * pw + x + 1]).sqrt();
    let on_skeleton = |x: i64, y: i64| {
        x >= 0 && y >= 0 && (x as usize) < w && (y as usize) < h && skeleton[(y as usize + 1) * pw + x as usize + 1]
    };
    let ring: [(i64, i64); 8] = [(0, 1), (1, 1), (1, 0), (1, -1), (0, -1), (-1, -1), (-1, 0), (-1, 1)];
    let crossing = |x: i64, y: i64| {
        (0..8)
            .filter(|&k| {
                let (ax, ay) = ring[k];
                let (bx, by) = ring[(k + 1) % 8];
                !on_skeleton(x + ax, y + ay) && on_skeleton(x + bx, y + by)
            })
            .count()
    };
    // Critical points: skeleton cells of degree 2 (crossing number 2) whose
    // clearance is a local minimum: along the skeleton, within `reach`
    // cells on each side, the clearance rises by at least `min_drop`.
    let reach = (3.0 * min_drop).max(10.0) as usize;
    let mut candidates: Vec<CriticalPoint> = Vec::new();
    for y in 0..h as i64 {
        for x in 0..w as i64 {
            if !on_skeleton(x, y) || crossing(x, y) != 2 {
                continue;
            }
            let here = clearance(x as usize, y as usize);
            let neighbours: Vec<(i64, i64)> =
                ring.iter().map(|&(dx, dy)| (x + dx, y + dy)).filter(|&(nx, ny)| on_skeleton(nx, ny)).collect();
            // A cheap first test: no skeleton neighbour is narrower.
            if neighbours.iter().any(|&(nx, ny)| clearance(nx as usize, ny as usize) < here) {
                continue;
            }
            // Split the neighbours into the two sides (ring order: runs of skeleton cells).
            let mut sides: Vec<Vec<(i64, i64)>> = Vec::new();
            for k in 0..8 {
                let (dx, dy) = ring[k];
                let (px, py) = ring[(k + 7) % 8];
                if on_skeleton(x + dx, y + dy) {
                    if !on_skeleton(x + px, y + py) || sides.is_empty() {
                        sides.push(Vec::new());
                    }
                    if let Some(side) = sides.last_mut() {
                        side.push((x + dx, y + dy));
                    }
                }
            }
            if sides.len() > 2 {
                // The first and last runs wrap around the ring.
                let last = sides.pop().unwrap_or_default();
                sides[0].extend(last);
            }
            if sides.len() != 2 {
                continue;
            }
            let widest_within_reach = |start: &[(i64, i64)]| {
                let mut visited = std::collections::HashSet::new();
                visited.insert((x, y));
                let mut queue: VecDeque<((i64, i64), usize)> = start.iter().map(|&c| (c, 1)).collect();
                for &c in start {
                    visited.insert(c);
                }
                let mut widest = f64::NEG_INFINITY;
                while let Some(((cx, cy), d)) = queue.pop_front() {
                    widest = widest.max(clearance(cx as usize, cy as usize));
                    if d >= reach {
                        continue;
                    }
                    for &(dx, dy) in &ring {
                        let n = (cx + dx, cy + dy);
                        if on_skeleton(n.0, n.1) && visited.insert(n) {
                            queue.push_back((n, d + 1));
                        }
                    }
                }
                widest
            };
            if sides.iter().all(|side| widest_within_reach(side) - here >= min_drop) {
                candidates.push(CriticalPoint { cell: Cell::new(x as i32, y as i32), clearance: here });
            }
        }
    }
    // One critical point per narrow passage: the narrowest, then the first.
    candidates.sort_by(|a, b| {
        a.clearance.total_cmp(&b.clearance).then(a.cell.y.cmp(&b.cell.y)).then(a.cell.x.cmp(&b.cell.x))
    });
    let mut chosen: Vec<CriticalPoint> = Vec::new();
    for c in candidates {
        if chosen.iter().all(|k| k.cell.distance(c.cell) > 2.0 * (k.clearance + c.clearance).max(2.0)) {
            chosen.push(c);
        }
    }
    let candidates = chosen;
    let frontier_mask = mask_of(&frame, frontier);
    // Cut at every candidate, then keep only the cuts that lead into unknown space.
    let first = split(&frame, free, &candidates, &frontier_mask, min_cells);
    let kept: Vec<CriticalPoint> = candidates
        .iter()
        .filter(|cp| {
            cuts == Cuts::All
                || first
                    .adjacent_labels(cp)
                    .iter()
                    .any(|&l| first.frontier_counts.get(l as usize).copied().unwrap_or(0) > 0)
        })
        .copied()
        .collect();
    let final_split =
        if kept.len() == candidates.len() { first } else { split(&frame, free, &kept, &frontier_mask, min_cells) };
    let segments = segments_of(&frame, &final_split.labels, final_split.count, &frontier_mask);
    Segmentation { frame, labels: final_split.labels, segments, critical_points: kept }
}

/// The segmentation of what `grid` knows by rooms given with the mission
/// (Wurm et al. 2008, §VI: "we assumed a given segmentation of the
/// environment into rooms and corridors in our simulation experiments").
/// `rooms` holds one label per cell of the grid's frame, row-major, 0 for
/// none.
///
/// A segment is a given room as far as it is known: the known free cells
/// with its label, renumbered densely from 1 in the order of the given
/// labels. Frontier cells that no room covers form one segment of their
/// own, so no frontier is lost to a gap in the labels. `None` when `rooms`
/// does not hold one label per cell.
pub fn given(grid: &OccupancyGrid, rooms: &[u32], frontier: &[Cell]) -> Option<Segmentation> {
    let frame = *grid.frame();
    if rooms.len() != frame.len() {
        return None;
    }
    let frontier_mask = mask_of(&frame, frontier);
    // Keys above every u32 label stand for "frontier outside any room".
    const OUTSIDE: u64 = 1 << 32;
    let key = |i: usize| -> Option<u64> {
        let in_space = frontier_mask[i] || crate::grid::classify(grid.cells()[i]) == CellClass::Free;
        match rooms[i] {
            _ if !in_space => None,
            0 if frontier_mask[i] => Some(OUTSIDE),
            0 => None,
            room => Some(u64::from(room)),
        }
    };
    let mut keys: Vec<u64> = Vec::new();
    let mut last = None;
    for i in 0..frame.len() {
        let k = key(i);
        if k.is_some() && k != last {
            keys.extend(k);
        }
        last = k;
    }
    keys.sort_unstable();
    keys.dedup();
    let labels: Vec<u32> = (0..frame.len())
        .map(|i| key(i).map_or(0, |k| keys.binary_search(&k).map_or(0, |position| position as u32 + 1)))
        .collect();
    let segments = segments_of(&frame, &labels, keys.len(), &frontier_mask);
    Some(Segmentation { frame, labels, segments, critical_points: Vec::new() })
}

/// A mask of `cells` over `frame`; cells off the frame are left out.
fn mask_of(frame: &GridFrame, cells: &[Cell]) -> Vec<bool> {
    let mut mask = vec![false; frame.len()];
    for c in cells {
        if frame.contains(*c) {
            mask[frame.index(*c)] = true;
        }
    }
    mask
}

/// The segments `1..=count` of dense `labels`: their cells, bounds and
/// frontier cells.
fn segments_of(frame: &GridFrame, labels: &[u32], count: usize, frontier_mask: &[bool]) -> Vec<Segment> {
    let mut segments: Vec<Segment> = (1..count as u32 + 1)
        .map(|id| Segment { id, cells: 0, bounds: CellRect::new(0, 0, 0, 0), frontier: Vec::new() })
        .collect();
    for (i, &label) in labels.iter().enumerate() {
        if label == 0 {
            continue;
        }
        let cell = frame.cell(i);
        let s = &mut segments[label as usize - 1];
        s.bounds = if s.cells == 0 { CellRect::new(cell.x, cell.y, 1, 1) } else { s.bounds.including(cell) };
        s.cells += 1;
        if frontier_mask[i] {
            s.frontier.push(cell);
        }
    }
    segments
}

struct Split {
    frame: GridFrame,
    labels: Vec<u32>,
    count: usize,
    /// Frontier cells per label (index 0 unused).
    frontier_counts: Vec<usize>,
}

impl Split {
    /// The labels of the cells just around a critical point's cut.
    fn adjacent_labels(&self, cp: &CriticalPoint) -> Vec<u32> {
        let r = cp.clearance.ceil() as i32 + 2;
        let mut labels: Vec<u32> = CellRect::new(cp.cell.x - r, cp.cell.y - r, (2 * r + 1) as u32, (2 * r + 1) as u32)
            .cells()
            .filter(|c| self.frame.contains(*c))
            .map(|c| self.labels[self.frame.index(c)])
            .filter(|&l| l != 0)
            .collect();
        labels.sort_unstable();
        labels.dedup();
        labels
    }
}

/// Labels the free cells minus the cuts, then gives the cut cells (and
/// segments below `min_cells`) to their neighbours.
fn split(frame: &GridFrame, free: &[bool], cuts: &[CriticalPoint], frontier: &[bool], min_cells: usize) -> Split {
    let mut blocked = vec![false; free.len()];
    for cp in cuts {
        let r = cp.clearance + 1.0;
        let reach = r.ceil() as i32;
        for dy in -reach..=reach {
            for dx in -reach..=reach {
                let c = Cell::new(cp.cell.x + dx, cp.cell.y + dy);
                if frame.contains(c) && f64::from(dx * dx + dy * dy) <= r * r {
                    blocked[frame.index(c)] = true;
                }
            }
        }
    }
    let mut labels = vec![0u32; free.len()];
    let mut sizes = vec![0usize];
    for start in 0..free.len() {
        if !free[start] || blocked[start] || labels[start] != 0 {
            continue;
        }
        let id = sizes.len() as u32;
        let mut size = 0;
        let mut stack = vec![start];
        labels[start] = id;
        while let Some(i) = stack.pop() {
            size += 1;
            let c = frame.cell(i);
            for (dx, dy) in &NEIGHBOURS_8[..4] {
                let n = Cell::new(c.x + dx, c.y + dy);
                if frame.contains(n) {
                    let j = frame.index(n);
                    if free[j] && !blocked[j] && labels[j] == 0 {
                        labels[j] = id;
                        stack.push(j);
                    }
                }
            }
        }
        sizes.push(size);
    }
    // Small segments give their cells back: unlabel them, then grow every
    // big segment into the unlabelled free cells, breadth first.
    for l in labels.iter_mut() {
        if *l != 0 && sizes[*l as usize] < min_cells {
            *l = 0;
        }
    }
    let mut queue: VecDeque<usize> = (0..free.len()).filter(|&i| labels[i] != 0).collect();
    while let Some(i) = queue.pop_front() {
        let c = frame.cell(i);
        for (dx, dy) in &NEIGHBOURS_8[..4] {
            let n = Cell::new(c.x + dx, c.y + dy);
            if frame.contains(n) {
                let j = frame.index(n);
                if free[j] && labels[j] == 0 {
                    labels[j] = labels[i];
                    queue.push_back(j);
                }
            }
        }
    }
    // Renumber densely from 1.
    let mut renumber = vec![0u32; sizes.len()];
    let mut count = 0usize;
    for l in labels.iter_mut() {
        if *l == 0 {
            continue;
        }
        if renumber[*l as usize] == 0 {
            count += 1;
            renumber[*l as usize] = count as u32;
        }
        *l = renumber[*l as usize];
    }
    let mut frontier_counts = vec![0usize; count + 1];
    for (i, &l) in labels.iter().enumerate() {
        if l != 0 && frontier[i] {
            frontier_counts[l as usize] += 1;
        }
    }
    Split { frame: *frame, labels, count, frontier_counts }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::grid::testing::grid_from_picture;

    #[test]
    fn a_door_between_two_rooms_is_a_critical_point() {
        // Two rooms joined by a one-cell door; unknown space beyond the right room.
        let grid = grid_from_picture(&[
            "###################?", //
            "#.......#.........#?", //
            "#.......#..........?", //
            "#.......#.........#?", //
            "#..................#", //
            "#.......#.........#?", //
            "#.......#.........#?", //
            "#.......#.........#?", //
            "###################?", //
        ]);
        let frontier = crate::frontier::FrontierMap::detect(&grid).cells();
        assert!(!frontier.is_empty());
        let s = segment(&grid, &frontier, 1.0, 4);
        assert_eq!(s.segments.len(), 2, "{:?}", s.critical_points);
        let left = s.segment_of(Cell::new(2, 4)).unwrap();
        let right = s.segment_of(Cell::new(15, 4)).unwrap();
        assert_ne!(left, right);
        assert_eq!(s.critical_points.len(), 1);
        let door = s.critical_points[0].cell;
        assert!((7..=9).contains(&door.x) && door.y == 4, "{door:?}");
        assert!(!s.segments[right as usize - 1].frontier.is_empty());
    }

    #[test]
    fn a_cut_that_leads_nowhere_unknown_is_dropped() {
        // The same two rooms, fully explored: no frontier, one segment.
        let grid = grid_from_picture(&[
            "####################", //
            "#.......#.........##", //
            "#.......#.........##", //
            "#.......#.........##", //
            "#..................#", //
            "#.......#.........##", //
            "#.......#.........##", //
            "#.......#.........##", //
            "####################", //
        ]);
        let s = segment(&grid, &[], 1.0, 4);
        assert_eq!(s.segments.len(), 1);
        assert!(s.critical_points.is_empty());
        // A finished map keeps every cut: the two rooms.
        let complete = segment_complete(&grid, 1.0, 4);
        assert_eq!(complete.segments.len(), 2, "{:?}", complete.critical_points);
        assert_ne!(complete.segment_of(Cell::new(2, 4)), complete.segment_of(Cell::new(15, 4)));
    }

    #[test]
    fn given_rooms_are_renumbered_and_frontier_outside_them_is_kept() {
        let grid = grid_from_picture(&[
            "#########", //
            "?.......?", //
            "#########", //
        ]);
        let frame = *grid.frame();
        // Rooms 7 (x < 4) and 3 (4 ≤ x < 7); the right end's cells carry no room.
        let rooms: Vec<u32> = (0..frame.len())
            .map(|i| match frame.cell(i).x {
                0..4 => 7,
                4..7 => 3,
                _ => 0,
            })
            .collect();
        let frontier = crate::frontier::FrontierMap::detect(&grid).cells();
        let s = given(&grid, &rooms, &frontier).unwrap();
        // In the order of the given labels: room 3, room 7, then the frontier outside.
        assert_eq!(s.segment_of(Cell::new(5, 1)), Some(1));
        assert_eq!(s.segment_of(Cell::new(2, 1)), Some(2));
        assert_eq!(s.segment_of(Cell::new(7, 1)), Some(3), "the right end's frontier is a segment of its own");
        assert_eq!(s.segment_of(Cell::new(6, 1)), Some(1));
        assert_eq!(s.segments.len(), 3);
        let in_segments: usize = s.segments.iter().map(|seg| seg.frontier.len()).sum();
        assert_eq!(in_segments, frontier.len(), "every frontier cell is in a segment");
        assert_eq!(s.segment_of(Cell::new(0, 0)), None, "walls belong to no segment");
        assert!(given(&grid, &rooms[1..], &frontier).is_none());
    }

    /// Rooms joined by corridors, walled, on an unknown background: a known
    /// window of a larger grid, placed anywhere in it, with rooms running
    /// into the window's edge where the frontier is.
    fn rooms_in_a_window(seed: u64) -> OccupancyGrid {
        let mut rng = crate::rng::SplitMix64::new(seed);
        let (w, h) = (40 + rng.below(30) as i32, 30 + rng.below(20) as i32);
        let mut grid = OccupancyGrid::unknown(GridFrame::new(0.1, Point2::new(-1.0, 2.0), w as u32, h as u32));
        let (kx, ky) = (rng.below(w as u64 / 2) as i32, rng.below(h as u64 / 2) as i32);
        let (kw, kh) = (10 + rng.below((w - kx - 9) as u64) as i32, 10 + rng.below((h - ky - 9) as u64) as i32);
        let mut carve = |x0: i32, y0: i32, x1: i32, y1: i32, value: u8| {
            for y in y0.max(ky)..=y1.min(ky + kh - 1) {
                for x in x0.max(kx)..=x1.min(kx + kw - 1) {
                    grid.set(Cell::new(x, y), value);
                }
            }
        };
        carve(kx, ky, kx + kw, ky + kh, 97);
        let mut centres = Vec::new();
        for _ in 0..2 + rng.below(5) {
            let (x, y) = (kx + rng.below(kw as u64) as i32, ky + rng.below(kh as u64) as i32);
            let (rw, rh) = (2 + rng.below(8) as i32, 2 + rng.below(8) as i32);
            carve(x - rw, y - rh, x + rw, y + rh, 12);
            centres.push((x, y));
        }
        for pair in centres.windows(2) {
            let ((ax, ay), (bx, by)) = (pair[0], pair[1]);
            let width = rng.below(2) as i32;
            carve(ax.min(bx), ay, ax.max(bx), ay + width, 12);
            carve(bx, ay.min(by), bx + width, ay.max(by), 12);
        }
        grid
    }

    /// Segmenting only the box around the free cells gives exactly what
    /// segmenting the whole grid gave: labels, segments, frontier lists and
    /// critical points, with and without the frontier's choice of cuts.
    #[test]
    fn segmenting_the_known_box_is_segmenting_the_whole_grid() {
        let mut split_somewhere = 0;
        for seed in 0..150 {
            let grid = rooms_in_a_window(seed);
            let frame = *grid.frame();
            let free: Vec<bool> = grid.cells().iter().map(|&v| crate::grid::classify(v) == CellClass::Free).collect();
            let frontier = crate::frontier::FrontierMap::detect(&grid).cells();
            for cuts in [Cuts::IntoUnknown, Cuts::All] {
                let whole = segment_free(frame, &free, &frontier, 1.0, 4, cuts);
                let cropped = segment_keeping(&grid, &frontier, 1.0, 4, cuts);
                assert_eq!(cropped, whole, "seed {seed}, {cuts:?}");
                split_somewhere += usize::from(whole.segments.len() > 1);
            }
        }
        // The worlds have doors to cut at, not only single rooms.
        assert!(split_somewhere > 100, "{split_somewhere} segmentations with two segments or more");
    }

    #[test]
    fn a_grid_without_free_cells_has_no_segments() {
        let grid = OccupancyGrid::unknown(GridFrame::new(0.1, Point2::new(0.0, 0.0), 7, 5));
        let s = segment(&grid, &[Cell::new(3, 3)], 1.0, 4);
        assert!(s.segments.is_empty() && s.critical_points.is_empty());
        assert_eq!(s.labels, vec![0; 35]);
    }
}
