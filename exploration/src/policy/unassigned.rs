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
use super::{Plan, PlanningInput, Policy, Target, current_target, free_space_cost_maps};
use crate::cost::CostCache;
use crate::grid::Cell;

pub(super) const NAME: &str = "unassigned";

/// The catalogue's entry: name, what it does, parameters with units, and
/// how it is built from a validated configuration.
pub(super) const DESCRIPTOR: PolicyDescriptor = PolicyDescriptor {
    name: NAME,
    description: "each robot in turn (by id) takes the closest frontier cell no other robot has taken yet (Wurm et al. 2008, §VI: the baseline of their experiments)",
    params: &[MIN_FRONTIER_SIZE, SWITCH_METRES],
    build: |c| Box::new(Unassigned { switch_margin: c.get("switch_margin") }),
};

/// Wurm et al. 2008's baseline. Complexity: one cost map per robot, then
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
        let frontier = input.frontier_cells();
        let maps = free_space_cost_maps(input, costs);
        let mut order: Vec<usize> = (0..input.robots.len()).collect();
        order.sort_by_key(|&i| input.robots[i].id);
        let mut taken: Vec<Cell> = Vec::new();
        let mut targets = vec![None; input.robots.len()];
        for i in order {
            let robot = &input.robots[i];
            let reachable: Vec<(Cell, f64)> =
                frontier.iter().filter_map(|&cell| robot.cost_to(&maps[i], cell).map(|cost| (cell, cost))).collect();
            // Ties go to the first cell in row-major order: deterministic.
            let closest = |free_only: bool| {
                reachable
                    .iter()
                    .copied()
                    .filter(|(cell, _)| !free_only || !taken.contains(cell))
                    .min_by(|a, b| a.1.total_cmp(&b.1).then(a.0.y.cmp(&b.0.y)).then(a.0.x.cmp(&b.0.x)))
            };
            let Some(best) = closest(true).or_else(|| closest(false)) else { continue };
            // Hysteresis: keep the current target while it is free and not
            // farther than the best by more than the margin.
            let kept = current_target(robot)
                .filter(|c| !taken.contains(c))
                .and_then(|c| reachable.iter().copied().find(|(cell, _)| *cell == c))
                .filter(|(_, cost)| cost - self.switch_margin <= best.1);
            let (cell, cost) = kept.unwrap_or(best);
            taken.push(cell);
            targets[i] = Some(Target { cell, utility: -cost, path_cost: cost, gain_region: None });
        }
        Plan::of(targets)
    }
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
}
