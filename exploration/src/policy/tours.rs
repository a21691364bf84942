//! `tours`: ours. MinPos's spread, each robot visiting the frontiers it is
//! first at in the order of a short tour, and robots that are first nowhere
//! sent where nobody is heading.
//!
//! - **Who is first where** (Bautin, Simonin & Charpillet 2011, Algorithm 3,
//!   position 0; a partition of the frontier by path distance, as Hu et al.
//!   2020 partition the unknown by Voronoi cells): each frontier cluster
//!   belongs to the robot with the least path cost to it, ties to the robot
//!   listed first. A robot that owns clusters is first there, where MinPos
//!   would send it too.
//! - **Tours** (Kulich, Faigl & Přeučil 2011: a frontier's cost is its place
//!   in a tour, which avoids leaving small pockets behind): MinPos and the
//!   closest frontier take the nearest owned cluster and leave behind the
//!   ones that lie the other way, and a late trip back to them is what the
//!   tail of an exploration is made of (in `bautin-fig9-10`, 17–31 % of the
//!   time to full coverage passes after 90 %). A robot here goes to the
//!   first cluster of the shortest open path that starts at it and visits
//!   its `tour_length` nearest owned clusters, on path costs between
//!   clusters (one wavefront per cluster on the tour), solved exactly by
//!   Held–Karp dynamic programming.
//! - **Helpers**: a robot that owns nothing (larger teams, where robots
//!   outnumber the clusters they are first at) takes, cheapest pair first
//!   (Bautin's Algorithm 2), a cluster no robot is heading to, such as the
//!   later stops of another robot's tour; when every cluster has a robot, it
//!   takes MinPos's choice (the least position, then the least cost).
//! - **Places by the unknown behind** (`behind_m`; Solanas & García 2004
//!   and Hu et al. 2020 divide the unknown among the robots): a cluster
//!   takes up to the team's share of the unknown cells within `behind_m`
//!   of it (a breadth-first wave through unknown cells from each cluster,
//!   a cell counted for the wave that reaches it first), at least one. A
//!   wide opening onto a large unexplored area then takes several helpers
//!   and a pocket one; a robot sent where another already heads takes the
//!   cluster's cell nearest to it that is out of the other's sensor range
//!   (Burgard et al. 2005: robots that share a view gain less).
//! - **Hysteresis** (Simmons et al. 2000 keep a robot's task unless a clearly
//!   better one appears): the robot's current cluster costs it
//!   `switch_margin` less, in its ownership, its tour and its helper choice.
//!
//! The target in a cluster is its cell nearest to the robot, as in MinPos
//! (with `behind_m`, the nearest out of view of the robots already sent there).

use super::registry::{MIN_FRONTIER_SIZE, ParamSpec, PolicyDescriptor, SWITCH_METRES};
use super::{ClusterCosts, Plan, PlanningInput, Policy, RobotView, Target, cluster_cost_matrix};
use crate::cost::{CostCache, CostMap, TraversalKind};
use crate::frontier::FrontierCluster;
use crate::grid::{Cell, NEIGHBOURS_8, OccupancyGrid, UNKNOWN};
use std::collections::VecDeque;

pub(super) const NAME: &str = "tours";

/// The most clusters one tour visits: Held–Karp takes O(2^m·m²).
pub const MAX_TOUR: usize = 8;

const POCKET_CELLS: ParamSpec = ParamSpec {
    name: "pocket_cells",
    description: "beyond its nearest, a tour visits only owned frontier clusters of at most this many cells (pockets); 0 visits any",
    default: 0.0,
    min: 0.0,
    max: 10_000.0,
};

const BEHIND_M: ParamSpec = ParamSpec {
    name: "behind_m",
    description: "helpers: a frontier cluster may take robots in proportion to the unknown area within this many metres behind it; 0 sends helpers only where nobody is heading",
    default: 0.0,
    min: 0.0,
    max: 100.0,
};

const TOUR_LENGTH: ParamSpec = ParamSpec {
    name: "tour_length",
    description: "how many of its nearest owned frontier clusters a robot's tour visits; 1 is MinPos with helpers",
    default: 5.0,
    min: 1.0,
    max: MAX_TOUR as f64,
};

/// The catalogue's entry: name, what it does, parameters with units, and
/// how it is built from a validated configuration.
pub(super) const DESCRIPTOR: PolicyDescriptor = PolicyDescriptor {
    name: NAME,
    description: "ours: each robot is sent along the shortest tour through the frontiers it is closest to (Bautin et al. 2011, Kulich et al. 2011); robots closest nowhere take the frontiers nobody is heading to",
    params: &[MIN_FRONTIER_SIZE, SWITCH_METRES, TOUR_LENGTH, POCKET_CELLS, BEHIND_M],
    build: |c| {
        Box::new(Tours {
            switch_margin: c.get("switch_margin"),
            tour_length: c.get("tour_length").round() as usize,
            pocket_cells: c.get("pocket_cells").round() as usize,
            behind_m: c.get("behind_m"),
        })
    },
};

/// Our policy. Complexity: MinPos's cost matrix, one wavefront per cluster
/// on a tour of two or more (at most [`wavefront_budget`]), and O(2^m·m²)
/// per robot for its tour of m.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Tours {
    /// Hysteresis: a robot's current cluster costs it this much less, metres.
    pub switch_margin: f64,
    /// Clusters per tour, 1 to [`MAX_TOUR`].
    pub tour_length: usize,
    /// Past the nearest, a tour's stops are the owned clusters of at most
    /// this many cells; 0 for any cluster.
    pub pocket_cells: usize,
    /// Metres of unknown counted behind a cluster for its share of the
    /// helpers; 0 for one robot per cluster.
    pub behind_m: f64,
}

impl Default for Tours {
    fn default() -> Self {
        Self {
            switch_margin: SWITCH_METRES.default,
            tour_length: TOUR_LENGTH.default as usize,
            pocket_cells: POCKET_CELLS.default as usize,
            behind_m: BEHIND_M.default,
        }
    }
}

impl Policy for Tours {
    fn name(&self) -> &'static str {
        NAME
    }

    fn plan(&self, input: &PlanningInput<'_>, costs: &mut CostCache<'_>) -> Plan {
        // The legs between a tour's stops read the clusters' wavefronts at
        // other clusters' cells.
        let matrix = cluster_cost_matrix(input, costs, self.switch_margin, &input.frontier_cells());
        let tours = self.tours(&matrix, input.clusters);
        let legs = legs_between_stops(input, costs, &matrix, &tours);
        let mut chosen: Vec<Option<usize>> = tours
            .iter()
            .zip(&legs)
            .enumerate()
            .map(|(i, (stops, legs))| match stops.len() {
                0 => None,
                1 => Some(stops[0]),
                _ => {
                    let start: Vec<f64> = stops.iter().map(|&j| score(&matrix, i, j)).collect();
                    first_stop_of_shortest_tour(&start, legs).map(|k| stops[k])
                }
            })
            .collect();
        let places = self.places_per_cluster(input);
        send_helpers(&matrix, &places, &mut chosen);
        let mut taken: Vec<Vec<Cell>> = vec![Vec::new(); input.clusters.len()];
        let targets = chosen
            .iter()
            .enumerate()
            .map(|(i, j)| {
                let j = (*j)?;
                let c = matrix[i][j]?;
                let mut cell = matrix.cell(i, j)?;
                if places[j] > 1 {
                    let apart = input.grid.frame().cells_from_metres(input.robots[i].capabilities.sensor_range_m);
                    cell = out_of_view(&input.robots[i], &input.clusters[j], cell, &taken[j], apart);
                }
                taken[j].push(cell);
                // The path cost stays that of the cluster's nearest cell: a
                // cell moved along the frontier has no search of its own.
                Some(Target { cell, utility: -c.score, path_cost: c.cost, gain_region: None })
            })
            .collect();
        Plan::of(targets)
    }
}

impl Tours {
    /// Per robot, the clusters it is first at (by score, ties to the robot
    /// listed first), its `tour_length` nearest of them, nearest first;
    /// past the nearest, only pockets when `pocket_cells` is set.
    fn tours(&self, matrix: &ClusterCosts, frontier: &[FrontierCluster]) -> Vec<Vec<usize>> {
        let robots = matrix.len();
        let clusters = matrix.first().map_or(0, Vec::len);
        let mut owned: Vec<Vec<usize>> = vec![Vec::new(); robots];
        for j in 0..clusters {
            let owner = (0..robots)
                .filter(|&i| matrix[i][j].is_some())
                .min_by(|&a, &b| score(matrix, a, j).total_cmp(&score(matrix, b, j)).then(a.cmp(&b)));
            if let Some(i) = owner {
                owned[i].push(j);
            }
        }
        for (i, stops) in owned.iter_mut().enumerate() {
            stops.sort_by(|&a, &b| score(matrix, i, a).total_cmp(&score(matrix, i, b)).then(a.cmp(&b)));
            if self.pocket_cells > 0
                && let Some(&nearest) = stops.first()
            {
                stops.retain(|&j| j == nearest || frontier[j].len() <= self.pocket_cells);
            }
        }
        // Each cluster on a tour of two or more costs a wavefront: shorten
        // every tour alike until they fit the budget.
        let budget = wavefront_budget(robots);
        let mut length = self.tour_length.clamp(1, MAX_TOUR);
        while length > 1 && owned.iter().filter(|s| s.len() > 1).map(|s| s.len().min(length)).sum::<usize>() > budget {
            length -= 1;
        }
        for stops in &mut owned {
            stops.truncate(length);
        }
        owned
    }
}

/// The most cluster wavefronts one replanning computes for tours: twice
/// the team, and at least 32, so that a map of a thousand small frontier
/// clusters costs a bounded multiple of MinPos's one wavefront per robot.
fn wavefront_budget(robots: usize) -> usize {
    (2 * robots).max(32)
}

/// Robot `i`'s score for cluster `j` (its path cost, less the hysteresis
/// margin on its current cluster); ∞ where it cannot reach it.
fn score(matrix: &ClusterCosts, i: usize, j: usize) -> f64 {
    matrix[i][j].map_or(f64::INFINITY, |c| c.score)
}

/// Per robot, the path costs between the stops of its tour (row a, column
/// b: from stop a to stop b's cheapest cell), from one wavefront per stop
/// (the matrix's own where it has them) over the robot's traversal. Each
/// wavefront is read and dropped at once, so that memory stays at one map
/// per thread. Tours of one stop need none.
fn legs_between_stops(
    input: &PlanningInput<'_>,
    costs: &mut CostCache<'_>,
    matrix: &ClusterCosts,
    tours: &[Vec<usize>],
) -> Vec<Vec<Vec<f64>>> {
    let reused = matrix.cluster_maps();
    let mut jobs = Vec::new();
    for (i, stops) in tours.iter().enumerate().filter(|(_, stops)| stops.len() > 1) {
        let kind = TraversalKind::free_space(input.robots[i].capabilities.footprint_radius_m);
        for (a, &j) in stops.iter().enumerate() {
            let source = match reused {
                Some(maps) => Wavefront::Reused(maps[j].clone()),
                None => Wavefront::Compute(costs.traversal(kind)),
            };
            jobs.push((i, a, source));
        }
    }
    let rows = crate::workers::in_parallel(&jobs, input.workers, |(i, a, source)| {
        let stops = &tours[*i];
        let map = match source {
            Wavefront::Reused(map) => map.clone(),
            Wavefront::Compute(traversal) => {
                std::sync::Arc::new(crate::cost::cost_map(traversal, &input.clusters[stops[*a]].cells))
            }
        };
        stops
            .iter()
            .enumerate()
            .map(|(b, &j)| {
                if b == *a {
                    return 0.0;
                }
                input.clusters[j].cells.iter().filter_map(|&c| map.cost(c)).fold(f64::INFINITY, f64::min)
            })
            .collect::<Vec<f64>>()
    });
    let mut legs: Vec<Vec<Vec<f64>>> = vec![Vec::new(); tours.len()];
    for ((i, _, _), row) in jobs.iter().zip(rows) {
        legs[*i].push(row);
    }
    legs
}

/// Where a stop's wavefront comes from.
enum Wavefront {
    /// The cost matrix's own.
    Reused(std::sync::Arc<CostMap>),
    /// Computed over this traversal.
    Compute(std::sync::Arc<crate::cost::TraversalMap>),
}

impl Tours {
    /// How many robots each cluster may take before helpers look elsewhere:
    /// one, or with `behind_m` set, the team's share of the unknown behind
    /// it (a wide opening onto a large unexplored area takes several robots,
    /// a pocket one; Solanas & García 2004 and Hu et al. 2020 divide the
    /// unknown among robots in this spirit).
    fn places_per_cluster(&self, input: &PlanningInput<'_>) -> Vec<usize> {
        let clusters = input.clusters.len();
        let radius = input.grid.frame().cells_from_metres(self.behind_m).round();
        if radius < 1.0 {
            return vec![1; clusters];
        }
        let behind = unknown_behind(input.grid, input.clusters, radius as u32);
        let total: usize = behind.iter().sum();
        if total == 0 {
            return vec![1; clusters];
        }
        let team = input.robots.len() as f64;
        behind.iter().map(|&area| ((team * area as f64 / total as f64).round() as usize).max(1)).collect()
    }
}

/// The cluster's cell nearest to `preferred` that lies at least `apart`
/// cells from every target already taken in it (Burgard et al. 2005: robots
/// that share a view gain less), or `preferred` when there is none.
fn out_of_view(robot: &RobotView, cluster: &FrontierCluster, preferred: Cell, taken: &[Cell], apart: f64) -> Cell {
    let clear = |c: Cell| taken.iter().all(|&t| c.distance(t) >= apart);
    if clear(preferred) {
        return preferred;
    }
    cluster
        .cells
        .iter()
        .copied()
        .filter(|&c| clear(c) && robot.may_target(c))
        .min_by(|a, b| a.distance(preferred).total_cmp(&b.distance(preferred)).then(a.cmp(b)))
        .unwrap_or(preferred)
}

/// Per cluster, the unknown cells within `radius` steps of it (4-connected,
/// through unknown cells only), each counted for the cluster whose
/// breadth-first wave reaches it first (ties to the cluster listed first).
fn unknown_behind(grid: &OccupancyGrid, clusters: &[FrontierCluster], radius: u32) -> Vec<usize> {
    let frame = grid.frame();
    let mut claimed = vec![false; frame.len()];
    let mut behind = vec![0usize; clusters.len()];
    // The frontier cells themselves (free) start the waves at depth 0,
    // cluster by cluster, so that ties go to the cluster listed first.
    let mut wave: VecDeque<(Cell, usize, u32)> =
        clusters.iter().enumerate().flat_map(|(j, c)| c.cells.iter().map(move |&cell| (cell, j, 0))).collect();
    while let Some((cell, j, depth)) = wave.pop_front() {
        if depth == radius {
            continue;
        }
        // The first four of the eight neighbours are the 4-connected ones.
        for &(dx, dy) in &NEIGHBOURS_8[..4] {
            let next = Cell::new(cell.x + dx, cell.y + dy);
            if !frame.contains(next) || grid.value(next) != UNKNOWN || claimed[frame.index(next)] {
                continue;
            }
            claimed[frame.index(next)] = true;
            behind[j] += 1;
            wave.push_back((next, j, depth + 1));
        }
    }
    behind
}

/// Robots that own no cluster: cheapest pair first onto the clusters with
/// a place left (`places[j]` robots heading to cluster j, one unless
/// `behind_m` is set; Bautin et al. 2011, Algorithm 2); the rest take
/// MinPos's choice, the least position and then the least score (Algorithm 3).
fn send_helpers(matrix: &ClusterCosts, places: &[usize], chosen: &mut [Option<usize>]) {
    let n = chosen.len();
    let m = matrix.first().map_or(0, Vec::len);
    let mut left = places.to_vec();
    for &j in chosen.iter().flatten() {
        left[j] = left[j].saturating_sub(1);
    }
    let helpers: Vec<usize> = (0..n).filter(|&i| chosen[i].is_none()).collect();
    loop {
        let open = &left;
        let best = helpers
            .iter()
            .filter(|&&i| chosen[i].is_none())
            .flat_map(|&i| (0..m).filter(move |&j| open[j] > 0 && matrix[i][j].is_some()).map(move |j| (i, j)))
            .min_by(|&(a, j), &(b, k)| score(matrix, a, j).total_cmp(&score(matrix, b, k)).then((a, j).cmp(&(b, k))));
        let Some((i, j)) = best else { break };
        chosen[i] = Some(j);
        left[j] -= 1;
    }
    for &i in &helpers {
        if chosen[i].is_some() {
            continue;
        }
        let position =
            |j: usize| (0..n).filter(|&k| k != i && matrix[k][j].is_some_and(|o| o.cost < score(matrix, i, j))).count();
        chosen[i] = (0..m).filter(|&j| matrix[i][j].is_some()).min_by(|&a, &b| {
            position(a).cmp(&position(b)).then(score(matrix, i, a).total_cmp(&score(matrix, i, b))).then(a.cmp(&b))
        });
    }
}

/// The first stop of the cheapest open path that starts at the robot and
/// visits every stop once: `start[j]` is the cost from the robot to stop j,
/// `between[a][b]` from stop a to stop b (∞ where there is no way). Exact,
/// by Held–Karp dynamic programming over the stops still to visit, O(2^m·m²);
/// `None` for no stops or more than [`MAX_TOUR`]. Ties go to the lower stop.
/// When no path visits every stop, the cheapest stop to reach.
pub fn first_stop_of_shortest_tour(start: &[f64], between: &[Vec<f64>]) -> Option<usize> {
    let m = start.len();
    if m == 0 || m > MAX_TOUR {
        return None;
    }
    // to_go[visited][last]: the cheapest way on from `last` through the stops not in `visited`.
    let full = (1usize << m) - 1;
    let mut to_go = vec![vec![f64::INFINITY; m]; full + 1];
    to_go[full] = vec![0.0; m];
    for visited in (1..full).rev() {
        for last in (0..m).filter(|&l| visited & (1 << l) != 0) {
            to_go[visited][last] = (0..m)
                .filter(|&next| visited & (1 << next) == 0)
                .map(|next| between[last][next] + to_go[visited | (1 << next)][next])
                .fold(f64::INFINITY, f64::min);
        }
    }
    let tour = |j: usize| start[j] + to_go[1 << j][j];
    let cheapest = |f: &dyn Fn(usize) -> f64| {
        (0..m).filter(|&j| f(j).is_finite()).min_by(|&a, &b| f(a).total_cmp(&f(b)).then(a.cmp(&b)))
    };
    cheapest(&tour).or_else(|| cheapest(&|j| start[j]))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::grid::Cell;
    use crate::grid::testing::grid_from_picture;
    use crate::policy::testing::{plan_targets, plan_with_defaults, robot, with_input};
    use crate::policy::{CurrentTask, MinPos, Nearest};

    /// A corridor open at both ends, with a side opening up from it at x =
    /// 18. The robot at x = 10 is 8 from the side opening, 10 from the left
    /// end and 30 from the right. The nearest frontier is the side opening,
    /// after which the left end is a long way back; the shortest tour takes
    /// the left end first (10 + 18 + 22 = 50, against 8 + 18 + 40 = 66).
    #[test]
    fn a_pocket_behind_the_robot_is_visited_before_moving_on() {
        let grid = grid_from_picture(&[
            "##################?######################", //
            "?.......................................?", //
            "#########################################", //
        ]);
        let robots = [robot(0, Cell::new(10, 1), 1.0)];
        let tours = plan_with_defaults("tours", &grid, &robots);
        assert_eq!(tours[0].map(|c| c.x), Some(1), "tours goes to the pocket first: {tours:?}");
        for other in ["nearest", "minpos", "greedy"] {
            let targets = plan_with_defaults(other, &grid, &robots);
            assert_eq!(targets[0], Some(Cell::new(18, 1)), "{other} takes the nearest: {targets:?}");
        }
    }

    /// The corridor of the test above, three cells wider (the robot in its
    /// top row, y = 4), so that its left end is a wide opening (a way on
    /// into unexplored space, not a pocket) while the side opening and the
    /// right end stay small. With pockets only, the left end is not on the
    /// tour: the robot takes the side opening and then the right end,
    /// instead of going back first.
    #[test]
    fn a_tour_through_pockets_only_leaves_a_wide_opening_for_later() {
        let grid = grid_from_picture(&[
            "##################?######################", //
            "?.......................................?", //
            "?.......................................#", //
            "?.......................................#", //
            "?.......................................#", //
            "#########################################", //
        ]);
        let robots = [robot(0, Cell::new(10, 4), 1.0)];
        let sizes = with_input(&grid, &robots, &[Vec::new()], |input| {
            let mut sizes: Vec<(i32, usize)> = input.clusters.iter().map(|c| (c.representative.x, c.len())).collect();
            sizes.sort_unstable();
            sizes
        });
        assert!(
            matches!(sizes.as_slice(), [(1, 4..), (18, 1..=3), (39, 1..=3)]),
            "left end wide, others small: {sizes:?}"
        );
        let any = plan_targets(&Tours::default(), &grid, &robots);
        assert_eq!(any[0].map(|c| c.x), Some(1), "any cluster on the tour: back to the left end first: {any:?}");
        let pockets = plan_targets(&Tours { pocket_cells: 3, ..Tours::default() }, &grid, &robots);
        assert!(pockets[0].is_some_and(|c| (17..=19).contains(&c.x)), "pockets only: the side opening: {pockets:?}");
    }

    /// Robot 0 in a corridor is closest to both ends; robot 1 at the bottom
    /// of a branch below it is closest to neither. MinPos sends robot 1
    /// where it is second and nearest, behind robot 0; ours sends it to the
    /// end robot 0 is not heading to.
    #[test]
    fn a_robot_first_nowhere_takes_the_cluster_nobody_is_heading_to() {
        let grid = grid_from_picture(&[
            "######################", //
            "?....................?", //
            "#########.############", //
            "#########.############", //
            "#########.############", //
            "######################", //
        ]);
        let robots = [robot(0, Cell::new(9, 4), 1.0), robot(1, Cell::new(9, 1), 1.0)];
        let ours = plan_with_defaults("tours", &grid, &robots);
        assert_eq!(ours.iter().map(|t| t.map(|c| c.x)).collect::<Vec<_>>(), [Some(1), Some(20)], "{ours:?}");
        let minpos = plan_targets(&MinPos::default(), &grid, &robots);
        assert_eq!(minpos.iter().map(|t| t.map(|c| c.x)).collect::<Vec<_>>(), [Some(1), Some(1)], "{minpos:?}");
        let nearest = plan_targets(&Nearest::default(), &grid, &robots);
        assert!(nearest.iter().all(|t| t.is_some_and(|c| c.x == 1)), "{nearest:?}");
    }

    /// The pocket situation, with the robot already heading to the side
    /// opening: a tour through the pocket first is shorter by 16, so a
    /// margin of 20 keeps it on its way, and a margin of 1 does not.
    #[test]
    fn the_current_target_is_kept_unless_a_tour_is_better_by_the_margin() {
        let grid = grid_from_picture(&[
            "##################?######################", //
            "?.......................................?", //
            "#########################################", //
        ]);
        let mut heading = robot(0, Cell::new(10, 1), 1.0);
        heading.current = Some(CurrentTask { target: Cell::new(18, 1), gain_region: None });
        let kept = plan_targets(&Tours { switch_margin: 20.0, ..Tours::default() }, &grid, &[heading.clone()]);
        assert_eq!(kept[0], Some(Cell::new(18, 1)), "{kept:?}");
        let switched = plan_targets(&Tours { switch_margin: 1.0, ..Tours::default() }, &grid, &[heading]);
        assert_eq!(switched[0].map(|c| c.x), Some(1), "{switched:?}");
    }

    /// A room with a one-cell pocket in its floor (x = 5) and its right side
    /// (x = 25) open onto a large unexplored area. Robot 0 is first at the
    /// pocket, robot 1 at the opening; robot 2, first nowhere, is nearer
    /// the pocket. One robot per cluster (and MinPos) sends it after robot
    /// 0 into the pocket; counting the unknown behind each cluster sends it
    /// to the opening, to a cell out of robot 1's sensor range from its
    /// target.
    #[test]
    fn a_helper_goes_where_the_most_unknown_lies_behind_the_frontier() {
        let grid = grid_from_picture(&[
            "##########################??????????", //
            "#.........................??????????", //
            "#.........................??????????", //
            "#.........................??????????", //
            "#.........................??????????", //
            "#.........................??????????", //
            "#####?####################??????????", //
        ]);
        let robots = [robot(0, Cell::new(5, 3), 2.0), robot(1, Cell::new(22, 3), 2.0), robot(2, Cell::new(12, 3), 2.0)];
        let in_pocket = |c: Option<Cell>| c.is_some_and(|c| c.y == 1 && (4..=6).contains(&c.x));
        for one_each in [plan_with_defaults("tours", &grid, &robots), plan_targets(&MinPos::default(), &grid, &robots)]
        {
            assert!(in_pocket(one_each[0]) && in_pocket(one_each[2]), "both into the pocket: {one_each:?}");
        }
        let behind = plan_targets(&Tours { behind_m: 10.0, ..Tours::default() }, &grid, &robots);
        assert!(in_pocket(behind[0]), "{behind:?}");
        let (Some(first), Some(helper)) = (behind[1], behind[2]) else { panic!("{behind:?}") };
        assert_eq!((first.x, helper.x), (25, 25), "both at the opening: {behind:?}");
        assert!(first.distance(helper) >= 2.0, "out of each other's view: {behind:?}");
    }

    /// A corridor with one unknown cell beyond its left end and five beyond
    /// its right: each cluster counts the unknown its wave reaches within
    /// the radius.
    #[test]
    fn the_unknown_behind_a_cluster_is_counted_within_the_radius() {
        let grid = grid_from_picture(&[
            "##########", //
            "?....?????", //
            "##########", //
        ]);
        with_input(&grid, &[], &[], |input| {
            let by_x = |behind: Vec<usize>| -> Vec<(i32, usize)> {
                let mut pairs: Vec<(i32, usize)> =
                    input.clusters.iter().map(|c| c.representative.x).zip(behind).collect();
                pairs.sort_unstable();
                pairs
            };
            assert_eq!(by_x(unknown_behind(input.grid, input.clusters, 3)), [(1, 1), (4, 3)]);
            assert_eq!(by_x(unknown_behind(input.grid, input.clusters, 10)), [(1, 1), (4, 5)]);
        });
    }

    /// Robot i is 1 m from clusters 4i..4i+4 and 50 m from the others.
    fn four_clusters_each(robots: usize) -> ClusterCosts {
        let cost = |i: usize, j: usize| if j / 4 == i { 1.0 } else { 50.0 };
        let rows = (0..robots)
            .map(|i| {
                (0..4 * robots)
                    .map(|j| {
                        Some(super::super::ClusterCost {
                            cell: Cell::new(j as i32, 0),
                            cost: cost(i, j),
                            score: cost(i, j),
                            descend: false,
                        })
                    })
                    .collect()
            })
            .collect();
        ClusterCosts { rows, descent: None }
    }

    #[test]
    fn tours_are_shortened_alike_to_fit_the_wavefront_budget() {
        let policy = Tours { switch_margin: 1.0, ..Tours::default() };
        // 4 robots own 4 clusters each: 16 wavefronts, within 32.
        assert!(policy.tours(&four_clusters_each(4), &[]).iter().all(|t| t.len() == 4));
        // 10 robots: 40 would exceed it; 3 stops each make 30.
        let tours = policy.tours(&four_clusters_each(10), &[]);
        assert!(tours.iter().enumerate().all(|(i, t)| t.len() == 3 && t.iter().all(|j| j / 4 == i)), "{tours:?}");
    }

    /// The cost of the cheapest tour from the robot through every stop,
    /// by trying every order.
    fn brute_force(start: &[f64], between: &[Vec<f64>], first: Option<usize>) -> f64 {
        fn walk(at: usize, left: &mut Vec<usize>, between: &[Vec<f64>]) -> f64 {
            if left.is_empty() {
                return 0.0;
            }
            let mut best = f64::INFINITY;
            for k in 0..left.len() {
                let next = left.remove(k);
                best = best.min(between[at][next] + walk(next, left, between));
                left.insert(k, next);
            }
            best
        }
        (0..start.len())
            .filter(|&j| first.is_none_or(|f| f == j))
            .map(|j| {
                let mut left: Vec<usize> = (0..start.len()).filter(|&k| k != j).collect();
                start[j] + walk(j, &mut left, between)
            })
            .fold(f64::INFINITY, f64::min)
    }

    proptest::proptest! {
        /// The first stop Held–Karp returns begins a tour as cheap as the
        /// cheapest of all orders.
        #[test]
        fn the_first_stop_begins_a_cheapest_tour(
            m in 1usize..=6,
            values in proptest::collection::vec(0.0f64..100.0, 6 + 36),
        ) {
            let start: Vec<f64> = values[..m].to_vec();
            let between: Vec<Vec<f64>> = (0..m).map(|a| (0..m).map(|b| if a == b { 0.0 } else { values[6 + a * 6 + b] }).collect()).collect();
            let first = first_stop_of_shortest_tour(&start, &between).unwrap();
            let best = brute_force(&start, &between, None);
            let ours = brute_force(&start, &between, Some(first));
            proptest::prop_assert!((ours - best).abs() <= 1e-9 * best.max(1.0), "{ours} vs {best}");
        }
    }

    #[test]
    fn tours_with_no_way_through_fall_back_to_the_cheapest_stop() {
        let inf = f64::INFINITY;
        assert_eq!(first_stop_of_shortest_tour(&[], &[]), None);
        assert_eq!(first_stop_of_shortest_tour(&[5.0, 3.0], &[vec![0.0, inf], vec![inf, 0.0]]), Some(1));
        assert_eq!(first_stop_of_shortest_tour(&[inf, inf], &[vec![0.0, 1.0], vec![1.0, 0.0]]), None);
        assert_eq!(first_stop_of_shortest_tour(&[1.0; 9], &vec![vec![1.0; 9]; 9]), None, "more than MAX_TOUR");
    }
}
