//! `unassigned`: each robot takes the closest frontier cell that no other
//! robot has taken yet.
//!
//! Wurm, Stachniss & Burgard 2008, §VI: the baseline of their experiments,
//! "a frontier-based approach in which each robot is assigned to the
//! closest frontier which has not been assigned to another robot yet". It
//! is weaker than Bautin's greedy (which takes the cheapest robot-frontier
//! pair of all first): robots choose one after another, and frontiers are
//! cells, so two robots can take neighbouring cells of one frontier; the
//! paper notes it "will in general also assign more than one robot to one
//! room or corridor". The paper does not say in which order robots choose;
//! here by robot id. When every reachable frontier cell is taken, a robot
//! shares the closest one.

use std::sync::{Mutex, PoisonError};

use super::registry::{MIN_FRONTIER_SIZE, PolicyDescriptor, SWITCH_METRES};
use super::{Plan, PlanningInput, Policy, RobotView, Target, current_target, towards_goals};
use crate::cost::{CostCache, GrowingCostMap, TraversalKind};
use crate::grid::Cell;
use crate::workers::in_parallel;

pub(super) const NAME: &str = "unassigned";

/// The catalogue's entry: name, what it does, parameters with units, and
/// how it is built from a validated configuration.
pub(super) const DESCRIPTOR: PolicyDescriptor = PolicyDescriptor {
    name: NAME,
    description: "each robot in turn (by id) takes the closest frontier cell no other robot has taken yet (Wurm et al. 2008, §VI: the baseline of their experiments)",
    params: &[MIN_FRONTIER_SIZE, SWITCH_METRES],
    build: |c| Box::new(Unassigned { switch_margin: c.get("switch_margin") }),
};

/// Wurm et al. 2008's baseline. Complexity: per robot, a search out to its
/// choice (a whole cost map at worst), then O(n · f) for the choices.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Unassigned {
    /// Hysteresis: the current target wins unless another is closer by more than this, metres.
    pub switch_margin: f64,
}

impl Policy for Unassigned {
    fn name(&self) -> &'static str {
        NAME
    }

    /// Each robot's search goes only as far as its choice needs (see
    /// [`Unassigned::choose`]). The choices depend on each other in id
    /// order, the searches need not: they run on the planner's threads, in
    /// id order, each with the cells the robots before it would take by
    /// what their searches, finished by then, reached; then, in rounds,
    /// again for the robots whose choice is still not sure. The choices are
    /// then made in id order from what the searches reached, as one robot
    /// after another would; a robot still unsure there searches again on
    /// its own. The guesses decide how far each search goes, never what it
    /// chooses.
    fn plan(&self, input: &PlanningInput<'_>, costs: &mut CostCache<'_>) -> Plan {
        let frontier = input.frontier_cells();
        let kinds: Vec<TraversalKind> = input.robots.iter().map(RobotView::free_space).collect();
        let traversals = towards_goals(&kinds, costs, &frontier);
        let search = |i: usize, taken: &[Cell]| {
            let (robot, (traversal, goals)) = (&input.robots[i], &traversals[i]);
            let mut search = GrowingCostMap::towards(traversal, robot.cell, goals);
            let choice = self.choose(robot, &mut search, &frontier, taken);
            (choice, Reached::of(robot, &search, &frontier))
        };
        let mut order: Vec<usize> = (0..input.robots.len()).collect();
        order.sort_by_key(|&i| input.robots[i].id);
        let mut reached = self.first_searches(input, &order, |i, taken| search(i, taken).1);
        for _ in 0..SPECULATIVE_ROUNDS {
            let unsure = self.unsure(input.robots, &order, &reached);
            if unsure.is_empty() {
                break;
            }
            let again = in_parallel(&unsure, input.workers, |(i, taken)| search(*i, taken).1);
            for ((i, _), r) in unsure.into_iter().zip(again) {
                if r.radius > reached[i].radius {
                    reached[i] = r;
                }
            }
        }
        let mut taken: Vec<Cell> = Vec::new();
        let mut targets = vec![None; input.robots.len()];
        for &i in &order {
            let robot = &input.robots[i];
            let choice = match self.decide(robot, &reached[i], &taken) {
                Ok(choice) => choice,
                Err(_) => search(i, &taken).0,
            };
            let Some((cell, cost)) = choice else { continue };
            taken.push(cell);
            targets[i] = Some(Target { cell, utility: -cost, path_cost: cost, gain_region: None });
        }
        Plan::of(targets)
    }
}

/// How many times the robots whose choices are not sure search again
/// together before the rest search one after another. Each round makes at
/// least the first unsure robot in id order sure.
const SPECULATIVE_ROUNDS: usize = 4;

/// The first searches' results as they come in, by position in id order,
/// and the choices made from them so far.
struct SoFar {
    reached: Vec<Option<Reached>>,
    /// Positions before this are all searched; their choices are `taken`.
    settled: usize,
    taken: Vec<Cell>,
}

impl SoFar {
    /// Nothing searched yet, of `robots`.
    fn new(robots: usize) -> Self {
        Self { reached: std::iter::repeat_with(|| None).take(robots).collect(), settled: 0, taken: Vec::new() }
    }

    /// The cells the robots before position `p` would take, by `choice`
    /// (position, what its search reached, the cells taken before it),
    /// from the searches finished so far; a robot still searching takes
    /// none.
    fn taken_before(&mut self, p: usize, choice: impl Fn(usize, &Reached, &[Cell]) -> Option<Cell>) -> Vec<Cell> {
        while self.settled < p {
            let Some(reached) = &self.reached[self.settled] else { break };
            self.taken.extend(choice(self.settled, reached, &self.taken));
            self.settled += 1;
        }
        let mut taken = self.taken.clone();
        for (q, reached) in self.reached.iter().enumerate().take(p).skip(self.settled) {
            if let Some(reached) = reached {
                taken.extend(choice(q, reached, &taken));
            }
        }
        taken
    }
}

/// What a robot's search has reached: the frontier cells it may be sent
/// to with their costs, and the radius below which nothing is missing.
struct Reached {
    cells: Vec<(Cell, f64)>,
    radius: f64,
}

impl Reached {
    fn of(robot: &RobotView, search: &GrowingCostMap<'_>, frontier: &[Cell]) -> Self {
        let cells =
            frontier.iter().filter(|&&c| robot.may_target(c)).filter_map(|&c| Some((c, search.cost(c)?))).collect();
        Self { cells, radius: search.radius() }
    }

    /// The closest cell reached, of those not `taken` when `free_only`.
    /// Ties go to the first cell in row-major order: deterministic.
    fn closest(&self, taken: &[Cell], free_only: bool) -> Option<(Cell, f64)> {
        self.cells
            .iter()
            .copied()
            .filter(|(cell, _)| !free_only || !taken.contains(cell))
            .min_by(|a, b| a.1.total_cmp(&b.1).then(a.0.y.cmp(&b.0.y)).then(a.0.x.cmp(&b.0.x)))
    }
}

impl Unassigned {
    /// The robot's choice: the closest frontier cell not `taken`, or its
    /// current target while that is free and not farther by more than the
    /// margin; the closest taken one when every reachable cell is taken.
    /// Searches further until the choice is sure.
    fn choose(
        &self,
        robot: &RobotView,
        search: &mut GrowingCostMap<'_>,
        frontier: &[Cell],
        taken: &[Cell],
    ) -> Option<(Cell, f64)> {
        // A robot's first look: about its own size past the nearest
        // frontier cell (where a search towards the frontier starts), then
        // a quarter of the slack further each time.
        loop {
            let reached = Reached::of(robot, search, frontier);
            let best = match self.decide(robot, &reached, taken) {
                Ok(choice) => return choice,
                Err(best) => best,
            };
            let mut radius = search.next_radius();
            if let Some(cost) = best {
                // Just past it: a search towards the frontier pays for
                // every metre of slack with a wider band.
                radius = radius.min(cost + self.margin(robot, taken) + 1e-3);
            }
            search.grow_to(radius);
        }
    }

    /// The choice [`Self::choose`] makes from what a search `reached`, or,
    /// when a cell not reached yet could still change it, the cost of the
    /// closest free cell reached so far. A cell not reached costs at least
    /// the radius.
    fn decide(&self, robot: &RobotView, reached: &Reached, taken: &[Cell]) -> Result<Option<(Cell, f64)>, Option<f64>> {
        let closest = |free_only: bool| reached.closest(taken, free_only);
        let best = closest(true);
        let everything = reached.radius == f64::INFINITY;
        // Sure when nothing unreached can be closer or tie, nor be a
        // current target within the margin (for a robot that holds one).
        let sure = best.is_some_and(|(_, cost)| cost + self.margin(robot, taken) < reached.radius);
        if !(sure || everything) {
            return Err(best.map(|(_, cost)| cost));
        }
        let Some(best) = best.or_else(|| closest(false)) else { return Ok(None) };
        // Hysteresis: keep the current target while it is free and not
        // farther than the best by more than the margin.
        let kept = current_target(robot)
            .filter(|c| !taken.contains(c))
            .and_then(|c| reached.cells.iter().copied().find(|(cell, _)| *cell == c))
            .filter(|(_, cost)| cost - self.switch_margin <= best.1);
        Ok(Some(kept.unwrap_or(best)))
    }

    /// Every robot's first search (`search(robot, taken)`), by index, made
    /// in id `order` on the planner's threads. Each is told the cells the
    /// robots before it would take by what their searches, finished by
    /// then, reached: the threads take robots in order, so all but the few
    /// still searching. Only what each search reached is kept: a search
    /// holds a label per known cell, too much to keep one per robot of a
    /// large team.
    fn first_searches(
        &self,
        input: &PlanningInput<'_>,
        order: &[usize],
        search: impl Fn(usize, &[Cell]) -> Reached + Sync,
    ) -> Vec<Reached> {
        let so_far = Mutex::new(SoFar::new(order.len()));
        let lock = || so_far.lock().unwrap_or_else(PoisonError::into_inner);
        let likely =
            |p: usize, reached: &Reached, taken: &[Cell]| self.likely(&input.robots[order[p]], reached, taken).0;
        let positions: Vec<usize> = (0..order.len()).collect();
        in_parallel(&positions, input.workers, |&p| {
            let taken = lock().taken_before(p, likely);
            let reached = search(order[p], &taken);
            lock().reached[p] = Some(reached);
        });
        let mut by_robot: Vec<Option<Reached>> = std::iter::repeat_with(|| None).take(order.len()).collect();
        for (&i, reached) in order.iter().zip(so_far.into_inner().unwrap_or_else(PoisonError::into_inner).reached) {
            by_robot[i] = reached;
        }
        by_robot.into_iter().flatten().collect()
    }

    /// The robots whose choice is not sure from what their searches
    /// `reached`, each with the cells the robots before it in id `order`
    /// would take by [`Self::likely`].
    fn unsure(&self, robots: &[RobotView], order: &[usize], reached: &[Reached]) -> Vec<(usize, Vec<Cell>)> {
        let mut taken = Vec::new();
        let mut unsure = Vec::new();
        for &i in order {
            let (choice, sure) = self.likely(&robots[i], &reached[i], &taken);
            if !sure {
                unsure.push((i, taken.clone()));
            }
            taken.extend(choice);
        }
        unsure
    }

    /// The robot's choice from what its search `reached` when it is sure
    /// (true), else a guess: its closest free cell reached so far, right
    /// unless a cell not reached yet is as close.
    fn likely(&self, robot: &RobotView, reached: &Reached, taken: &[Cell]) -> (Option<Cell>, bool) {
        match self.decide(robot, reached, taken) {
            Ok(choice) => (choice.map(|(cell, _)| cell), true),
            Err(_) => (reached.closest(taken, true).map(|(cell, _)| cell), false),
        }
    }

    /// How far past its closest cell a robot's search must go: the
    /// hysteresis margin for a robot whose current target is still free.
    fn margin(&self, robot: &RobotView, taken: &[Cell]) -> f64 {
        if current_target(robot).is_some_and(|c| !taken.contains(&c)) { self.switch_margin } else { 0.0 }
    }
}

#[cfg(test)]
mod tests {
    use crate::grid::Cell;
    use crate::grid::testing::grid_from_picture;
    use crate::policy::testing::{plan_with_defaults, robot};
    use crate::workers::Workers;

    /// Two robots beside a frontier two cells high, another frontier far
    /// behind them: each takes its own cell of the near frontier (Wurm's
    /// remark: one corridor, two robots). Closest frontier sends both to the
    /// same cell; MinPos sends the second one to the far frontier.
    #[test]
    fn robots_take_distinct_cells_even_of_one_frontier() {
        let grid = grid_from_picture(&[
            "######################", //
            "?....................?", //
            "?....................?", //
            "######################", //
        ]);
        let robots = [robot(0, Cell::new(4, 1), 3.0), robot(1, Cell::new(5, 1), 3.0)];
        let targets = plan_with_defaults("unassigned", &grid, &robots);
        assert!(targets.iter().all(|t| t.is_some_and(|c| c.x == 1)), "{targets:?}");
        assert_ne!(targets[0], targets[1], "{targets:?}");
        let nearest = plan_with_defaults("nearest", &grid, &robots);
        assert_eq!(nearest[0], nearest[1], "{nearest:?}");
        let minpos = plan_with_defaults("minpos", &grid, &robots);
        assert!(minpos.iter().any(|t| t.is_some_and(|c| c.x == 20)), "{minpos:?}");
    }

    /// More robots than frontier cells: the last one shares the closest cell.
    #[test]
    fn when_every_cell_is_taken_a_robot_shares_the_closest() {
        let grid = grid_from_picture(&[
            "#######", //
            "?.....#", //
            "#######", //
        ]);
        let robots = [robot(0, Cell::new(3, 1), 3.0), robot(1, Cell::new(5, 1), 3.0)];
        let targets = plan_with_defaults("unassigned", &grid, &robots);
        assert_eq!(targets, vec![Some(Cell::new(1, 1)), Some(Cell::new(1, 1))]);
    }

    proptest::proptest! {
        #![proptest_config(crate::testing::seeded_proptest(256))]
        /// Searching only as far as each choice needs chooses as the full
        /// cost maps do, with current targets, exclusions and more robots
        /// than frontier cells.
        #[test]
        fn searching_as_far_as_needed_chooses_as_the_full_search(
            width in 4u32..28,
            height in 4u32..28,
            seed in 0u64..1_000_000,
            robots in 1usize..8,
            margin_tenths in 0u32..30,
        ) {
            use crate::cost::{CostCache, TraversalKind, cost_map};
            use crate::frontier::{FrontierMap, clusters};
            use crate::policy::testing::{random_known_rectangle, random_team};
            use crate::policy::{Plan, PlanningInput, Policy, Target};
            use crate::rng::SplitMix64;

            let mut rng = SplitMix64::new(seed);
            let (grid, free) = random_known_rectangle(width, height, &mut rng, |rng| if rng.below(5) == 0 { 95 } else { 5 });
            proptest::prop_assume!(!free.is_empty());
            let team = random_team(robots, &free, &free, true, &mut rng);
            let frontier_map = FrontierMap::detect(&grid);
            let clusters = clusters(&frontier_map, 1);
            let bids = vec![Vec::new(); robots];
            let input = PlanningInput {
                grid: &grid,
                clusters: &clusters,
                robots: &team,
                workers: Workers::unpaced(1 + (seed % 3) as usize),
                bids: &bids,
                seed: 0,
                reserved: &[],
                rooms: None,
            };
            let policy = super::Unassigned { switch_margin: f64::from(margin_tenths) / 10.0 };
            let lazily = policy.plan(&input, &mut CostCache::new(&grid));
            // The same choices over complete searches.
            let traversal = CostCache::new(&grid).traversal(TraversalKind::free_space(0.0));
            let frontier = input.frontier_cells();
            let mut taken = Vec::new();
            let fully = Plan::of(team.iter().map(|r| {
                let map = cost_map(&traversal, &[r.cell]);
                let cells = frontier.iter().filter(|&&c| r.may_target(c)).filter_map(|&c| Some((c, map.cost(c)?))).collect();
                let complete = super::Reached { cells, radius: f64::INFINITY };
                let (cell, cost) = policy.decide(r, &complete, &taken).ok()??;
                taken.push(cell);
                Some(Target { cell, utility: -cost, path_cost: cost, gain_region: None })
            }).collect());
            proptest::prop_assert_eq!(lazily, fully);
        }
    }
}
