//! `colares`: information, distance and coordination in one utility.
//!
//! Colares & Chaimowicz 2016, Eq. 1: each robot takes the frontier f of
//! highest
//!
//! U(f) = Inf(f) + Dist(f) − Coord(f).
//!
//! As in the paper's information map and Fig. 3c, f is evaluated cell by
//! cell: every frontier cell is a candidate, and its frontier is the part
//! of the frontier inside an n × n window around it.
//!
//! - Inf (§3.1, Eqs. 2–3): a cell's information potential is a
//!   non-normalized Gaussian of its P(occ) centred on 0.5 (unknown cells
//!   count as 0.5), summed with its eight neighbours'; Inf(f) sums that over
//!   the frontier cells in the window.
//! - Dist (§3.2, Eq. 4): w^(α−1) · (1 − w)^(β−1), w the robot's wavefront
//!   distance to the cell divided by the largest over the frontier cells.
//! - Coord (§3.3): a negative wavefront from each other robot's pose,
//!   highest at the robot and falling with distance, normalized to [0, 1];
//!   with several robots the strongest one counts.
//!
//! When a robot chooses again: the paper's robot "decides to explore" a
//! frontier and navigates to it; it evaluates the utility again when it
//! meets another robot (§3.3) or when there is nothing left there (§4,
//! Fig. 11). With `commit` (the default) a robot therefore keeps its
//! frontier cell while that cell is still frontier, and chooses again as
//! soon as it is explored, reached or unreachable; here every robot always
//! sees every other, so meetings add no decision points. With `commit` off
//! it chooses again at every replanning, which the paper does not do: Eq.
//! 4's factor peaks at a distance, so a robot approaching its choice finds
//! it less attractive and turns back (`commit = 0` can livelock). With
//! `commit = 2` a robot keeps its cell until it stands on it (or cannot
//! reach it), as a navigation goal is kept until reached: the other reading
//! of "navigates to it", since a sensor that reaches further than a cell
//! explores the chosen cell before the robot gets there. Where
//! utilities tie, the first frontier cell in row order wins (the paper is
//! silent on ties).
//!
//! The paper adds the three factors; Inf (a sum over cells) and Dist (a
//! product of powers below one) live on different scales, so both are
//! normalized to [0, 1] over the current frontiers before adding, as Coord
//! is. The paper's robots decide alone and meet to merge maps; here all
//! poses are known to the executive, so every robot sees every other.

#[cfg(test)]
use super::CurrentTask;
use super::registry::{MIN_FRONTIER_SIZE, ParamSpec, PolicyDescriptor, SWITCH_UTILITY};
use super::{Plan, PlanningInput, Policy, RobotView, Target, costs_to_cells, current_target};
use crate::cost::{CostCache, TraversalKind};
use crate::grid::{Cell, CellRect, NEIGHBOURS_8, OccupancyGrid, UNKNOWN};

pub(super) const NAME: &str = "colares";

/// The catalogue's entry: name, what it does, parameters with units, and
/// how it is built from a validated configuration.
pub(super) const DESCRIPTOR: PolicyDescriptor = PolicyDescriptor {
    name: NAME,
    description: "Colares & Chaimowicz 2016: U(f) = Inf(f) + Dist(f) - Coord(f), information potential, a beta-shaped distance factor and a negative wavefront from the other robots",
    params: &[
        MIN_FRONTIER_SIZE,
        SWITCH_UTILITY,
        ParamSpec {
            name: "alpha",
            description: "exponent alpha of the distance factor w^(alpha-1) (1-w)^(beta-1) (Eq. 4); the paper's best: 5 or 8",
            default: 5.0,
            min: 1.0,
            max: 50.0,
        },
        ParamSpec {
            name: "beta",
            description: "exponent beta of the distance factor (Eq. 4); the paper's best: 9 or 8",
            default: 9.0,
            min: 1.0,
            max: 50.0,
        },
        ParamSpec {
            name: "sigma",
            description: "width of the Gaussian of P(occ) centred on 0.5 that gives a cell's information potential (§3.1)",
            default: 0.15,
            min: 0.01,
            max: 10.0,
        },
        ParamSpec {
            name: "commit",
            description: "1, the paper's: a robot keeps the frontier cell it chose while that cell is still frontier; 2: until it stands on it (or cannot reach it); 0: it chooses again at every replanning (not in the paper; can livelock, as Eq. 4 peaks at a distance)",
            default: 1.0,
            min: 0.0,
            max: 2.0,
        },
        ParamSpec {
            name: "window",
            description: "side n of the n × n window whose frontier cells make a cell's frontier (§3.1), cells",
            default: 5.0,
            min: 1.0,
            max: 101.0,
        },
    ],
    build: |c| {
        Box::new(Colares {
            switch_margin: c.get("switch_margin"),
            alpha: c.get("alpha"),
            beta: c.get("beta"),
            sigma: c.get("sigma"),
            window: c.get("window").round() as usize,
            commit: Commit::from_param(c.get("commit")),
        })
    },
};

/// Colares & Chaimowicz 2016, Eq. 1.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Colares {
    /// α of the distance factor (Eq. 4).
    pub alpha: f64,
    /// β of the distance factor (Eq. 4).
    pub beta: f64,
    /// Width of the Gaussian of P(occ) (§3.1).
    pub sigma: f64,
    /// Side n of the window that makes a cell's frontier, cells (odd).
    pub window: usize,
    /// Hysteresis: a robot's current target scores this much more.
    pub switch_margin: f64,
    /// How long a robot keeps the frontier cell it chose.
    pub commit: Commit,
}

/// How long a robot keeps the frontier cell it chose (§3–4: the paper's
/// robots navigate to the frontier they chose).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Commit {
    /// Not at all: it chooses again at every replanning.
    Never,
    /// While the cell is still frontier.
    WhileFrontier,
    /// Until it stands on the cell, or cannot reach it.
    UntilReached,
}

impl Commit {
    /// From the `commit` parameter: 0, 1 or 2, rounded.
    fn from_param(value: f64) -> Self {
        match value.round() as i64 {
            i64::MIN..=0 => Self::Never,
            1 => Self::WhileFrontier,
            _ => Self::UntilReached,
        }
    }
}

/// Eq. 4: the distance factor w^(α−1) · (1 − w)^(β−1) of a normalized
/// distance w ∈ [0, 1]; peaks at w = (α − 1)/(α + β − 2).
pub fn distance_factor(w: f64, alpha: f64, beta: f64) -> f64 {
    let w = w.clamp(0.0, 1.0);
    w.powf(alpha - 1.0) * (1.0 - w).powf(beta - 1.0)
}

/// §3.1, Eq. 2: IP(c) = G(c) + Σ over the eight neighbours G(n), with
/// G(p) = exp(−(p − 0.5)² / (2σ²)) and unknown cells at p = 0.5. Cells
/// beyond the grid count as known walls (G of p = 1).
pub fn information_potential(grid: &OccupancyGrid, cell: Cell, sigma: f64) -> f64 {
    let frame = grid.frame();
    let g = |c: Cell| {
        let p = if !frame.contains(c) {
            1.0
        } else {
            match grid.value(c) {
                UNKNOWN => 0.5,
                v => f64::from(v) / 100.0,
            }
        };
        (-(p - 0.5) * (p - 0.5) / (2.0 * sigma * sigma)).exp()
    };
    g(cell) + NEIGHBOURS_8.iter().map(|&(dx, dy)| g(Cell::new(cell.x + dx, cell.y + dy))).sum::<f64>()
}

fn normalized(values: &[f64]) -> Vec<f64> {
    let max = values.iter().copied().filter(|v| v.is_finite()).fold(0.0f64, f64::max);
    values.iter().map(|v| if max > 0.0 { v / max } else { 0.0 }).collect()
}

impl Policy for Colares {
    fn name(&self) -> &'static str {
        NAME
    }

    fn plan(&self, input: &PlanningInput<'_>, costs: &mut CostCache<'_>) -> Plan {
        let frontier = input.frontier_cells();
        let frame = input.grid.frame();
        // Eqs. 2–3 over each cell's window, normalized over the frontier.
        let potential: Vec<f64> = frontier.iter().map(|&c| information_potential(input.grid, c, self.sigma)).collect();
        let mut in_window = vec![f64::NAN; frame.len()];
        for (c, p) in frontier.iter().zip(&potential) {
            in_window[frame.index(*c)] = *p;
        }
        let half = (self.window / 2) as i32;
        let inf: Vec<f64> = frontier
            .iter()
            .map(|c| {
                CellRect::new(c.x - half, c.y - half, 2 * half as u32 + 1, 2 * half as u32 + 1)
                    .cells()
                    .filter(|n| frame.contains(*n))
                    .map(|n| in_window[frame.index(n)])
                    .filter(|p| !p.is_nan())
                    .sum()
            })
            .collect();
        let inf = normalized(&inf);
        let distances = frontier_distances(input, costs, &frontier);
        let farthest: Vec<f64> =
            distances.iter().map(|row| row.iter().flatten().copied().fold(0.0f64, f64::max)).collect();
        // Negative wavefronts: 1 at each robot, falling to 0 at its farthest frontier cell.
        let pressure: Vec<Vec<f64>> = distances
            .iter()
            .zip(&farthest)
            .map(|(row, &far)| {
                row.iter()
                    .map(|d| match d {
                        Some(d) if far > 0.0 => 1.0 - d / far,
                        Some(_) => 1.0,
                        None => 0.0,
                    })
                    .collect()
            })
            .collect();
        let targets = (0..input.robots.len())
            .map(|i| {
                let robot = &input.robots[i];
                let still_frontier = |c: Cell| frame.contains(c) && !in_window[frame.index(c)].is_nan();
                let keeps = |target: Cell| match self.commit {
                    Commit::Never => false,
                    Commit::WhileFrontier => still_frontier(target),
                    Commit::UntilReached => true,
                };
                let committed = robot.current.filter(|c| c.target != robot.cell && keeps(c.target));
                if let Some((current, cost)) = committed.and_then(|c| {
                    // A target no longer frontier (kept until reached) is off
                    // the way the search towards the frontier went.
                    let cost = match frontier.iter().position(|&f| f == c.target) {
                        Some(t) => distances[i][t],
                        None => robot.cost_to(&costs.cost_map(robot.free_space(), robot.cell), c.target),
                    };
                    cost.map(|cost| (c, cost))
                }) {
                    return Some(Target { cell: current.target, utility: 0.0, path_cost: cost, gain_region: None });
                }
                let far = farthest[i];
                let dist: Vec<f64> = distances[i]
                    .iter()
                    .map(|d| {
                        d.map_or(0.0, |d| distance_factor(if far > 0.0 { d / far } else { 0.0 }, self.alpha, self.beta))
                    })
                    .collect();
                let dist = normalized(&dist);
                let current = current_target(&input.robots[i]);
                distances[i]
                    .iter()
                    .enumerate()
                    .filter_map(|(t, d)| d.map(|d| (t, d)))
                    .map(|(t, d)| {
                        let coord =
                            (0..input.robots.len()).filter(|&k| k != i).map(|k| pressure[k][t]).fold(0.0f64, f64::max);
                        let keep = if Some(frontier[t]) == current { self.switch_margin } else { 0.0 };
                        (inf[t] + dist[t] - coord + keep, t, d)
                    })
                    // Ties to the first cell: deterministic.
                    .max_by(|a, b| a.0.total_cmp(&b.0).then(b.1.cmp(&a.1)))
                    .map(|(utility, t, d)| Target { cell: frontier[t], utility, path_cost: d, gain_region: None })
            })
            .collect();
        Plan::of(targets)
    }
}

/// Each robot's wavefront distance to every frontier cell (`None` where it
/// cannot go or must not be sent), searched towards the frontier.
fn frontier_distances(
    input: &PlanningInput<'_>,
    costs: &mut CostCache<'_>,
    frontier: &[Cell],
) -> Vec<Vec<Option<f64>>> {
    let kinds: Vec<TraversalKind> = input.robots.iter().map(RobotView::free_space).collect();
    costs_to_cells(input, costs, &kinds, frontier)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::grid::testing::grid_from_picture;
    use crate::policy::testing::{plan_targets, plan_with_defaults, robot};
    use crate::workers::Workers;

    /// Colares & Chaimowicz 2016, Fig. 2: (α, β) = (4, 9) favours near
    /// frontiers, (9, 4) far ones; each curve rises to a single peak at
    /// (α − 1)/(α + β − 2) and falls to zero at both ends.
    #[test]
    fn the_distance_factor_has_the_shape_of_fig_2() {
        let peak = |a: f64, b: f64| {
            (0..=1000)
                .map(|k| k as f64 / 1000.0)
                .max_by(|x, y| distance_factor(*x, a, b).total_cmp(&distance_factor(*y, a, b)))
                .unwrap()
        };
        assert!((peak(4.0, 9.0) - 3.0 / 11.0).abs() < 1e-3);
        assert!((peak(9.0, 4.0) - 8.0 / 11.0).abs() < 1e-3);
        for (a, b) in [(4.0, 9.0), (9.0, 4.0)] {
            assert_eq!(distance_factor(0.0, a, b), 0.0);
            assert_eq!(distance_factor(1.0, a, b), 0.0);
            let p = peak(a, b);
            for k in 1..100 {
                let (x, y) = (k as f64 / 100.0, (k + 1) as f64 / 100.0);
                let (fx, fy) = (distance_factor(x, a, b), distance_factor(y, a, b));
                if y <= p {
                    assert!(fy > fx, "({a}, {b}) rises before its peak");
                } else if x >= p {
                    assert!(fy < fx, "({a}, {b}) falls after its peak");
                }
            }
        }
        // Mirror images: (4, 9) at w is (9, 4) at 1 − w.
        for k in 0..=20 {
            let w = k as f64 / 20.0;
            assert!((distance_factor(w, 4.0, 9.0) - distance_factor(1.0 - w, 9.0, 4.0)).abs() < 1e-15);
        }
    }

    #[test]
    fn unknown_cells_carry_the_most_potential() {
        let grid = grid_from_picture(&["???", "???", "???", "...", "###"]);
        let unknown = information_potential(&grid, Cell::new(1, 3), 0.15);
        let edge = information_potential(&grid, Cell::new(1, 2), 0.15);
        assert!((unknown - 9.0).abs() < 1e-9);
        assert!(edge < unknown);
    }

    #[test]
    fn alpha_and_beta_choose_between_near_and_far_frontier_cells() {
        // A long frontier along a wall of unknown space; the robot at one end.
        let grid = grid_from_picture(&[
            "??????????????????????", //
            "......................", //
            "######################", //
        ]);
        let robots = [robot(0, Cell::new(0, 1), 3.0)];
        let colares =
            |alpha, beta| Colares { alpha, beta, sigma: 0.15, window: 5, switch_margin: 0.0, commit: Commit::Never };
        let near = plan_targets(&colares(2.0, 9.0), &grid, &robots)[0].unwrap();
        let far = plan_targets(&colares(9.0, 2.0), &grid, &robots)[0].unwrap();
        // Peaks at w = 1/9 and 8/9 of the 21 cells.
        assert!((1..=4).contains(&near.x), "{near:?}");
        assert!((17..=20).contains(&far.x), "{far:?}");
    }

    fn heading_for(mut robot: RobotView, target: Cell) -> RobotView {
        robot.current = Some(CurrentTask { target, gain_region: None });
        robot
    }

    /// With its default settings ((α, β) = (5, 9), commitment as in §3–4) a
    /// robot takes a frontier cell a third of the way along, where Eq. 4
    /// peaks, not the closest one; it keeps the cell it chose while that is
    /// still frontier, and chooses again once it has been explored.
    #[test]
    fn with_its_defaults_a_robot_keeps_its_frontier_until_it_is_explored() {
        // Picture rows run from the top (y = 3) down; the frontier is y = 2.
        let grid = grid_from_picture(&[
            "??????????????????????", //
            "......................", //
            "......................", //
            "######################", //
        ]);
        let robots = [robot(0, Cell::new(0, 1), 3.0)];
        let chosen = plan_with_defaults("colares", &grid, &robots)[0].unwrap();
        assert!((5..=9).contains(&chosen.x) && chosen.y == 2, "{chosen:?}");
        let nearest = plan_with_defaults("nearest", &grid, &robots)[0].unwrap();
        assert!(nearest.x <= 1, "{nearest:?}");

        // Heading for (15, 2), still frontier: it keeps it.
        let heading = [heading_for(robots[0].clone(), Cell::new(15, 2))];
        assert_eq!(plan_with_defaults("colares", &grid, &heading), vec![Some(Cell::new(15, 2))]);
        // The unknown above (15, 2) has been seen: it chooses again.
        let seen = grid_from_picture(&[
            "?????????????.....????", //
            "......................", //
            "......................", //
            "######################", //
        ]);
        let again = plan_with_defaults("colares", &seen, &heading)[0].unwrap();
        assert!((5..=9).contains(&again.x), "{again:?}");

        // With commit = 2 it keeps (15, 2) although it has been seen, until it stands there.
        let overrides = std::collections::BTreeMap::from([("commit".to_owned(), 2.0)]);
        let policy = crate::policy::PolicyConfig::new("colares", &overrides).unwrap().build();
        let until_reached = |robots: &[RobotView]| plan_targets(policy.as_ref(), &seen, robots)[0];
        assert_eq!(until_reached(&heading), Some(Cell::new(15, 2)));
        let arrived = [heading_for(robot(0, Cell::new(15, 2), 3.0), Cell::new(15, 2))];
        assert_ne!(until_reached(&arrived), Some(Cell::new(15, 2)), "there, it chooses again");
    }

    /// §3.3's coordination term: another robot's negative wavefront makes
    /// cells near it less attractive. A robot in the middle of a long
    /// frontier has two equal peaks of Eq. 4, left and right, and takes the
    /// left one (ties to the first cell); with another robot standing there,
    /// it takes the right one. Closest frontier ignores the other robot.
    #[test]
    fn another_robot_pushes_the_choice_to_the_other_side() {
        let grid = grid_from_picture(&[
            "???????????????????????????????????????????", //
            "...........................................", //
            "...........................................", //
            "###########################################", //
        ]);
        let alone = [robot(0, Cell::new(21, 1), 3.0)];
        let chosen = plan_with_defaults("colares", &grid, &alone)[0].unwrap();
        assert!(chosen.x < 21, "{chosen:?}");
        let pair = [robot(0, Cell::new(21, 1), 3.0), robot(1, Cell::new(chosen.x, 1), 3.0)];
        let pushed = plan_with_defaults("colares", &grid, &pair)[0].unwrap();
        assert!(pushed.x > 21, "alone {chosen:?}, with a robot below it: {pushed:?}");
        let nearest = [plan_with_defaults("nearest", &grid, &alone)[0], plan_with_defaults("nearest", &grid, &pair)[0]];
        assert_eq!(nearest, [Some(Cell::new(21, 2)); 2]);
    }

    proptest::proptest! {
        #![proptest_config(crate::testing::seeded_proptest(256))]
        /// The searches towards the frontier give every robot the distance
        /// to every frontier cell that its complete wavefront gives, over
        /// random rooms, walls, footprints and excluded cells.
        #[test]
        fn searches_towards_the_frontier_measure_as_complete_wavefronts(
            width in 4u32..30,
            height in 4u32..30,
            seed in 0u64..1_000_000,
            robots in 1usize..6,
        ) {
            use crate::policy::free_space_cost_maps;
            use crate::policy::testing::{random_team, random_walled_rectangle, with_input};
            use crate::rng::SplitMix64;

            let mut rng = SplitMix64::new(seed);
            let (grid, free) = random_walled_rectangle(width, height, &mut rng);
            proptest::prop_assume!(!free.is_empty());
            let mut team = random_team(robots, &free, &free, true, &mut rng);
            for robot in team.iter_mut().filter(|_| rng.below(2) == 0) {
                robot.capabilities.footprint_radius_m = 0.6;
            }
            let (towards, complete) = with_input(&grid, &team, &vec![Vec::new(); robots], |input| {
                let input = PlanningInput { workers: Workers::unpaced(1 + (seed % 2) as usize), ..*input };
                let frontier = input.frontier_cells();
                let towards = frontier_distances(&input, &mut CostCache::new(&grid), &frontier);
                let complete: Vec<Vec<Option<f64>>> = free_space_cost_maps(&input, &mut CostCache::new(&grid))
                    .iter()
                    .zip(&team)
                    .map(|(m, r)| frontier.iter().map(|&c| r.cost_to(m, c)).collect())
                    .collect();
                (towards, complete)
            });
            proptest::prop_assert_eq!(towards, complete);
        }
    }
}
