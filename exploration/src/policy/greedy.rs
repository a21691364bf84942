//! `greedy`: the cheapest robot–frontier pair first.
//!
//! Bautin, Simonin & Charpillet 2011, Algorithm 2: repeatedly find
//! (i, j) = argmin C_ij over the robots still without a frontier and the
//! frontiers not yet taken, assign, and remove both; when the frontiers run
//! out, start again from the full set (F = F_init), so that every robot gets
//! one. C_ij is the path length from robot i to the nearest cell of frontier
//! (cluster) j, which is also the robot's target.

use super::{Plan, PlanningInput, Policy, Target, cluster_cost_matrix};
use crate::cost::CostCache;

pub(super) const NAME: &str = "greedy";

/// Bautin et al. 2011, Algorithm 2. Complexity: one cost map per robot plus
/// O(n²·m) for n robots and m frontiers.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Greedy {
    /// Hysteresis: a robot's current frontier costs it this much less, metres.
    pub switch_margin: f64,
}

impl Policy for Greedy {
    fn name(&self) -> &'static str {
        NAME
    }

    fn plan(&self, input: &PlanningInput<'_>, costs: &mut CostCache<'_>) -> Plan {
        let matrix = cluster_cost_matrix(input, costs, self.switch_margin);
        let m = input.clusters.len();
        let mut targets: Vec<Option<Target>> = vec![None; input.robots.len()];
        let mut free_frontier = vec![true; m];
        loop {
            let best = matrix
                .iter()
                .enumerate()
                .filter(|(i, _)| targets[*i].is_none())
                .flat_map(|(i, row)| {
                    row.iter()
                        .enumerate()
                        .filter(|(j, _)| free_frontier[*j])
                        .filter_map(move |(j, c)| c.map(|c| (c.score, i, j, c)))
                })
                // Ties to the lower robot, then the lower frontier: deterministic.
                .min_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)).then(a.2.cmp(&b.2)));
            match best {
                Some((_, i, j, c)) => {
                    targets[i] = matrix.cell(i, j).map(|cell| Target {
                        cell,
                        utility: -c.cost,
                        path_cost: c.cost,
                        gain_region: None,
                    });
                    free_frontier[j] = false;
                    if free_frontier.iter().all(|f| !f) {
                        free_frontier.fill(true);
                    }
                }
                None if free_frontier.iter().any(|f| !f) => free_frontier.fill(true),
                None => break,
            }
        }
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
    fn the_cheapest_pair_goes_first_and_frontiers_are_reused_when_they_run_out() {
        // Bautin et al. 2011, Fig. 4: robots spread over the frontiers;
        // a third robot gets a frontier again once both are taken.
        let grid = grid_from_picture(&[
            "##############", //
            "?............?", //
            "##############", //
        ]);
        let robots = [robot(0, Cell::new(3, 1), 5.0), robot(1, Cell::new(4, 1), 5.0), robot(2, Cell::new(10, 1), 5.0)];
        let targets = plan_targets(&Greedy::default(), &grid, &robots);
        // Robots 0 and 2 are each two cells from an end; robot 0 goes first on
        // the tie (left), robot 2 then takes the right end, and robot 1 gets
        // the left end again once both were taken.
        assert_eq!(targets, vec![Some(Cell::new(1, 1)), Some(Cell::new(1, 1)), Some(Cell::new(12, 1))]);
    }
}
