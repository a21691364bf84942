//! Traversal costs and cost maps.
//!
//! A [`TraversalMap`] says what entering each cell costs per metre (infinite
//! where a robot may not go); a [`CostMap`] holds the cumulative cost of the
//! cheapest 8-connected path from a source to every cell. Burgard et al.
//! 2005, §II-A compute it by deterministic value iteration,
//!
//! V(x,y) ← min { V(x+Δx, y+Δy) + √(Δx²+Δy²) · P(occ(x+Δx, y+Δy)) },
//!
//! repeated until convergence; we reach the same fixed point with Dijkstra's
//! label-setting order (costs are non-negative), in O(N log N) instead of
//! O(N) per sweep times the number of sweeps. With a constant cost of one per
//! metre the same routine is the wavefront of Yamauchi and Bautin et al. 2011.
//! A diagonal step needs both cells beside it passable: robots do not cut
//! corners.

use std::collections::{BinaryHeap, HashMap};
use std::sync::Arc;

use crate::grid::{Cell, GridFrame, NEIGHBOURS_8, OccupancyGrid};
use crate::workers::{Workers, in_parallel};

mod growing;
mod search;
mod traversal;
pub use growing::{GoalDistance, GrowingCostMap};
use search::{Buckets, key, settle, unkey};
use traversal::Window;
pub use traversal::{TraversalKind, TraversalMap, gaussian_blur};

/// Cumulative cost of the cheapest path from the sources to every cell.
#[derive(Debug, Clone, PartialEq)]
pub struct CostMap {
    frame: GridFrame,
    /// The traversal's window.
    window: Window,
    /// Over the window; infinite where unreachable.
    cost: Vec<f32>,
    /// Sources outside the window, with their index among the sources: a
    /// robot where nothing passable is near reaches only its own cell.
    stranded: Vec<(Cell, u32)>,
    /// Labels below this are final and answered; the others are not (a
    /// search stopped early, [`cost_map_reaching`]). Infinite when complete.
    settled_below: f32,
}

impl CostMap {
    /// The cost of reaching an on-grid cell, or `None` if it cannot be
    /// reached (or, for a map of [`cost_map_reaching`], was not settled).
    #[inline]
    pub fn cost(&self, cell: Cell) -> Option<f64> {
        if !self.frame.contains(cell) {
            return None;
        }
        let c = self.raw(cell);
        c.is_finite().then_some(f64::from(c))
    }

    /// The label of a cell, infinite where unreachable or off the grid.
    #[inline]
    fn raw(&self, cell: Cell) -> f32 {
        match self.window.index(cell).map(|i| self.cost[i]) {
            Some(c) if c < self.settled_below => c,
            _ if self.stranded.iter().any(|(s, _)| *s == cell) => 0.0,
            _ => f32::INFINITY,
        }
    }

    /// The grid frame.
    pub fn frame(&self) -> &GridFrame {
        &self.frame
    }

    /// Number of reachable cells (of those settled, for a map of
    /// [`cost_map_reaching`]).
    pub fn reachable_cells(&self) -> usize {
        self.cost.iter().filter(|&&c| c < self.settled_below).count() + self.stranded.len()
    }

    /// The cheapest path from a source to `goal` (source first, goal last),
    /// by steepest descent in the cost map (Burgard et al. 2005, §II-A).
    /// `None` when `goal` is unreachable.
    pub fn path_to(&self, traversal: &TraversalMap, goal: Cell) -> Option<Vec<Cell>> {
        self.cost(goal)?;
        let mut path = vec![goal];
        let mut current = goal;
        loop {
            let here = self.raw(current);
            if here == 0.0 {
                break;
            }
            let mut best: Option<(f32, Cell)> = None;
            for (dx, dy) in NEIGHBOURS_8 {
                let n = Cell::new(current.x + dx, current.y + dy);
                let diagonal_clear = dx == 0
                    || dy == 0
                    || (traversal.passable(Cell::new(current.x + dx, current.y))
                        && traversal.passable(Cell::new(current.x, current.y + dy)));
                if !self.frame.contains(n) || !diagonal_clear {
                    continue;
                }
                let c = self.raw(n);
                if c < here && best.is_none_or(|(b, _)| c < b) {
                    best = Some((c, n));
                }
            }
            let (_, next) = best?;
            path.push(next);
            current = next;
        }
        path.reverse();
        Some(path)
    }
}

/// Whether a diagonal step may pass a corner where one side cell is blocked.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Corners {
    /// A diagonal step needs both side cells passable: robots do not cut corners.
    #[default]
    Keep,
    /// A diagonal step needs only its end cells passable (scikit-image's
    /// `MCP_Geometric` and scipy's graph semantics, for the benchmarks).
    Cut,
}

/// A cost map from `sources` (each at cost zero) over `traversal`, without
/// cutting corners. See [`cost_map_with`].
pub fn cost_map(traversal: &TraversalMap, sources: &[Cell]) -> CostMap {
    cost_map_with(traversal, sources, Corners::Keep)
}

/// A cost map from `sources` (each at cost zero) over `traversal`.
///
/// Moving from a cell to one of its eight neighbours costs the step length in
/// metres times the neighbour's cost per metre. Sources are always allowed,
/// even inside an inflated obstacle, so a robot standing near a wall can
/// still leave.
///
/// Labels are settled in buckets as wide as the cheapest possible step
/// (Dial 1969): a cell in the current bucket cannot improve another cell of
/// the same bucket, since any step leads at least one bucket further, so the
/// result equals Dijkstra's, in O(1) per relaxation. When step costs span too
/// wide a range for a small ring of buckets, a binary heap is used instead.
///
/// Complexity: O(N) with buckets, O(N log N) with the heap, for N reachable cells.
pub fn cost_map_with(traversal: &TraversalMap, sources: &[Cell], corners: Corners) -> CostMap {
    settle_from(traversal, sources, corners, &mut [])
}

/// A cost map from several sources that also records, for every cell,
/// which source it is cheapest to reach from: with reversible costs (the
/// free-space traversal), the source nearest to each cell, from one search
/// instead of one per cell of interest.
#[derive(Debug, Clone, PartialEq)]
pub struct LabelledCostMap {
    map: CostMap,
    /// Per cell of the window: index into the sources, or `u32::MAX`.
    labels: Vec<u32>,
}

impl LabelledCostMap {
    /// The cost map.
    pub fn map(&self) -> &CostMap {
        &self.map
    }

    /// The index of the source `cell` is cheapest to reach from, if any.
    pub fn source_of(&self, cell: Cell) -> Option<usize> {
        if !self.map.frame.contains(cell) {
            return None;
        }
        let label = match self.map.window.index(cell).map(|i| self.labels[i]) {
            Some(label) if label != u32::MAX => label,
            _ => self.map.stranded.iter().find(|(s, _)| *s == cell).map_or(u32::MAX, |(_, k)| *k),
        };
        (label != u32::MAX).then_some(label as usize)
    }
}

/// A [`LabelledCostMap`] from `sources` over `traversal`, without cutting corners.
///
/// Complexity: as [`cost_map_with`], one search whatever the number of sources.
pub fn labelled_cost_map(traversal: &TraversalMap, sources: &[Cell]) -> LabelledCostMap {
    let mut labels = vec![u32::MAX; traversal.padded.len()];
    let map = settle_from(traversal, sources, Corners::Keep, &mut labels);
    LabelledCostMap { map, labels }
}

/// Runs the search; `labels`, when not empty, start as each source's index
/// (the last where a cell is listed twice) and follow the improvements.
fn settle_from(traversal: &TraversalMap, sources: &[Cell], corners: Corners, labels: &mut [u32]) -> CostMap {
    let mut cost = vec![f32::INFINITY; traversal.padded.len()];
    let (starts, stranded) = traversal.seed(sources, &mut cost, labels);
    let bounds = traversal.step_bounds();
    match (traversal.is_uniform(), corners == Corners::Cut) {
        (true, true) => settle::<_, true>(&traversal.uniform(), &mut cost, labels, &starts, bounds),
        (true, false) => settle::<_, false>(&traversal.uniform(), &mut cost, labels, &starts, bounds),
        (false, true) => settle::<_, true>(&traversal.weighted(), &mut cost, labels, &starts, bounds),
        (false, false) => settle::<_, false>(&traversal.weighted(), &mut cost, labels, &starts, bounds),
    }
    CostMap { frame: traversal.frame, window: traversal.window, cost, stranded, settled_below: f32::INFINITY }
}

/// A cost map from `sources` over `traversal`, as [`cost_map`]'s, but
/// settled only until each of `cells` is (or everything reachable is). It
/// answers for the cells cheaper than a radius at least the dearest of
/// `cells` it reaches, so also for every cell of the cheapest paths to
/// them ([`CostMap::path_to`]), and for no others.
///
/// A frontier cluster's wavefront is read at the robots' cells only (Bautin
/// et al. 2011's MinPos): late in a mission the robots gather near the last
/// frontiers, and the part of the map behind the farthest robot, most of
/// it by then, need not be searched.
pub fn cost_map_reaching(traversal: &TraversalMap, sources: &[Cell], cells: &[Cell]) -> CostMap {
    let mut cost = vec![f32::INFINITY; traversal.padded.len()];
    let (starts, stranded) = traversal.seed(sources, &mut cost, &mut []);
    // A cell no step enters gets a label only as a source.
    let mut waiting: Vec<usize> = cells
        .iter()
        .filter_map(|&c| traversal.start_index(c))
        .filter(|&i| traversal.padded[i].is_finite() || cost[i] == 0.0)
        .collect();
    let mut settled_below = f32::INFINITY;
    let bounds = traversal.step_bounds();
    match Buckets::fitting(&starts, bounds) {
        Some(mut buckets) => {
            // A settled label stays settled: popping from the end while the
            // last is settled costs O(1) a bucket, not a scan of thousands
            // of frontier cells (`tours`) every bucket.
            let done = |cost: &[f32], radius: f32| {
                while waiting.last().is_some_and(|&i| cost[i] < radius) {
                    waiting.pop();
                }
                waiting.is_empty()
            };
            if traversal.is_uniform() {
                buckets.drain_until::<_, false, false>(&traversal.uniform(), &mut cost, &mut [], done);
            } else {
                buckets.drain_until::<_, false, false>(&traversal.weighted(), &mut cost, &mut [], done);
            }
            settled_below = buckets.radius();
        }
        None => settle::<_, false>(&traversal.weighted(), &mut cost, &mut [], &starts, bounds),
    }
    CostMap { frame: traversal.frame, window: traversal.window, cost, stranded, settled_below }
}

/// The shortest 8-connected path from `start` to `goal` over cells where
/// `passable` holds, by A* with the octile-distance heuristic (Hart, Nilsson
/// & Raphael 1968). Diagonal steps need both side cells passable, as in
/// [`cost_map`]; `start` itself is always allowed. Returns the cells from
/// `start` to `goal`, or `None` when `goal` cannot be reached.
///
/// Complexity: O(N log N) in the worst case, far less when the goal is near.
pub fn shortest_path(frame: &GridFrame, start: Cell, goal: Cell, passable: impl Fn(Cell) -> bool) -> Option<Vec<Cell>> {
    if !frame.contains(start) || !frame.contains(goal) || !passable(goal) {
        return None;
    }
    let heuristic = |c: Cell| {
        let dx = (c.x - goal.x).abs() as f32;
        let dy = (c.y - goal.y).abs() as f32;
        dx.max(dy) + (std::f32::consts::SQRT_2 - 1.0) * dx.min(dy)
    };
    let mut g = vec![f32::INFINITY; frame.len()];
    let mut parent = vec![u32::MAX; frame.len()];
    let mut heap = BinaryHeap::new();
    let s = frame.index(start);
    g[s] = 0.0;
    heap.push(std::cmp::Reverse(key(heuristic(start), s)));
    let goal_index = frame.index(goal);
    while let Some(std::cmp::Reverse(k)) = heap.pop() {
        let (_, i) = unkey(k);
        if i == goal_index {
            let mut path = vec![goal];
            let mut j = i;
            while j != s {
                j = parent[j] as usize;
                path.push(frame.cell(j));
            }
            path.reverse();
            return Some(path);
        }
        let c = frame.cell(i);
        for (dx, dy) in NEIGHBOURS_8 {
            let n = Cell::new(c.x + dx, c.y + dy);
            if !frame.contains(n) || !passable(n) {
                continue;
            }
            let diagonal = dx != 0 && dy != 0;
            if diagonal && !(passable(Cell::new(c.x + dx, c.y)) && passable(Cell::new(c.x, c.y + dy))) {
                continue;
            }
            let j = frame.index(n);
            let next = g[i] + if diagonal { std::f32::consts::SQRT_2 } else { 1.0 };
            if next < g[j] {
                g[j] = next;
                parent[j] = i as u32;
                heap.push(std::cmp::Reverse(key(next + heuristic(n), j)));
            }
        }
    }
    None
}

/// Cost maps for one replanning, each computed once however many policies or
/// robots ask for it. Built over one grid; throw it away when the grid changes.
#[derive(Debug)]
pub struct CostCache<'g> {
    grid: &'g OccupancyGrid,
    traversals: HashMap<TraversalKind, Arc<TraversalMap>>,
    maps: HashMap<(TraversalKind, Cell), Arc<CostMap>>,
    computed: usize,
}

impl<'g> CostCache<'g> {
    /// An empty cache over `grid`.
    pub fn new(grid: &'g OccupancyGrid) -> Self {
        Self { grid, traversals: HashMap::new(), maps: HashMap::new(), computed: 0 }
    }

    /// The grid the cache works on.
    pub fn grid(&self) -> &'g OccupancyGrid {
        self.grid
    }

    /// The traversal map of a kind, built on first use.
    pub fn traversal(&mut self, kind: TraversalKind) -> Arc<TraversalMap> {
        let grid = self.grid;
        self.traversals.entry(kind).or_insert_with(|| Arc::new(kind.build(grid))).clone()
    }

    /// The cost map from `source` over a traversal, computed on first use.
    pub fn cost_map(&mut self, kind: TraversalKind, source: Cell) -> Arc<CostMap> {
        if let Some(map) = self.maps.get(&(kind, source)) {
            return map.clone();
        }
        let traversal = self.traversal(kind);
        let map = Arc::new(cost_map(&traversal, &[source]));
        self.computed += 1;
        self.maps.insert((kind, source), map.clone());
        map
    }

    /// Cost maps from several sources, the missing ones computed in parallel
    /// by `workers`.
    pub fn cost_maps(&mut self, kind: TraversalKind, sources: &[Cell], workers: Workers<'_>) -> Vec<Arc<CostMap>> {
        let traversal = self.traversal(kind);
        let mut missing: Vec<Cell> = sources.iter().copied().filter(|s| !self.maps.contains_key(&(kind, *s))).collect();
        missing.sort_unstable();
        missing.dedup();
        let computed = in_parallel(&missing, workers, |&s| cost_map(&traversal, &[s]));
        for (s, map) in missing.into_iter().zip(computed) {
            self.computed += 1;
            self.maps.insert((kind, s), Arc::new(map));
        }
        sources.iter().map(|&s| self.cost_map(kind, s)).collect()
    }

    /// How many cost maps were computed (not served from the cache),
    /// counting searches towards goals that the cache does not hold.
    pub fn computed(&self) -> usize {
        self.computed
    }

    /// Counts `searches` made outside the cache ([`GrowingCostMap`]s).
    pub fn count_searches(&mut self, searches: usize) {
        self.computed += searches;
    }
}

#[cfg(test)]
mod tests {
    use super::search::{Moves, Neighbourhood, Weighted, heap};
    use super::*;
    use crate::grid::UNKNOWN;
    use crate::grid::testing::grid_from_picture;

    #[test]
    fn free_space_costs_are_path_lengths_and_walls_force_detours() {
        let grid = grid_from_picture(&[
            ".....", //
            ".###.", //
            ".....", //
        ]);
        let t = TraversalMap::free_space(&grid, 0.0);
        let map = cost_map(&t, &[Cell::new(0, 1)]);
        // Straight up the left column: 1 cell.
        assert_eq!(map.cost(Cell::new(0, 2)), Some(1.0));
        // Around the wall: up, four cells right, down. The diagonals past the
        // wall's ends would cut its corners.
        assert_eq!(map.cost(Cell::new(4, 1)), Some(6.0));
        assert_eq!(map.cost(Cell::new(2, 1)), None, "walls are unreachable");
        let path = map.path_to(&t, Cell::new(4, 1)).unwrap();
        assert_eq!(path.first(), Some(&Cell::new(0, 1)));
        assert_eq!(path.last(), Some(&Cell::new(4, 1)));
        for pair in path.windows(2) {
            assert!(pair[0].distance(pair[1]) < 1.5);
            assert!(t.passable(pair[1]));
        }
    }

    #[test]
    fn a_star_finds_the_same_length_as_the_cost_map() {
        let grid = grid_from_picture(&[
            "........", //
            ".######.", //
            ".#....#.", //
            ".#.##.#.", //
            "...#....", //
        ]);
        let t = TraversalMap::free_space(&grid, 0.0);
        let start = Cell::new(2, 1);
        let map = cost_map(&t, &[start]);
        let frame = *grid.frame();
        for goal in frame.bounds().cells() {
            let path = shortest_path(&frame, start, goal, |c| t.passable(c));
            match (map.cost(goal), path) {
                (Some(cost), Some(path)) => {
                    let length: f64 = path.windows(2).map(|w| w[0].distance(w[1])).sum();
                    assert!((length - cost).abs() < 1e-4, "{goal:?}: {length} vs {cost}");
                    assert_eq!(path[0], start);
                }
                (None, None) => {}
                (a, b) => panic!("{goal:?}: cost map {a:?}, A* {b:?}"),
            }
        }
    }

    proptest::proptest! {
        #![proptest_config(crate::testing::seeded_proptest(256))]
        /// The step masks say what the corner rule says, cell by cell: a
        /// step out lands on a passable cell, a step in enters one, and a
        /// diagonal either way needs both side cells passable.
        #[test]
        fn step_masks_follow_the_corner_rule(
            width in 1u32..24,
            height in 1u32..24,
            seed in 0u64..1_000_000,
            blocked_per_mille in 0u64..600,
        ) {
            let frame = GridFrame::new(0.25, crate::math::Point2::origin(), width, height);
            let mut rng = crate::rng::SplitMix64::new(seed);
            let costs: Vec<f32> =
                (0..frame.len()).map(|_| if rng.below(1000) < blocked_per_mille { f32::INFINITY } else { 1.0 }).collect();
            let t = TraversalMap::from_costs(frame, costs);
            let (stride, rows) = (t.window.stride as i64, t.window.rows as i64);
            let passable = |x: i64, y: i64| {
                (0..stride).contains(&x) && (0..rows).contains(&y) && t.padded[(y * stride + x) as usize].is_finite()
            };
            let steps = [(1, 0), (-1, 0), (0, 1), (0, -1), (1, 1), (-1, 1), (1, -1), (-1, -1)];
            for (i, (&out, &into)) in t.moves.iter().zip(&t.entries).enumerate() {
                let (x, y) = (i as i64 % stride, i as i64 / stride);
                for (k, &(dx, dy)) in steps.iter().enumerate() {
                    proptest::prop_assert_eq!(Moves::offsets(t.window.stride)[k], (dy * stride + dx) as isize);
                    let corners_free = passable(x + dx, y) && passable(x, y + dy);
                    let straight = dx == 0 || dy == 0;
                    let may_leave = passable(x + dx, y + dy) && (straight || corners_free);
                    let may_enter = passable(x, y) && (straight || corners_free);
                    proptest::prop_assert_eq!(out >> k & 1 != 0, may_leave, "out of ({}, {}) by {:?}", x, y, (dx, dy));
                    proptest::prop_assert_eq!(into >> k & 1 != 0, may_enter, "into ({}, {}) from {:?}", x, y, (dx, dy));
                }
            }
        }

        /// Dial's buckets settle the same labels as Dijkstra with a heap.
        #[test]
        fn buckets_agree_with_a_binary_heap(
            width in 1u32..24,
            height in 1u32..24,
            seed in 0u64..1_000_000,
            blocked_per_mille in 0u64..400,
            cut in proptest::bool::ANY,
        ) {
            let frame = GridFrame::new(0.25, crate::math::Point2::origin(), width, height);
            let mut rng = crate::rng::SplitMix64::new(seed);
            let costs: Vec<f32> = (0..frame.len())
                .map(|_| if rng.below(1000) < blocked_per_mille { f32::INFINITY } else { 0.1 + 0.9 * rng.next_f64() as f32 })
                .collect();
            let t = TraversalMap::from_costs(frame, costs);
            let source = Cell::new(rng.below(u64::from(width)) as i32, rng.below(u64::from(height)) as i32);
            let corners = if cut { Corners::Cut } else { Corners::Keep };
            let fast = cost_map_with(&t, &[source], corners);
            let mut slow = vec![f32::INFINITY; t.padded.len()];
            let Some(start) = t.window.start_index(source) else {
                proptest::prop_assert!(fast.cost(source) == Some(0.0) && fast.reachable_cells() == 1);
                return Ok(());
            };
            slow[start] = 0.0;
            let n = Weighted {
                costs: &t.padded,
                bits: &t.passable_bits,
                moves: &t.moves,
                entries: &t.entries,
                // Every step read from the neighbour's cost: the reference.
                flat: &[],
                stride: t.window.stride,
                orthogonal: 0.25,
                diagonal: (0.25 * std::f64::consts::SQRT_2) as f32,
            };
            if cut {
                heap::<_, true>(&n, &mut slow, &mut [], &[start]);
            } else {
                heap::<_, false>(&n, &mut slow, &mut [], &[start]);
            }
            for cell in frame.bounds().cells() {
                let a = fast.cost(cell);
                let b = t.window.index(cell).map_or(f32::INFINITY, |i| slow[i]);
                match a {
                    Some(a) => proptest::prop_assert!((a - f64::from(b)).abs() < 1e-4, "{:?}: {} vs {}", cell, a, b),
                    None => proptest::prop_assert!(!b.is_finite()),
                }
            }
        }
    }

    proptest::proptest! {
        #![proptest_config(crate::testing::seeded_proptest(256))]
        /// A flat cell's steps, taken as uniform ones, offer its neighbours
        /// the same costs, to the bit and in the same order, as the steps
        /// that read each neighbour's cost; and the costs come in patches,
        /// so that flat cells are common.
        #[test]
        fn flat_cells_step_as_the_per_cell_costs_do(
            width in 1u32..24,
            height in 1u32..24,
            seed in 0u64..1_000_000,
            patch in 1u32..6,
            blocked_per_mille in 0u64..300,
        ) {
            let frame = GridFrame::new(0.1, crate::math::Point2::origin(), width, height);
            let mut rng = crate::rng::SplitMix64::new(seed);
            let levels = [0.12f32, 0.3, 0.1 + rng.next_f64() as f32];
            let per_patch: Vec<f32> = (0..frame.len()).map(|_| levels[rng.below(3) as usize]).collect();
            let costs: Vec<f32> = frame
                .bounds()
                .cells()
                .map(|c| {
                    let patch_of = (c.y as u32 / patch) * width + c.x as u32 / patch;
                    if rng.below(1000) < blocked_per_mille { f32::INFINITY } else { per_patch[patch_of as usize] }
                })
                .collect();
            let t = TraversalMap::from_costs(frame, costs);
            let with_flat = t.weighted();
            let reference = Weighted { flat: &[], ..with_flat };
            let offered = |n: &Weighted<'_>, i: usize, here: f32| {
                let mut steps = Vec::new();
                n.neighbours::<false>(i, here, |j, c| steps.push((j, c.to_bits())));
                steps
            };
            for i in 0..t.padded.len() {
                let here = rng.next_f64() as f32 * 100.0;
                proptest::prop_assert_eq!(offered(&with_flat, i, here), offered(&reference, i, here), "cell {}", i);
            }
            // A flat cell is one whose every step enters a cell of its own cost.
            let flat = (0..t.padded.len()).filter(|&i| !t.flat.is_empty() && super::search::bit(&t.flat, i)).count();
            if t.is_uniform() {
                proptest::prop_assert!(t.flat.is_empty());
            } else if patch >= 4 && blocked_per_mille == 0 && width >= 12 && height >= 12 {
                proptest::prop_assert!(flat > 0, "patches of {} cells leave some cell flat", patch);
            }
        }
    }

    proptest::proptest! {
        #![proptest_config(crate::testing::seeded_proptest(256))]
        /// A search confined to the window around the passable cells finds
        /// what A* over the whole grid finds, from any source: inside the
        /// known part, beside it, or far from it.
        #[test]
        fn the_window_loses_no_path(
            width in 1u32..20,
            height in 1u32..20,
            seed in 0u64..1_000_000,
            blocked_per_mille in 0u64..400,
        ) {
            let frame = GridFrame::new(0.25, crate::math::Point2::origin(), width, height);
            let mut rng = crate::rng::SplitMix64::new(seed);
            let mut corner = |n: u32| (rng.below(u64::from(n)) as i32, rng.below(u64::from(n)) as i32);
            let ((x0, x1), (y0, y1)) = (corner(width), corner(height));
            let known = |c: Cell| (x0.min(x1)..=x0.max(x1)).contains(&c.x) && (y0.min(y1)..=y0.max(y1)).contains(&c.y);
            let cells: Vec<u8> = (0..frame.len())
                .map(|i| match (known(frame.cell(i)), rng.below(1000) < blocked_per_mille) {
                    (false, _) => UNKNOWN,
                    (true, true) => 100,
                    (true, false) => 0,
                })
                .collect();
            let grid = OccupancyGrid::from_cells(frame, cells);
            let t = TraversalMap::free_space(&grid, 0.0);
            let source = Cell::new(rng.below(u64::from(width)) as i32, rng.below(u64::from(height)) as i32);
            let map = cost_map(&t, &[source]);
            let labelled = labelled_cost_map(&t, &[Cell::new(-1, 0), source]);
            for goal in frame.bounds().cells() {
                let path = shortest_path(&frame, source, goal, |c| t.passable(c));
                // A* never ends on an impassable cell; a search starts on any.
                let expected = if goal == source {
                    Some(0.0)
                } else {
                    path.map(|p| p.windows(2).map(|w| w[0].distance(w[1])).sum::<f64>() * 0.25)
                };
                match (map.cost(goal), expected) {
                    (Some(a), Some(b)) => proptest::prop_assert!((a - b).abs() < 1e-4, "{:?}: {} vs {}", goal, a, b),
                    (a, b) => proptest::prop_assert_eq!(a.is_some(), b.is_some(), "{:?}", goal),
                }
                proptest::prop_assert_eq!(labelled.source_of(goal), map.cost(goal).map(|_| 1), "{:?}", goal);
            }
        }
    }

    proptest::proptest! {
        #![proptest_config(crate::testing::seeded_proptest(256))]
        /// A map settled only until given cells are answers for them as the
        /// complete map does, and for the cells of the paths down from them;
        /// whatever else it answers, it answers right.
        #[test]
        fn a_map_settled_until_some_cells_answers_them_as_the_complete_one(
            width in 1u32..24,
            height in 1u32..24,
            seed in 0u64..1_000_000,
            blocked_per_mille in 0u64..400,
            weighted in proptest::bool::ANY,
            sources in 1usize..4,
            wanted in 0usize..6,
        ) {
            let frame = GridFrame::new(0.25, crate::math::Point2::origin(), width, height);
            let mut rng = crate::rng::SplitMix64::new(seed);
            let costs: Vec<f32> = (0..frame.len())
                .map(|_| match (rng.below(1000) < blocked_per_mille, weighted) {
                    (true, _) => f32::INFINITY,
                    (false, true) => 0.1 + 0.9 * rng.next_f64() as f32,
                    (false, false) => 1.0,
                })
                .collect();
            let t = TraversalMap::from_costs(frame, costs);
            let mut cell = || Cell::new(rng.below(u64::from(width)) as i32, rng.below(u64::from(height)) as i32);
            let sources: Vec<Cell> = (0..sources).map(|_| cell()).collect();
            let wanted: Vec<Cell> = (0..wanted).map(|_| cell()).collect();
            let complete = cost_map(&t, &sources);
            let partial = cost_map_reaching(&t, &sources, &wanted);
            for &c in &wanted {
                proptest::prop_assert_eq!(partial.cost(c), complete.cost(c), "{:?}", c);
                proptest::prop_assert_eq!(partial.path_to(&t, c), complete.path_to(&t, c), "{:?}", c);
            }
            for c in frame.bounds().cells() {
                if let Some(answer) = partial.cost(c) {
                    proptest::prop_assert_eq!(Some(answer), complete.cost(c), "{:?}", c);
                }
            }
        }
    }

    #[test]
    fn a_map_settled_until_some_cells_stops_past_them() {
        // A corridor of 40 cells: from its west end, the cell 10 along.
        let grid = grid_from_picture(&["........................................"]);
        let t = TraversalMap::free_space(&grid, 0.0);
        let map = cost_map_reaching(&t, &[Cell::new(0, 0)], &[Cell::new(10, 0)]);
        assert_eq!(map.cost(Cell::new(10, 0)), cost_map(&t, &[Cell::new(0, 0)]).cost(Cell::new(10, 0)));
        assert_eq!(map.cost(Cell::new(39, 0)), None, "the far end is not searched");
        assert!(map.reachable_cells() < 20, "{} cells answered", map.reachable_cells());
        // A wanted cell it cannot reach leaves the search complete.
        let cut = grid_from_picture(&["..........#....................."]);
        let t = TraversalMap::free_space(&cut, 0.0);
        let map = cost_map_reaching(&t, &[Cell::new(0, 0)], &[Cell::new(1, 0), Cell::new(20, 0)]);
        assert_eq!(map, cost_map(&t, &[Cell::new(0, 0)]));
    }

    #[test]
    fn a_labelled_map_tells_the_nearest_source() {
        let grid = grid_from_picture(&[
            "...........", //
            ".#########.", //
            "...........", //
        ]);
        let t = TraversalMap::free_space(&grid, 0.0);
        let sources = [Cell::new(0, 1), Cell::new(10, 1)];
        let labelled = labelled_cost_map(&t, &sources);
        assert_eq!(labelled.source_of(Cell::new(2, 2)), Some(0));
        assert_eq!(labelled.source_of(Cell::new(8, 0)), Some(1));
        assert_eq!(labelled.source_of(Cell::new(5, 1)), None, "a wall is reached from nowhere");
        let plain = cost_map(&t, &sources);
        for cell in grid.frame().bounds().cells() {
            assert_eq!(labelled.map().cost(cell), plain.cost(cell));
        }
    }

    #[test]
    fn cells_far_off_the_grid_are_neither_passable_nor_reached() {
        let grid = grid_from_picture(&["....", "...."]);
        let t = TraversalMap::free_space(&grid, 0.0);
        let map = cost_map(&t, &[Cell::new(0, 0)]);
        for cell in [Cell::new(i32::MIN, 0), Cell::new(i32::MAX, i32::MAX), Cell::new(-3, 1), Cell::new(1, i32::MIN)] {
            assert!(!t.passable(cell), "{cell:?}");
            assert_eq!(t.cost_per_metre(cell), f32::INFINITY, "{cell:?}");
            assert_eq!(map.cost(cell), None, "{cell:?}");
        }
        assert_eq!(cost_map(&t, &[Cell::new(i32::MIN, i32::MIN)]).reachable_cells(), 0);
    }

    #[test]
    fn corners_are_not_cut() {
        let grid = grid_from_picture(&[
            ".#", //
            "#.", //
        ]);
        let t = TraversalMap::free_space(&grid, 0.0);
        let map = cost_map(&t, &[Cell::new(0, 1)]);
        assert_eq!(map.cost(Cell::new(1, 0)), None);
    }

    #[test]
    fn burgard_costs_grow_with_occupancy_and_occ_max_blocks() {
        let frame = GridFrame::new(1.0, crate::math::Point2::origin(), 3, 1);
        let grid = OccupancyGrid::from_cells(frame, vec![10, 50, 10]);
        let open = TraversalMap::burgard(&grid, 0.6, 0.0, 0.0);
        let map = cost_map(&open, &[Cell::new(0, 0)]);
        assert!((map.cost(Cell::new(1, 0)).unwrap() - 0.5).abs() < 1e-6);
        assert!((map.cost(Cell::new(2, 0)).unwrap() - 0.6).abs() < 1e-6);
        let strict = TraversalMap::burgard(&grid, 0.4, 0.0, 0.0);
        assert_eq!(cost_map(&strict, &[Cell::new(0, 0)]).cost(Cell::new(2, 0)), None);
    }

    #[test]
    fn inflation_closes_gaps_narrower_than_the_robot() {
        let grid = grid_from_picture(&[
            "#####.#####", //
            "...........", //
            "...........", //
        ]);
        let thin = TraversalMap::free_space(&grid, 0.0);
        assert!(thin.passable(Cell::new(5, 2)));
        let wide = TraversalMap::free_space(&grid, 1.0);
        assert!(!wide.passable(Cell::new(5, 2)));
        assert!(!wide.passable(Cell::new(3, 1)));
        assert!(wide.passable(Cell::new(3, 0)));
    }

    #[test]
    fn the_cache_computes_each_map_once() {
        let grid = grid_from_picture(&["....", "...."]);
        let mut cache = CostCache::new(&grid);
        let kind = TraversalKind::free_space(0.0);
        let a = cache.cost_map(kind, Cell::new(0, 0));
        let b = cache.cost_map(kind, Cell::new(0, 0));
        assert!(Arc::ptr_eq(&a, &b));
        let many = cache.cost_maps(kind, &[Cell::new(0, 0), Cell::new(3, 1), Cell::new(2, 0)], Workers::unpaced(2));
        assert_eq!(many.len(), 3);
        assert_eq!(cache.computed(), 3);
        assert_eq!(many[1].cost(Cell::new(3, 1)), Some(0.0));
    }
}
