//! `minpos`: the frontier for which the fewest robots are closer.
//!
//! Bautin, Simonin & Charpillet 2011, Algorithm 3 (MinPos). C_ij is robot
//! i's wavefront distance to frontier j on the configuration space (obstacles
//! inflated by the robot's radius, §IV-B). Robot i's position towards j is
//! P_ij = #{k ≠ i : C_kj < C_ij}; it takes j = argmin_j P_ij, ties broken by
//! the least C_ij. Only strictly closer robots count, as in the paper, so
//! robots on one cell rank alike everywhere and move as one until something
//! separates them; that is why the simulator starts teams on distinct cells
//! (no tie rule by id changes this: it shifts a co-located robot's position
//! by the same amount at every frontier). The paper propagates one wavefront from each frontier so
//! that each robot can compute every C_kj alone; the central executive
//! propagates one from each robot instead, which gives the same C_ij (paths
//! on the grid are reversible) with min(robots, frontiers) fewer maps in
//! large teams. The target is the frontier's cell nearest to the robot,
//! where descending the frontier's potential field leads.

use super::registry::{MIN_FRONTIER_SIZE, PolicyDescriptor, SWITCH_METRES};
use super::{Plan, PlanningInput, Policy, Target, cluster_cost_matrix};
use crate::cost::CostCache;

pub(super) const NAME: &str = "minpos";

/// The catalogue's entry: name, what it does, parameters with units, and
/// how it is built from a validated configuration.
pub(super) const DESCRIPTOR: PolicyDescriptor = PolicyDescriptor {
    name: NAME,
    description: "Bautin et al. 2011, Algorithm 3 (MinPos): each robot takes the frontier for which the fewest robots are strictly closer, ties by path cost",
    params: &[MIN_FRONTIER_SIZE, SWITCH_METRES],
    build: |c| Box::new(MinPos { switch_margin: c.get("switch_margin") }),
};

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
        let matrix = cluster_cost_matrix(input, costs, self.switch_margin, &[]);
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
    use crate::policy::testing::{plan_targets, plan_with_defaults, robot};

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

    /// Robots on one cell rank alike (Eq. for P_ij counts only strictly
    /// closer robots), so they go where a third robot is not ahead of them:
    /// here robot 0 is closer to the left frontier, the pair on (6, 1) is
    /// second there and first on the right, so both go right. Closest
    /// frontier sends all three left.
    #[test]
    fn robots_on_one_cell_go_where_nobody_is_ahead_of_them() {
        let grid = grid_from_picture(&[
            "######################", //
            "?....................?", //
            "?....................?", //
            "######################", //
        ]);
        let robots = [robot(0, Cell::new(3, 1), 3.0), robot(1, Cell::new(6, 1), 3.0), robot(2, Cell::new(6, 1), 3.0)];
        let targets = plan_with_defaults("minpos", &grid, &robots);
        let xs: Vec<_> = targets.iter().map(|t| t.map(|c| c.x)).collect();
        assert_eq!(xs, [Some(1), Some(20), Some(20)], "{targets:?}");
        let nearest = plan_with_defaults("nearest", &grid, &robots);
        assert!(nearest.iter().all(|t| t.is_some_and(|c| c.x == 1)), "{nearest:?}");
    }
}
