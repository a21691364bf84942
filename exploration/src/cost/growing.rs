//! A cost map that is searched only as far as its user needs.
//!
//! A policy that needs a robot's costs to frontier cells only (the nearest
//! one, or all of them) needs no cost beyond them. A [`GrowingCostMap`]
//! settles labels up to a radius, answers for the cells inside it, and
//! resumes where it stopped when asked for more; its answers are the full
//! cost map's.
//!
//! Towards goals (frontier cells), the search is ordered by cost plus the
//! [`GoalDistance`] still to go (A*, Hart, Nilsson & Raphael 1968, with the
//! exact distance to the nearest goal as its estimate): a goal is settled in
//! the order of its cost as before, but only the cells on the way to goals
//! within the radius are touched, a band along the paths instead of a disc
//! around the robot.

use super::search::{Buckets, heap};
use super::{Cell, TraversalMap};

/// Every cell's cost to the nearest of a set of goals, over one traversal:
/// one search over the steps reversed, shared by all robots' searches.
#[derive(Debug)]
pub struct GoalDistance {
    /// Over the traversal's window; infinite where no goal can be reached.
    cost: Vec<f32>,
}

impl GoalDistance {
    /// The cost from every cell to the nearest of `goals` over `traversal`.
    pub fn new(traversal: &TraversalMap, goals: &[Cell]) -> Self {
        let mut cost = vec![f32::INFINITY; traversal.padded.len()];
        let (starts, _) = traversal.seed(goals, &mut cost, &mut []);
        let inbound = traversal.inbound();
        match Buckets::fitting(&starts, traversal.step_bounds()) {
            // Where every step costs the same, the per-cell costs need not be read.
            Some(mut b) if traversal.is_uniform() => {
                b.drain::<_, false, false>(&traversal.uniform_inbound(), &mut cost, &mut [])
            }
            Some(mut b) => b.drain::<_, false, false>(&inbound, &mut cost, &mut []),
            None => heap::<_, false>(&inbound, &mut cost, &mut [], &starts),
        }
        Self { cost }
    }

    /// The cost from `cell` to the nearest goal over `traversal` (the one
    /// this was computed over), when a search from `cell` reaches one; `None`
    /// for a cell no search starts from (off the traversal's window).
    pub fn cost(&self, traversal: &TraversalMap, cell: Cell) -> Option<f64> {
        let c = self.cost[traversal.start_index(cell)?];
        c.is_finite().then_some(f64::from(c))
    }
}

/// A search from one source towards the goals of a [`GoalDistance`],
/// settled up to [`GrowingCostMap::radius`].
#[derive(Debug)]
pub struct GrowingCostMap<'t> {
    traversal: &'t TraversalMap,
    /// Over the traversal's window; final below the radius.
    cost: Vec<f32>,
    /// The paused search and the cells whose present cost is still to be
    /// expanded; `None` once every cell it can reach is settled.
    search: Option<(Buckets, Vec<u64>)>,
    /// The source, when it lies outside the window (it reaches itself only).
    stranded: Option<Cell>,
    /// The estimate the search is ordered by; `None` when `cost` is
    /// complete (the fallback where buckets cannot hold the steps).
    goals: Option<&'t GoalDistance>,
    /// The radius before the search settled anything: about the source's
    /// cost to the nearest goal.
    first_radius: f64,
}

impl<'t> GrowingCostMap<'t> {
    /// The search from `source` towards the goals of `goals` (computed over
    /// the same traversal): it answers for the cells on the way to goals
    /// cheaper than its radius, goals included, and for no others.
    pub fn towards(traversal: &'t TraversalMap, source: Cell, goals: &'t GoalDistance) -> Self {
        let mut cost = vec![f32::INFINITY; traversal.padded.len()];
        let (starts, stranded) = traversal.seed(&[source], &mut cost, &mut []);
        let stranded = stranded.first().map(|&(cell, _)| cell);
        let mut map = Self { traversal, cost, search: None, stranded, goals: Some(goals), first_radius: 0.0 };
        // No goal can be reached from a source off the window or cut off from them.
        let Some(&start) = starts.first().filter(|&&i| goals.cost[i].is_finite()) else { return map };
        match Buckets::guided(start, goals.cost[start], traversal.step_bounds()) {
            Some(search) => {
                let mut open = vec![0u64; map.cost.len().div_ceil(64)];
                open[start / 64] |= 1 << (start % 64);
                map.search = Some((search, open));
                map.first_radius = map.radius();
            }
            None => {
                // Step costs too far apart for buckets: the complete search.
                heap::<_, false>(&traversal.weighted(), &mut map.cost, &mut [], &starts);
                map.goals = None;
            }
        }
        map
    }

    /// Every goal cheaper than this, and every cell whose cost plus its
    /// distance to the nearest goal is below it, is answered by
    /// [`Self::cost`]; every goal it does not answer costs at least this, or
    /// is unreachable. Infinite once the search has settled every cell it can.
    pub fn radius(&self) -> f64 {
        self.search.as_ref().map_or(f64::INFINITY, |(s, _)| f64::from(s.radius()))
    }

    /// Resumes the search until [`Self::radius`] is at least `radius`
    /// (everything, for an infinite one), and in any case a step further.
    pub fn grow_to(&mut self, radius: f64) {
        let (Some((search, open)), Some(goals)) = (&mut self.search, self.goals) else { return };
        // At least one bucket more, so that every call makes progress.
        let end = search.end_for(radius as f32).max(search.current + 1);
        let traversal = self.traversal;
        // Where every step costs the same, the per-cell costs need not be read.
        if traversal.is_uniform() {
            search.drain_guided(&traversal.uniform(), &mut self.cost, &goals.cost, open, end);
        } else {
            search.drain_guided(&traversal.weighted(), &mut self.cost, &goals.cost, open, end);
        }
        if search.exhausted() {
            self.search = None;
        }
    }

    /// Resumes the search until it answers for every one of `cells` or has
    /// settled all it can, in steps of [`Self::next_radius`].
    pub fn grow_to_reach(&mut self, cells: &[Cell]) {
        while self.radius() < f64::INFINITY && !cells.iter().all(|&c| self.cost(c).is_some()) {
            self.grow_to(self.next_radius());
        }
    }

    /// Where to grow to next when looking for something not reached yet: a
    /// unit of cost (a metre of free space) past the radius, or a quarter
    /// of the way searched so far past the first goal's, whichever is more.
    /// Everything settled past what was looked for is waste, and a search
    /// towards goals widens with every unit of slack: a quarter wastes at
    /// most a fifth of the slack (steps that double, up to half), in a
    /// number of steps that grows with its logarithm.
    pub fn next_radius(&self) -> f64 {
        let radius = self.radius();
        radius + (0.25 * (radius - self.first_radius)).max(1.0)
    }

    /// The cost of reaching `cell`, if it is below the radius; `None` for a
    /// cell beyond it, unreachable, or off the way to every goal within it.
    pub fn cost(&self, cell: Cell) -> Option<f64> {
        if !self.traversal.frame.contains(cell) {
            return None;
        }
        if self.stranded == Some(cell) {
            return Some(0.0);
        }
        let i = self.traversal.window.index(cell)?;
        let c = self.cost[i];
        let key = c + self.goals.map_or(0.0, |g| g.cost[i]);
        (f64::from(key) < self.radius() && c.is_finite()).then_some(f64::from(c))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cost::cost_map;
    use crate::grid::OccupancyGrid;
    use crate::grid::testing::grid_from_picture;

    /// Every cell a goal: the search is Dijkstra's, outwards from the source.
    fn every_cell(grid: &OccupancyGrid, traversal: &TraversalMap) -> GoalDistance {
        let cells: Vec<Cell> = (0..grid.frame().len()).map(|i| grid.frame().cell(i)).collect();
        GoalDistance::new(traversal, &cells)
    }

    #[test]
    fn it_answers_inside_its_radius_and_grows_to_the_full_map() {
        let grid = grid_from_picture(&[
            "..........", //
            ".########.", //
            "..........", //
        ]);
        let traversal = TraversalMap::free_space(&grid, 0.0);
        let source = Cell::new(0, 1);
        let full = cost_map(&traversal, &[source]);
        let everywhere = every_cell(&grid, &traversal);
        let mut growing = GrowingCostMap::towards(&traversal, source, &everywhere);
        growing.grow_to(3.0);
        let radius = growing.radius();
        assert!((3.0..4.0).contains(&radius), "radius {radius}");
        assert_eq!(growing.cost(Cell::new(9, 1)), None, "beyond the radius");
        for cell in (0..grid.frame().len()).map(|i| grid.frame().cell(i)) {
            match growing.cost(cell) {
                Some(c) => assert_eq!(Some(c), full.cost(cell)),
                None => assert!(full.cost(cell).is_none_or(|c| c >= radius), "{cell:?} costs {:?}", full.cost(cell)),
            }
        }
        growing.grow_to(f64::INFINITY);
        assert_eq!(growing.radius(), f64::INFINITY);
        for cell in (0..grid.frame().len()).map(|i| grid.frame().cell(i)) {
            assert_eq!(growing.cost(cell), full.cost(cell), "{cell:?}");
        }
    }

    #[test]
    fn a_source_off_the_passable_cells_reaches_itself_only() {
        let grid = grid_from_picture(&[
            "....", //
            "####", //
            "####", //
            "####", //
            "####", //
        ]);
        let traversal = TraversalMap::free_space(&grid, 0.0);
        let everywhere = every_cell(&grid, &traversal);
        let mut growing = GrowingCostMap::towards(&traversal, Cell::new(0, 0), &everywhere);
        growing.grow_to(100.0);
        assert_eq!(growing.cost(Cell::new(0, 0)), Some(0.0));
        assert_eq!(growing.cost(Cell::new(0, 4)), None);
        let off = GrowingCostMap::towards(&traversal, Cell::new(-5, 0), &everywhere);
        assert_eq!(off.cost(Cell::new(-5, 0)), None);
    }

    /// A room with the robot at one end and the only goal at the other:
    /// the search towards it touches the cells along the way, a search
    /// towards every cell (Dijkstra's) every cell as near as the goal.
    #[test]
    fn towards_a_goal_only_the_way_there_is_searched() {
        let row = ".".repeat(60);
        let picture: Vec<&str> = (0..40).map(|_| row.as_str()).collect();
        let grid = grid_from_picture(&picture);
        let traversal = TraversalMap::free_space(&grid, 0.0);
        let (source, goal) = (Cell::new(0, 20), Cell::new(59, 20));
        let goals = GoalDistance::new(&traversal, &[goal]);
        let mut guided = GrowingCostMap::towards(&traversal, source, &goals);
        let everywhere = every_cell(&grid, &traversal);
        let mut plain = GrowingCostMap::towards(&traversal, source, &everywhere);
        let full = cost_map(&traversal, &[source]).cost(goal).unwrap();
        for search in [&mut guided, &mut plain] {
            search.grow_to(full + 0.05);
            assert_eq!(search.cost(goal), Some(full));
        }
        let touched = |s: &GrowingCostMap<'_>| s.cost.iter().filter(|c| c.is_finite()).count();
        let (guided, plain) = (touched(&guided), touched(&plain));
        assert!(guided * 4 < plain, "guided {guided} cells, plain {plain}");
    }

    proptest::proptest! {
        #![proptest_config(crate::testing::seeded_proptest(256))]
        /// Towards goals, every goal below the radius costs what the full
        /// cost map says, and no goal left out is cheaper than the radius;
        /// over uneven costs (Burgard's smoothed occupancy), walls and
        /// sources off the passable cells, radius after radius.
        #[test]
        fn towards_goals_answers_every_goal_as_the_full_search(
            width in 3u32..30,
            height in 3u32..30,
            seed in 0u64..1_000_000,
            goal_count in 1usize..12,
            uneven in proptest::bool::ANY,
        ) {
            use crate::policy::testing::random_known_rectangle;
            use crate::rng::SplitMix64;

            let mut rng = SplitMix64::new(seed);
            let (grid, free) = random_known_rectangle(width, height, &mut rng, |rng| match rng.below(8) {
                0 => 95,
                1 => 70,
                _ => 5 + rng.below(40) as u8,
            });
            proptest::prop_assume!(!free.is_empty());
            let traversal = if uneven {
                TraversalMap::burgard(&grid, 0.6, 0.5, 0.0)
            } else {
                TraversalMap::free_space(&grid, 0.3)
            };
            let pick = |rng: &mut SplitMix64| free[rng.below(free.len() as u64) as usize];
            let goal_cells: Vec<Cell> = (0..goal_count).map(|_| pick(&mut rng)).collect();
            let source = pick(&mut rng);
            let full = cost_map(&traversal, &[source]);
            let goals = GoalDistance::new(&traversal, &goal_cells);
            let mut search = GrowingCostMap::towards(&traversal, source, &goals);
            let mut radius = 0.2;
            loop {
                search.grow_to(radius);
                let reached = search.radius();
                for &g in &goal_cells {
                    match search.cost(g) {
                        Some(c) => proptest::prop_assert_eq!(Some(c), full.cost(g), "{:?}", g),
                        None => proptest::prop_assert!(
                            full.cost(g).is_none_or(|c| c >= reached),
                            "{:?} costs {:?} below the radius {}", g, full.cost(g), reached
                        ),
                    }
                }
                if reached == f64::INFINITY {
                    break;
                }
                radius = reached * 1.7 + 0.1;
            }
        }
    }
}
