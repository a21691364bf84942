//! `greedy`: the cheapest robot–frontier pair first.
//!
//! Bautin, Simonin & Charpillet 2011, Algorithm 2: repeatedly find
//! (i, j) = argmin C_ij over the robots still without a frontier and the
//! frontiers not yet taken, assign, and remove both; when the frontiers run
//! out, start again from the full set (F = F_init), so that every robot gets
//! one. C_ij is the path length from robot i to the nearest cell of frontier
//! (cluster) j, which is also the robot's target.

use super::registry::{MIN_FRONTIER_SIZE, PolicyDescriptor, SWITCH_METRES};
use super::{Plan, PlanningInput, Policy, Target, cluster_cost_matrix};
use crate::cost::CostCache;

pub(super) const NAME: &str = "greedy";

/// The catalogue's entry: name, what it does, parameters with units, and
/// how it is built from a validated configuration.
pub(super) const DESCRIPTOR: PolicyDescriptor = PolicyDescriptor {
    name: NAME,
    description: "repeatedly the robot-frontier pair of lowest path cost, both removed; when frontiers run out, start again from all of them (Bautin et al. 2011, Algorithm 2)",
    params: &[MIN_FRONTIER_SIZE, SWITCH_METRES],
    build: |c| Box::new(Greedy { switch_margin: c.get("switch_margin") }),
};

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
        let matrix = cluster_cost_matrix(input, costs, self.switch_margin, &[]);
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
    use crate::policy::testing::{cheapest_pair_trap, plan_targets, plan_with_defaults, robot};

    #[test]
    fn the_cheapest_pair_goes_first_and_frontiers_are_reused_when_they_run_out() {
        // Bautin et al. 2011, Fig. 4: robots spread over the frontiers;
        // a third robot gets a frontier again once both are taken.
        let grid = grid_from_picture(&[
            "##############", //
            "?............?", //
            "##############", //
        ]);
        let (left, right) = (Some(Cell::new(1, 1)), Some(Cell::new(12, 1)));
        let robots = [robot(0, Cell::new(3, 1), 5.0), robot(1, Cell::new(4, 1), 5.0), robot(2, Cell::new(5, 1), 5.0)];
        // Robot 0 and the left end are the cheapest pair (2); robot 2 and the
        // right end the cheapest left (7); robot 1 then reuses the left end.
        assert_eq!(plan_targets(&Greedy::default(), &grid, &robots), vec![left, left, right]);
        // Every robot is nearer the left end: closest frontier sends all three.
        assert_eq!(plan_with_defaults("nearest", &grid, &robots), vec![left, left, left]);
    }

    /// Greedy is myopic: the cheapest pair first even when the team pays for
    /// it. Robot 1 sits in a branch: 2.4 from the left end, 11.4 from the
    /// right; robot 0 is 2 and 9 away. Greedy gives robot 0 the left end and
    /// robot 1 the far right (13.4 in all); the optimal assignment swaps them
    /// (11.4); closest frontier sends both left.
    #[test]
    fn the_cheapest_pair_wins_even_when_the_total_is_worse() {
        let (grid, robots, left, right) = cheapest_pair_trap();
        let (left, right) = (Some(left), Some(right));
        assert_eq!(plan_targets(&Greedy::default(), &grid, &robots), vec![left, right]);
        assert_eq!(plan_with_defaults("nearest", &grid, &robots), vec![left, left]);
        assert_eq!(plan_with_defaults("hungarian", &grid, &robots), vec![right, left]);
    }
}
