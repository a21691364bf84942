//! `nearest`: every robot heads for its closest frontier cell.
//!
//! Yamauchi 1998 ("each robot moves to the closest frontier"); Bautin et al.
//! 2011, Algorithm 1 (Closest frontier, j = argmin_j C_ij); the
//! "uncoordinated" strategy of Burgard et al. 2005, §IV-C. There is no
//! arbitration: robots that share a closest frontier all go there.

use super::{Plan, PlanningInput, Policy, Target, current_target, free_space_cost_maps};
use crate::cost::CostCache;

pub(super) const NAME: &str = "nearest";

/// Closest frontier cell by path length (Bautin et al. 2011, Algorithm 1).
/// Complexity: one cost map per robot plus O(n·m) for n robots, m frontier cells.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Nearest {
    /// Hysteresis: the current target wins unless another is closer by more than this, metres.
    pub switch_margin: f64,
}

impl Policy for Nearest {
    fn name(&self) -> &'static str {
        NAME
    }

    fn plan(&self, input: &PlanningInput<'_>, costs: &mut CostCache<'_>) -> Plan {
        let frontier = input.frontier_cells();
        let targets = free_space_cost_maps(input, costs)
            .iter()
            .zip(input.robots)
            .map(|(map, robot)| {
                let current = current_target(robot);
                frontier
                    .iter()
                    .filter_map(|&cell| {
                        let cost = map.cost(cell)?;
                        let score = if Some(cell) == current { cost - self.switch_margin } else { cost };
                        Some((score, cost, cell))
                    })
                    // Ties go to the first cell in row-major order: deterministic.
                    .min_by(|a, b| a.0.total_cmp(&b.0).then(a.2.y.cmp(&b.2.y)).then(a.2.x.cmp(&b.2.x)))
                    .map(|(_, cost, cell)| Target { cell, utility: -cost, path_cost: cost, gain_region: None })
            })
            .collect();
        Plan::of(targets)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::grid::Cell;
    use crate::grid::testing::grid_from_picture;
    use crate::policy::testing::{plan_targets, robot};

    #[test]
    fn robots_sharing_a_closest_frontier_all_go_there() {
        // Bautin et al. 2011, Fig. 6(a): a group beside one frontier, another
        // frontier behind them; closest-frontier sends everyone to the near one.
        let grid = grid_from_picture(&[
            "##############", //
            "?............?", //
            "##############", //
        ]);
        let robots: Vec<_> = (0..4).map(|i| robot(i, Cell::new(2 + i as i32 % 2, 1), 5.0)).collect();
        let targets = plan_targets(&Nearest::default(), &grid, &robots);
        assert!(targets.iter().all(|t| *t == Some(Cell::new(1, 1))), "{targets:?}");
    }

    #[test]
    fn a_robot_with_no_reachable_frontier_gets_nothing() {
        let grid = grid_from_picture(&[
            "#######", //
            "#..#..?", //
            "#######", //
        ]);
        let targets =
            plan_targets(&Nearest::default(), &grid, &[robot(0, Cell::new(1, 1), 5.0), robot(1, Cell::new(4, 1), 5.0)]);
        assert_eq!(targets, vec![None, Some(Cell::new(5, 1))]);
    }
}
