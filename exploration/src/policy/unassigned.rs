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

use super::registry::{MIN_FRONTIER_SIZE, PolicyDescriptor, SWITCH_METRES};
use super::{GrowingSearches, Plan, PlanningInput, Policy, RobotView, Target, current_target};
use crate::cost::{CostCache, TraversalKind};
use crate::grid::Cell;
use crate::reach::Reach;

pub(super) const NAME: &str = "unassigned";

/// The catalogue's entry: name, what it does, parameters with units, and
/// how it is built from a validated configuration.
pub(super) const DESCRIPTOR: PolicyDescriptor = PolicyDescriptor {
    name: NAME,
    description: "each robot in turn (by id) takes the closest frontier cell no other robot has taken yet (Wurm et al. 2008, §VI: the baseline of their experiments)",
    params: &[MIN_FRONTIER_SIZE, SWITCH_METRES],
    build: |c| Box::new(Unassigned { switch_margin: c.get("switch_margin") }),
};

/// Wurm et al. 2008's baseline. Complexity: per robot, a search as far as
/// its closest free frontier cell (the whole known map at worst), then
/// O(n · f) for the choices.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Unassigned {
    /// Hysteresis: the current target wins unless another is closer by more than this, metres.
    pub switch_margin: f64,
}

impl Policy for Unassigned {
    fn name(&self) -> &'static str {
        NAME
    }

    fn plan(&self, input: &PlanningInput<'_>, costs: &mut CostCache<'_>) -> Plan {
        self.plan_searching(input, costs, FIRST_SEARCH_M)
    }
}

/// How far each robot's search goes first, metres: the closest free
/// frontier cell is usually nearer, and a search is widened when it is not.
const FIRST_SEARCH_M: f64 = 8.0;

impl Unassigned {
    /// The plan, from searches that start at `first_limit` metres and are
    /// widened while a robot's choice still depends on what lies beyond.
    fn plan_searching(&self, input: &PlanningInput<'_>, costs: &mut CostCache<'_>, first_limit: f64) -> Plan {
        let frontier = input.frontier_cells();
        let kinds: Vec<TraversalKind> =
            input.robots.iter().map(|r| TraversalKind::free_space(r.capabilities.footprint_radius_m)).collect();
        let mut searches = GrowingSearches::new(input, costs, &kinds, &frontier, first_limit);
        let mut order: Vec<usize> = (0..input.robots.len()).collect();
        order.sort_by_key(|&i| input.robots[i].id);
        let mut taken: Vec<Cell> = Vec::new();
        let mut targets = vec![None; input.robots.len()];
        for i in order {
            let robot = &input.robots[i];
            let choice = loop {
                match self.choose(robot, &frontier, searches.reach(i), &taken) {
                    Choice::Decided(choice) => break choice,
                    Choice::SearchFurther => searches.widen(&[i]),
                }
            };
            let Some((cell, cost)) = choice else { continue };
            taken.push(cell);
            targets[i] = Some(Target { cell, utility: -cost, path_cost: cost, gain_region: None });
        }
        Plan::of(targets)
    }

    /// The robot's cell and its cost, if what its search settled decides it.
    fn choose(&self, robot: &RobotView, frontier: &[Cell], reach: &Reach, taken: &[Cell]) -> Choice {
        let reachable: Vec<(Cell, f64)> = frontier
            .iter()
            .enumerate()
            .filter(|(_, cell)| robot.may_target(**cell))
            .filter_map(|(k, &cell)| reach.cost(k).map(|cost| (cell, cost)))
            .collect();
        // Every cell not settled costs at least this.
        let unknown = reach.unknown_at_least();
        // Ties go to the first cell in row-major order: deterministic.
        let closest = |free_only: bool| {
            reachable
                .iter()
                .copied()
                .filter(|(cell, _)| !free_only || !taken.contains(cell))
                .min_by(|a, b| a.1.total_cmp(&b.1).then(a.0.y.cmp(&b.0.y)).then(a.0.x.cmp(&b.0.x)))
        };
        let best = match closest(true) {
            // A cell not settled could be as close.
            Some(best) if best.1 >= unknown => return Choice::SearchFurther,
            Some(best) => best,
            None if unknown.is_finite() => return Choice::SearchFurther,
            None => match closest(false) {
                Some(best) => best,
                None => return Choice::Decided(None),
            },
        };
        // Hysteresis: keep the current target while it is free and not
        // farther than the best by more than the margin.
        let current = current_target(robot).filter(|c| !taken.contains(c) && robot.may_target(*c));
        let known = current.and_then(|c| reachable.iter().copied().find(|(cell, _)| *cell == c));
        if current.is_some() && known.is_none() && unknown - self.switch_margin <= best.1 {
            return Choice::SearchFurther;
        }
        let kept = known.filter(|(_, cost)| cost - self.switch_margin <= best.1);
        Choice::Decided(Some(kept.unwrap_or(best)))
    }
}

/// A robot's choice, or that its search must go further first.
enum Choice {
    Decided(Option<(Cell, f64)>),
    SearchFurther,
}

#[cfg(test)]
mod tests {
    use crate::grid::Cell;
    use crate::grid::testing::grid_from_picture;
    use crate::policy::testing::{plan_with_defaults, robot};

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
        #![proptest_config(proptest::prelude::ProptestConfig { cases: 400, ..Default::default() })]

        /// Searches that start short and widen choose what full searches choose.
        #[test]
        fn growing_searches_choose_what_full_searches_choose(
            width in 3u32..22,
            height in 3u32..16,
            cells in proptest::collection::vec(0u8..100, 8..96),
            robots in proptest::collection::vec((0u32..400, proptest::option::of(0u32..400)), 1..7),
            first in 0.0f64..3.0,
            switch_margin in proptest::prop_oneof![proptest::strategy::Just(0.0), 0.0f64..3.0],
            uniform in proptest::prelude::any::<bool>(),
        ) {
            use crate::cost::CostCache;
            use crate::policy::testing::{random_situation, with_input};
            let situation = random_situation(width, height, &cells, &robots, uniform);
            proptest::prop_assume!(situation.is_some());
            let Some((grid, views)) = situation else { return Ok(()) };
            let policy = super::Unassigned { switch_margin };
            let (growing, full) = with_input(&grid, &views, &vec![Vec::new(); views.len()], |input| {
                (
                    policy.plan_searching(input, &mut CostCache::new(&grid), first),
                    policy.plan_searching(input, &mut CostCache::new(&grid), f64::INFINITY),
                )
            });
            proptest::prop_assert_eq!(growing.targets, full.targets);
        }
    }
}
