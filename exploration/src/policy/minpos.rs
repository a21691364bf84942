//! `minpos`: the frontier for which the fewest robots are closer.
//!
//! Bautin, Simonin & Charpillet 2011, Algorithm 3 (MinPos). C_ij is robot
//! i's wavefront distance to frontier j on the configuration space (obstacles
//! inflated by the robot's radius, §IV-B). Robot i's position towards j is
//! P_ij = #{k ≠ i : C_kj < C_ij}; it takes j = argmin_j P_ij, ties broken by
//! the least C_ij. The paper propagates one wavefront from each frontier so
//! that each robot can compute every C_kj alone; the central executive
//! propagates one from each robot instead, which gives the same C_ij (paths
//! on the grid are reversible) with min(robots, frontiers) fewer maps in
//! large teams. The target is the frontier's cell nearest to the robot,
//! where descending the frontier's potential field leads.

use super::{Plan, PlanningInput, Policy, Target, cluster_cost_matrix};
use crate::cost::CostCache;

pub(super) const NAME: &str = "minpos";

/// Bautin et al. 2011, Algorithm 3. Complexity: one cost map per robot plus
/// O(n²·m) for the positions (O(n·m) per robot as in the paper).
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct MinPos {
    /// Hysteresis: a robot's distance to its current frontier counts this
    /// much shorter, in its position and its tie-break, metres.
    pub switch_margin: f64,
}

impl Policy for MinPos {
    fn name(&self) -> &'static str {
        NAME
    }

    fn plan(&self, input: &PlanningInput<'_>, costs: &mut CostCache<'_>) -> Plan {
        let matrix = cluster_cost_matrix(input, costs, self.switch_margin);
        let n = matrix.len();
        let targets = (0..n)
            .map(|i| {
                matrix[i]
                    .iter()
                    .enumerate()
                    .filter_map(|(j, c)| c.map(|c| (j, c)))
                    .map(|(j, c)| {
                        let position = (0..n)
                            .filter(|&k| k != i && matrix[k][j].is_some_and(|other| other.cost < c.score))
                            .count();
                        (position, c.score, j, c)
                    })
                    .min_by(|a, b| a.0.cmp(&b.0).then(a.1.total_cmp(&b.1)).then(a.2.cmp(&b.2)))
                    .and_then(|(position, _, j, c)| {
                        Some(Target {
                            cell: matrix.cell(i, j)?,
                            utility: -(position as f64),
                            path_cost: c.cost,
                            gain_region: None,
                        })
                    })
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
    use crate::policy::Nearest;
    use crate::policy::testing::{plan_targets, robot};

    /// Bautin et al. 2011, Fig. 6: a group of robots beside one frontier,
    /// another frontier behind them. Closest frontier sends all of them to
    /// the near one; MinPos splits the group evenly between the two.
    #[test]
    fn a_group_splits_evenly_between_two_frontiers() {
        let grid = grid_from_picture(&[
            "######################", //
            "?....................?", //
            "?....................?", //
            "######################", //
        ]);
        // Four robots bunched near the left frontier.
        let cells = [Cell::new(4, 1), Cell::new(4, 2), Cell::new(5, 1), Cell::new(5, 2)];
        let robots: Vec<_> = cells.iter().enumerate().map(|(i, &c)| robot(i as u64, c, 3.0)).collect();
        let nearest = plan_targets(&Nearest::default(), &grid, &robots);
        assert!(nearest.iter().all(|t| t.is_some_and(|c| c.x == 1)), "{nearest:?}");
        let minpos = plan_targets(&MinPos::default(), &grid, &robots);
        let left = minpos.iter().filter(|t| t.is_some_and(|c| c.x == 1)).count();
        let right = minpos.iter().filter(|t| t.is_some_and(|c| c.x == 20)).count();
        assert_eq!((left, right), (2, 2), "{minpos:?}");
        // The two nearer the left go left.
        assert!(minpos[0].is_some_and(|c| c.x == 1) && minpos[1].is_some_and(|c| c.x == 1), "{minpos:?}");
    }
}
