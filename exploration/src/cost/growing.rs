//! A cost map that is searched only as far as its user needs.
//!
//! Policies that score a target by a bounded gain less a weighted path cost
//! (Burgard et al. 2005, Algorithm 1: U_t − β·V_t^i with U_t ≤ 1) never pick
//! a target whose cost alone rules it out. A [`GrowingCostMap`] settles
//! labels up to a radius, answers for the cells inside it, and resumes where
//! it stopped when asked for more; its answers are the full cost map's.
//!
//! Towards goals (frontier cells), the search is ordered by cost plus the
//! [`GoalDistance`] still to go (A*, Hart, Nilsson & Raphael 1968, with the
//! exact distance to the nearest goal as its estimate): a goal is settled in
//! the order of its cost as before, but only the cells on the way to goals
//! within the radius are touched, a band along the paths instead of a disc
//! around the robot.

use super::{Buckets, Cell, TraversalMap, heap};

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
            Some(mut b) => b.drain::<_, false, false>(&inbound, &mut cost, &mut [], usize::MAX),
            None => heap::<_, false>(&inbound, &mut cost, &mut [], &starts),
        }
        Self { cost }
    }

    /// The cost from `cell` to the nearest goal over `traversal` (the one
    /// this was computed over), when a search from `cell` reaches one; `None`
    /// for a cell no search starts from (off the traversal's window).
    pub fn cost(&self, traversal: &TraversalMap, cell: Cell) -> Option<f64> {
        let i = traversal.window.start_index(cell).filter(|_| traversal.frame.contains(cell))?;
        let c = self.cost[i];
        c.is_finite().then_some(f64::from(c))
    }

    /// Whether a search from `cell` over `traversal` starts inside its
    /// window (elsewhere a robot reaches only its own cell).
    pub fn starts_inside(traversal: &TraversalMap, cell: Cell) -> bool {
        traversal.frame.contains(cell) && traversal.window.start_index(cell).is_some()
    }
}

/// A cost map from one source, settled up to [`GrowingCostMap::radius`].
#[derive(Debug)]
pub struct GrowingCostMap<'t> {
    traversal: &'t TraversalMap,
    /// Over the traversal's window; final below the radius.
    cost: Vec<f32>,
    /// The paused search; `None` once every reachable cell is settled.
    search: Option<Buckets>,
    /// The source, when it lies outside the window (it reaches itself only).
    stranded: Option<Cell>,
    /// A guided search: the estimate it is ordered by, and the cells whose
    /// present cost is still to be expanded.
    towards: Option<(&'t GoalDistance, Vec<u64>)>,
}

impl<'t> GrowingCostMap<'t> {
    /// The search from `source`, nothing settled yet but the source.
    pub fn new(traversal: &'t TraversalMap, source: Cell) -> Self {
        let mut cost = vec![f32::INFINITY; traversal.padded.len()];
        let (starts, stranded) = traversal.seed(&[source], &mut cost, &mut []);
        let stranded = stranded.first().map(|&(cell, _)| cell);
        let search = if starts.is_empty() { None } else { Buckets::fitting(&starts, traversal.step_bounds()) };
        if search.is_none() && !starts.is_empty() {
            // Step costs too far apart for buckets: one full search with the heap.
            heap::<_, false>(&traversal.weighted(), &mut cost, &mut [], &starts);
        }
        Self { traversal, cost, search, stranded, towards: None }
    }

    /// The search from `source` towards the goals of `goals` (computed over
    /// the same traversal): it answers for the cells on the way to goals
    /// cheaper than its radius, goals included, and for no others.
    pub fn towards(traversal: &'t TraversalMap, source: Cell, goals: &'t GoalDistance) -> Self {
        let mut cost = vec![f32::INFINITY; traversal.padded.len()];
        let (starts, stranded) = traversal.seed(&[source], &mut cost, &mut []);
        let stranded = stranded.first().map(|&(cell, _)| cell);
        let Some(&start) = starts.first() else {
            return Self { traversal, cost, search: None, stranded, towards: None };
        };
        let estimate = goals.cost[start];
        if !estimate.is_finite() {
            // No goal can be reached from here: nothing to search.
            return Self { traversal, cost, search: None, stranded, towards: Some((goals, Vec::new())) };
        }
        let mut open = vec![0u64; cost.len().div_ceil(64)];
        open[start / 64] |= 1 << (start % 64);
        match Buckets::guided(start, estimate, traversal.step_bounds()) {
            Some(search) => Self { traversal, cost, search: Some(search), stranded, towards: Some((goals, open)) },
            None => {
                // Step costs too far apart for buckets: the full search.
                heap::<_, false>(&traversal.weighted(), &mut cost, &mut [], &starts);
                Self { traversal, cost, search: None, stranded, towards: None }
            }
        }
    }

    /// Every cell cheaper than this is answered by [`Self::cost`] (for a
    /// search towards goals: every goal, and every cell whose cost plus its
    /// distance to the nearest goal is below it); every goal it does not
    /// answer costs at least this, or is unreachable. Infinite once the
    /// search has settled every cell it can.
    pub fn radius(&self) -> f64 {
        self.search.as_ref().map_or(f64::INFINITY, |s| f64::from(s.radius()))
    }

    /// Resumes the search until [`Self::radius`] is at least `radius`
    /// (everything, for an infinite one), and in any case a step further.
    pub fn grow_to(&mut self, radius: f64) {
        let Some(search) = &mut self.search else { return };
        // At least one bucket more, so that every call makes progress.
        let end = search.end_for(radius as f32).max(search.current + 1);
        match &mut self.towards {
            Some((goals, open)) => {
                search.drain_guided(&self.traversal.weighted(), &mut self.cost, &goals.cost, open, end)
            }
            None if self.traversal.is_uniform() => {
                search.drain::<_, false, false>(&self.traversal.uniform(), &mut self.cost, &mut [], end)
            }
            None => search.drain::<_, false, false>(&self.traversal.weighted(), &mut self.cost, &mut [], end),
        }
        if search.exhausted() {
            self.search = None;
        }
    }

    /// Resumes the search until it answers for every one of `cells` or has
    /// settled all it can, in steps that double.
    pub fn grow_to_reach(&mut self, cells: &[Cell]) {
        let mut step = 1.0;
        while self.radius() < f64::INFINITY && !cells.iter().all(|&c| self.cost(c).is_some()) {
            self.grow_to(self.radius() + step);
            step *= 2.0;
        }
    }

    /// The cost of reaching `cell`, if it is below the radius; `None` for a
    /// cell beyond it or unreachable (or, searching towards goals, off the
    /// way to every goal within the radius).
    pub fn cost(&self, cell: Cell) -> Option<f64> {
        if !self.traversal.frame.contains(cell) {
            return None;
        }
        if self.stranded == Some(cell) {
            return Some(0.0);
        }
        let i = self.traversal.window.index(cell)?;
        let c = self.cost[i];
        let key = match &self.towards {
            Some((goals, _)) => c + goals.cost[i],
            None => c,
        };
        (f64::from(key) < self.radius() && c.is_finite()).then_some(f64::from(c))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cost::cost_map;
    use crate::grid::testing::grid_from_picture;

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
        let mut growing = GrowingCostMap::new(&traversal, source);
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
        let mut growing = GrowingCostMap::new(&traversal, Cell::new(0, 0));
        growing.grow_to(100.0);
        assert_eq!(growing.cost(Cell::new(0, 0)), Some(0.0));
        assert_eq!(growing.cost(Cell::new(0, 4)), None);
        let off = GrowingCostMap::new(&traversal, Cell::new(-5, 0));
        assert_eq!(off.cost(Cell::new(-5, 0)), None);
    }

    /// A room with the robot at one end and the only goal at the other:
    /// the search towards it touches the cells along the way, the plain
    /// search every cell as near as the goal.
    #[test]
    fn towards_a_goal_only_the_way_there_is_searched() {
        let row = ".".repeat(60);
        let picture: Vec<&str> = (0..40).map(|_| row.as_str()).collect();
        let grid = grid_from_picture(&picture);
        let traversal = TraversalMap::free_space(&grid, 0.0);
        let (source, goal) = (Cell::new(0, 20), Cell::new(59, 20));
        let goals = GoalDistance::new(&traversal, &[goal]);
        let mut guided = GrowingCostMap::towards(&traversal, source, &goals);
        let mut plain = GrowingCostMap::new(&traversal, source);
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
