//! `burgard`: coordinated exploration by utility discounting.
//!
//! Burgard, Moors, Stachniss & Schneider 2005, "Coordinated multi-robot
//! exploration", Algorithm 1. Every frontier cell t starts with utility
//! U_t = 1. Repeatedly the pair (robot i, frontier cell t) maximizing
//! U_t − β·V_t^i is chosen (line 5), where V^i is robot i's cost map by
//! deterministic value iteration over P(occ) (§II-A); then the utility of
//! every frontier cell t' that t's sensor would cover drops by
//! P(‖t − t'‖) (line 6, Eq. 1), with
//!
//! P(d) = 1 − d / max_range  if d < max_range, else 0          (Eq. 2)
//!
//! and P set to zero when an obstacle lies between t and t' (found by ray
//! casting). V is measured in metres × P(occ), so β does not depend on the
//! grid resolution (at the paper's 15 cm cells, V in cells is V/0.15).

use super::registry::{BETA, MIN_FRONTIER_SIZE, OCC_MAX, PolicyDescriptor, SMOOTHING, SWITCH_UTILITY};
use super::{Plan, PlanningInput, Policy, RobotView, Target, costs_to_cells, current_target};
use crate::cost::{CostCache, TraversalKind};
use crate::grid::{Cell, CellClass, OccupancyGrid};
use crate::visibility::line_of_sight;

pub(super) const NAME: &str = "burgard";

/// The catalogue's entry: name, what it does, parameters with units, and
/// how it is built from a validated configuration.
pub(super) const DESCRIPTOR: PolicyDescriptor = PolicyDescriptor {
    name: NAME,
    description: "Burgard et al. 2005, Algorithm 1: greedy on utility minus beta times value-iteration cost; utilities of frontier cells visible from chosen targets drop by P(d) = 1 - d/max_range",
    params: &[MIN_FRONTIER_SIZE, SWITCH_UTILITY, BETA, OCC_MAX, SMOOTHING],
    build: |c| {
        Box::new(Burgard {
            beta: c.get("beta"),
            occ_max: c.get("occ_max"),
            smoothing_sigma_m: c.get("smoothing_sigma_m"),
            switch_margin: c.get("switch_margin"),
        })
    },
};

/// Burgard et al. 2005, Algorithm 1, with Eqs. 1–2.
/// Complexity: one cost map per robot plus O(n²·T) for n robots, T frontier cells.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Burgard {
    /// β ≥ 0, the weight of cost against utility (Algorithm 1, line 5).
    pub beta: f64,
    /// occ_max: cells with a higher P(occ) are not traversable (§II-A).
    pub occ_max: f64,
    /// σ of the Gaussian the map is smoothed with (§II-A), metres.
    pub smoothing_sigma_m: f64,
    /// Hysteresis: a robot's current target scores this much more.
    pub switch_margin: f64,
}

/// P(d) of Eq. 2: the probability that a sensor of range `max_range` covers
/// a cell at distance `d` from where it stands.
pub fn coverage_probability(d: f64, max_range: f64) -> f64 {
    if d < max_range && max_range > 0.0 { 1.0 - d / max_range } else { 0.0 }
}

/// P(‖a − b‖) for a sensor of range `max_range_m` at `a`, zero when an
/// obstacle lies between (Eqs. 1–2 with ray casting, §II-B).
pub(super) fn covered(grid: &OccupancyGrid, a: Cell, b: Cell, max_range_m: f64) -> f64 {
    let resolution = grid.frame().resolution;
    let d = a.distance(b) * resolution;
    let p = coverage_probability(d, max_range_m);
    let opaque = |c: Cell| grid.class_or_wall(c) == CellClass::Occupied;
    if p > 0.0 && line_of_sight(a, b, opaque) { p } else { 0.0 }
}

impl Burgard {
    /// §II-A's traversal for a robot's footprint.
    fn traversal_kind(&self, robot: &RobotView) -> TraversalKind {
        TraversalKind::burgard(self.occ_max, self.smoothing_sigma_m, robot.capabilities.footprint_radius_m)
    }

    /// Line 2 of Algorithm 1: V_t^i for every robot i and frontier cell t.
    pub(super) fn cost_values(
        &self,
        input: &PlanningInput<'_>,
        costs: &mut CostCache<'_>,
        frontier: &[Cell],
    ) -> Vec<Vec<Option<f64>>> {
        let kinds: Vec<TraversalKind> = input.robots.iter().map(|r| self.traversal_kind(r)).collect();
        costs_to_cells(input, costs, &kinds, frontier)
    }

    /// Lines 3–7 of Algorithm 1 on V_t^i (`values`, per robot a row over
    /// the frontier cells, `None` where unreachable or forbidden).
    pub(super) fn assign(
        &self,
        input: &PlanningInput<'_>,
        frontier: &[Cell],
        values: &[Vec<Option<f64>>],
    ) -> Vec<Option<Target>> {
        let grid = input.grid;
        let resolution = grid.frame().resolution;
        // Line 3: all utilities start at 1, less what the targets of robots
        // out of reach already cover (§II-D).
        let mut utility = vec![1.0f64; frontier.len()];
        for &(held, range) in input.reserved {
            let range_cells_sq = ((range / resolution) * (range / resolution)).ceil() as i64;
            for (u, &other) in utility.iter_mut().zip(frontier) {
                if held.distance_squared(other) <= range_cells_sq {
                    *u -= covered(grid, held, other, range);
                }
            }
        }
        let mut targets: Vec<Option<Target>> = vec![None; input.robots.len()];
        // Line 4: while a robot is left without a target.
        loop {
            let best = self.best_pair(input, frontier, values, &utility, &targets);
            // Robots that cannot reach any frontier cell stay without a target.
            let Some((score, i, t)) = best else { break };
            let chosen = frontier[t];
            targets[i] = Some(Target {
                cell: chosen,
                utility: score,
                path_cost: values[i][t].unwrap_or(0.0),
                gain_region: None,
            });
            // Line 6, Eq. 1: discount what the chosen target's sensor would cover.
            let max_range = input.robots[i].capabilities.sensor_range_m;
            let range_cells = max_range / resolution;
            let range_cells_sq = (range_cells * range_cells).ceil() as i64;
            for (u, &other) in utility.iter_mut().zip(frontier) {
                if chosen.distance_squared(other) <= range_cells_sq {
                    *u -= covered(grid, chosen, other, max_range);
                }
            }
        }
        targets
    }

    /// Line 5: the pair (robot without a target, frontier cell) with the
    /// highest U_t − β·V_t^i.
    fn best_pair(
        &self,
        input: &PlanningInput<'_>,
        frontier: &[Cell],
        values: &[Vec<Option<f64>>],
        utility: &[f64],
        targets: &[Option<Target>],
    ) -> Option<(f64, usize, usize)> {
        let mut best: Option<(f64, usize, usize)> = None;
        for (i, robot) in input.robots.iter().enumerate() {
            if targets[i].is_some() {
                continue;
            }
            let current = current_target(robot);
            for (t, v) in values[i].iter().enumerate() {
                let Some(v) = v else { continue };
                let keep = if Some(frontier[t]) == current { self.switch_margin } else { 0.0 };
                let score = utility[t] - self.beta * v + keep;
                // Strictly greater: ties go to the lower robot, then the lower cell.
                if best.is_none_or(|(b, _, _)| score > b) {
                    best = Some((score, i, t));
                }
            }
        }
        best
    }
}

impl Policy for Burgard {
    fn name(&self) -> &'static str {
        NAME
    }

    fn plan(&self, input: &PlanningInput<'_>, costs: &mut CostCache<'_>) -> Plan {
        let frontier = input.frontier_cells();
        let values = self.cost_values(input, costs, &frontier);
        Plan::of(self.assign(input, &frontier, &values))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::grid::testing::grid_from_picture;
    use crate::policy::Nearest;
    use crate::policy::testing::{plan_targets, plan_with_defaults, robot};
    use crate::workers::Workers;

    fn burgard() -> Burgard {
        Burgard { beta: 1.0, occ_max: 0.6, smoothing_sigma_m: 0.0, switch_margin: 0.0 }
    }

    #[test]
    fn coverage_probability_follows_eq_2() {
        assert_eq!(coverage_probability(0.0, 5.0), 1.0);
        assert!((coverage_probability(2.5, 5.0) - 0.5).abs() < 1e-12);
        assert_eq!(coverage_probability(5.0, 5.0), 0.0);
        assert_eq!(coverage_probability(7.0, 5.0), 0.0);
    }

    /// Burgard et al. 2005, Figs. 1–2: two robots whose cheapest frontier is
    /// the same cell. Uncoordinated, both go there; coordinated, the second
    /// one's utility there is discounted and it takes the other way.
    #[test]
    fn two_robots_with_the_same_nearest_target_split() {
        // A corridor 1 m per cell: unknown at both ends; both robots near the left end.
        let grid = grid_from_picture(&[
            "##############", //
            "?............?", //
            "##############", //
        ]);
        let robots = [robot(0, Cell::new(3, 1), 5.0), robot(1, Cell::new(4, 1), 5.0)];
        let uncoordinated = plan_targets(&Nearest::default(), &grid, &robots);
        assert_eq!(uncoordinated, vec![Some(Cell::new(1, 1)), Some(Cell::new(1, 1))]);
        let coordinated = plan_targets(&burgard(), &grid, &robots);
        assert_eq!(coordinated[0], Some(Cell::new(1, 1)), "{coordinated:?}");
        assert_eq!(coordinated[1], Some(Cell::new(12, 1)), "{coordinated:?}");
    }

    /// What only the discount does: two openings of one room, two metres
    /// apart and in view of each other, and a frontier far down a corridor.
    /// Closest frontier sends both robots to the nearer opening and greedy
    /// (and the optimal assignment) gives the second robot the other
    /// opening; Algorithm 1 discounts that opening by what a sensor at the
    /// first covers (Eq. 1) and sends the second robot down the corridor.
    #[test]
    fn a_frontier_the_first_robot_will_see_is_worth_less_to_the_second() {
        let grid = grid_from_picture(&[
            "##################?#?#", //
            "?.....................", //
            "###########...........", //
            "###########...........", //
            "######################", //
        ]);
        let robots = [robot(0, Cell::new(12, 1), 5.0), robot(1, Cell::new(11, 3), 5.0)];
        let (near, other, corridor) = (Some(Cell::new(18, 3)), Some(Cell::new(20, 3)), Some(Cell::new(1, 3)));
        assert_eq!(plan_targets(&burgard(), &grid, &robots), vec![near, corridor]);
        assert_eq!(plan_with_defaults("burgard", &grid, &robots), vec![near, corridor]);
        assert_eq!(plan_with_defaults("nearest", &grid, &robots), vec![near, near]);
        assert_eq!(plan_with_defaults("greedy", &grid, &robots), vec![near, other]);
        assert_eq!(plan_with_defaults("hungarian", &grid, &robots), vec![near, other]);
    }

    /// Eq. 1 with ray casting: a frontier cell behind a wall is not covered
    /// by a sensor at the chosen target, so its utility is not discounted,
    /// while the same cell in the open is.
    #[test]
    fn walls_keep_utilities_apart() {
        use crate::cost::CostCache;
        use crate::frontier::{FrontierMap, clusters};
        use crate::policy::PlanningInput;

        let second_robot_utility = |picture: &[&str]| {
            let grid = grid_from_picture(picture);
            let frontier = FrontierMap::detect(&grid);
            let clusters = clusters(&frontier, 1);
            let robots = [robot(0, Cell::new(1, 0), 3.0), robot(1, Cell::new(3, 0), 3.0)];
            let input = PlanningInput {
                grid: &grid,
                clusters: &clusters,
                robots: &robots,
                workers: Workers::unpaced(1),
                bids: &[Vec::new(), Vec::new()],
                seed: 0,
                reserved: &[],
                rooms: None,
            };
            let plan = burgard().plan(&input, &mut CostCache::new(&grid));
            let first = plan.targets[0].unwrap();
            let second = plan.targets[1].unwrap();
            assert_eq!(first.cell, Cell::new(1, 2));
            assert_eq!(second.cell, Cell::new(3, 2));
            second.utility + second.path_cost
        };
        // Frontier cells (1,2) and (3,2), two cells apart, with a wall between.
        let walled = second_robot_utility(&[
            "#?#?#", //
            "#.#.#", //
            "#.#.#", //
            "#...#", //
        ]);
        assert!((walled - 1.0).abs() < 1e-9, "behind a wall: undiscounted, got {walled}");
        let open = second_robot_utility(&[
            "#?#?#", //
            "#...#", //
            "#...#", //
            "#...#", //
        ]);
        // In the open, (3,2) is 2 m from (1,2): U = 1 − (1 − 2/3) = 2/3.
        assert!((open - 2.0 / 3.0).abs() < 1e-9, "in the open: discounted, got {open}");
    }

    proptest::proptest! {
        #![proptest_config(crate::testing::seeded_proptest(256))]
        /// Searching from each robot towards the frontier gives V_t^i and
        /// the plan of the complete cost maps: the same targets, utilities
        /// and costs, with robots holding current targets (hysteresis),
        /// cells excluded for them, targets reserved by robots out of
        /// reach, any β.
        #[test]
        fn searching_towards_the_frontier_plans_as_the_complete_search(
            width in 4u32..28,
            height in 4u32..28,
            seed in 0u64..1_000_000,
            robots in 1usize..6,
            beta_tenths in 0u32..40,
        ) {
            use crate::frontier::{FrontierMap, clusters};
            use crate::policy::PlanningInput;
            use crate::policy::testing::{random_known_rectangle, random_team};
            use crate::rng::SplitMix64;

            let mut rng = SplitMix64::new(seed);
            // Mostly free, with walls and cells too uncertain to cross, so
            // that the smoothed costs vary.
            let (grid, free) = random_known_rectangle(width, height, &mut rng, |rng| match rng.below(10) {
                0 => 95,
                1 => 70,
                _ => 5 + rng.below(40) as u8,
            });
            proptest::prop_assume!(!free.is_empty());
            let team = random_team(robots, &free, &free, true, &mut rng);
            let pick = |rng: &mut SplitMix64| free[rng.below(free.len() as u64) as usize];
            let reserved: Vec<(Cell, f64)> = (0..rng.below(3)).map(|_| (pick(&mut rng), 2.0)).collect();
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
                reserved: &reserved,
                rooms: None,
            };
            let policy = Burgard { beta: f64::from(beta_tenths) / 10.0, occ_max: 0.6, smoothing_sigma_m: 1.0, switch_margin: 0.3 };
            let lazily = policy.plan(&input, &mut CostCache::new(&grid));
            let frontier = input.frontier_cells();
            // The complete cost maps, not the searches towards the frontier.
            let kinds: Vec<TraversalKind> = team.iter().map(|r| policy.traversal_kind(r)).collect();
            let values: Vec<Vec<Option<f64>>> = crate::policy::robot_cost_maps(&input, &mut CostCache::new(&grid), &kinds)
                .iter()
                .zip(&team)
                .map(|(map, robot)| frontier.iter().map(|&t| robot.cost_to(map, t)).collect())
                .collect();
            proptest::prop_assert_eq!(&policy.cost_values(&input, &mut CostCache::new(&grid), &frontier), &values);
            let fully = Plan::of(policy.assign(&input, &frontier, &values));
            proptest::prop_assert_eq!(lazily, fully);
        }
    }
}
