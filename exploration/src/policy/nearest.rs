//! `nearest`: every robot heads for its closest frontier cell.
//!
//! Yamauchi 1998 ("each robot moves to the closest frontier"); Bautin et al.
//! 2011, Algorithm 1 (Closest frontier, j = argmin_j C_ij); the
//! "uncoordinated" strategy of Burgard et al. 2005, §IV-C. There is no
//! arbitration: robots that share a closest frontier all go there.

use super::registry::{MIN_FRONTIER_SIZE, PolicyDescriptor, SWITCH_METRES};
use super::{Plan, PlanningInput, Policy, Target, current_target};
use crate::cost::{CostCache, TraversalKind, labelled_cost_map, shortest_path};

pub(super) const NAME: &str = "nearest";

/// The catalogue's entry: name, what it does, parameters with units, and
/// how it is built from a validated configuration.
pub(super) const DESCRIPTOR: PolicyDescriptor = PolicyDescriptor {
    name: NAME,
    description: "each robot heads for its closest frontier cell, without arbitration (Yamauchi 1998; Bautin et al. 2011, Algorithm 1; the uncoordinated baseline of Burgard et al. 2005)",
    params: &[MIN_FRONTIER_SIZE, SWITCH_METRES],
    build: |c| Box::new(Nearest { switch_margin: c.get("switch_margin") }),
};

/// Closest frontier cell by path length (Bautin et al. 2011, Algorithm 1).
/// Complexity: one wavefront from the frontier for the whole team (one per
/// robot when footprints differ), plus an A* per robot that has a target.
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
        let kinds: Vec<TraversalKind> = input.robots.iter().map(|r| r.free_space()).collect();
        // One wavefront from the whole frontier serves every robot of one
        // footprint: it finds each robot's closest frontier cell (costs are
        // reversible on the free-space traversal).
        let shared = (!kinds.is_empty() && kinds.windows(2).all(|w| w[0] == w[1]))
            .then(|| (costs.traversal(kinds[0]), kinds[0]))
            .map(|(traversal, kind)| (labelled_cost_map(&traversal, &frontier), traversal, kind));
        let targets = input
            .robots
            .iter()
            .map(|robot| {
                let nearest = match &shared {
                    Some((labelled, _, _)) if robot.excluded.is_empty() => labelled
                        .source_of(robot.cell)
                        .and_then(|k| labelled.map().cost(robot.cell).map(|cost| (frontier[k], cost))),
                    _ => None,
                };
                let nearest = nearest.or_else(|| {
                    let kind = robot.free_space();
                    let map = costs.cost_map(kind, robot.cell);
                    frontier
                        .iter()
                        .filter_map(|&cell| robot.cost_to(&map, cell).map(|cost| (cell, cost)))
                        // Ties go to the first cell in row-major order: deterministic.
                        .min_by(|a, b| a.1.total_cmp(&b.1).then(a.0.y.cmp(&b.0.y)).then(a.0.x.cmp(&b.0.x)))
                })?;
                // Hysteresis: stay on the current target unless the nearest is
                // closer by more than the margin.
                let kept = current_target(robot)
                    .filter(|c| *c != nearest.0 && frontier.contains(c) && robot.may_target(*c))
                    .and_then(|c| {
                        let traversal = costs.traversal(robot.free_space());
                        let path = shortest_path(traversal.frame(), robot.cell, c, |n| traversal.passable(n))?;
                        let length: f64 =
                            path.windows(2).map(|w| w[0].distance(w[1])).sum::<f64>() * traversal.frame().resolution;
                        (length - self.switch_margin <= nearest.1).then_some((c, length))
                    });
                let (cell, cost) = kept.unwrap_or(nearest);
                Some(Target { cell, utility: -cost, path_cost: cost, gain_region: None })
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
