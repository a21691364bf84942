//! `hungarian`: optimal robot-to-frontier assignment.
//!
//! Ko et al. 2003, as described by Burgard et al. 2005 (§V) and Wurm et al.
//! 2008 (§III): the Hungarian method on the matrix of path costs from each
//! robot to each frontier. Frontiers are frontier clusters, targets their
//! cells nearest to the robot. With more robots than frontiers, the
//! frontiers are offered again to the robots left over (Wurm et al.'s
//! "duplicating existing targets"); unreachable pairs are forbidden.

use super::registry::{MIN_FRONTIER_SIZE, PolicyDescriptor, SWITCH_METRES};
use super::{Plan, PlanningInput, Policy, Target, cluster_cost_matrix};
use crate::assign::assign_with_dummies;
use crate::cost::CostCache;

pub(super) const NAME: &str = "hungarian";

/// The catalogue's entry: name, what it does, parameters with units, and
/// how it is built from a validated configuration.
pub(super) const DESCRIPTOR: PolicyDescriptor = PolicyDescriptor {
    name: NAME,
    description: "Ko et al. 2003, as described by Burgard et al. 2005 and Wurm et al. 2008: optimal robot-to-frontier assignment on path costs (the Hungarian method)",
    params: &[MIN_FRONTIER_SIZE, SWITCH_METRES],
    build: |c| Box::new(Hungarian { switch_margin: c.get("switch_margin") }),
};

/// The Hungarian method on path costs (Kuhn 1955; Ko et al. 2003).
/// Complexity: one cost map per robot plus O(n²·m) per round.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Hungarian {
    /// Hysteresis: a robot's current frontier costs it this much less, metres.
    pub switch_margin: f64,
}

impl Policy for Hungarian {
    fn name(&self) -> &'static str {
        NAME
    }

    fn plan(&self, input: &PlanningInput<'_>, costs: &mut CostCache<'_>) -> Plan {
        let matrix = cluster_cost_matrix(input, costs, self.switch_margin, &[]);
        let m = input.clusters.len();
        let mut targets: Vec<Option<Target>> = vec![None; input.robots.len()];
        if m == 0 {
            return Plan::of(targets);
        }
        // Rounds: each hands every frontier to at most one of the robots still waiting.
        loop {
            let waiting: Vec<usize> =
                (0..targets.len()).filter(|&i| targets[i].is_none() && matrix[i].iter().any(Option::is_some)).collect();
            if waiting.is_empty() {
                break;
            }
            let costs: Vec<f64> =
                waiting.iter().flat_map(|&i| matrix[i].iter().map(|c| c.map_or(f64::INFINITY, |c| c.score))).collect();
            let Ok(solution) = assign_with_dummies(&costs, waiting.len(), m) else {
                break;
            };
            let mut progressed = false;
            for (row, col) in solution.row_to_col.iter().enumerate() {
                let i = waiting[row];
                if let Some((j, c)) = col.and_then(|j| matrix[i][j].map(|c| (j, c)))
                    && let Some(cell) = matrix.cell(i, j)
                {
                    targets[i] = Some(Target { cell, utility: -c.cost, path_cost: c.cost, gain_region: None });
                    progressed = true;
                }
            }
            if !progressed {
                break;
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
    fn the_total_path_cost_is_minimal() {
        let grid = grid_from_picture(&[
            "################", //
            "?..............?", //
            "################", //
        ]);
        let robots = [robot(0, Cell::new(5, 1), 5.0), robot(1, Cell::new(4, 1), 5.0)];
        let targets = plan_targets(&Hungarian::default(), &grid, &robots);
        // Sums: (0→right 9, 1→left 3) = 12 against (0→left 4, 1→right 10) = 14.
        assert_eq!(targets, vec![Some(Cell::new(14, 1)), Some(Cell::new(1, 1))]);
    }

    /// The same branch as greedy's test: the least total cost sends robot 0
    /// right and robot 1 (in the branch) left, 11.4 against greedy's 13.4;
    /// greedy and closest frontier answer otherwise.
    #[test]
    fn the_least_total_beats_the_cheapest_pair_first() {
        let (grid, robots, left, right) = cheapest_pair_trap();
        let (left, right) = (Some(left), Some(right));
        assert_eq!(plan_targets(&Hungarian::default(), &grid, &robots), vec![right, left]);
        assert_eq!(plan_with_defaults("greedy", &grid, &robots), vec![left, right]);
        assert_eq!(plan_with_defaults("nearest", &grid, &robots), vec![left, left]);
    }

    #[test]
    fn more_robots_than_frontiers_share_them() {
        let grid = grid_from_picture(&[
            "##########", //
            "?.........", //
            "##########", //
        ]);
        let robots: Vec<_> = (0..3).map(|i| robot(i, Cell::new(5 + i as i32, 1), 5.0)).collect();
        let targets = plan_targets(&Hungarian::default(), &grid, &robots);
        assert!(targets.iter().all(|t| *t == Some(Cell::new(1, 1))), "{targets:?}");
    }
}
