//! Coordination policies: who goes where next.
//!
//! A policy looks at the fused grid, its frontier clusters and the robots,
//! and returns at most one target per robot. Every policy implements
//! [`Policy`]; [`PolicyConfig`] validates a policy name and parameters
//! against the [`catalogue`] and builds it. Each policy lives in its own file
//! and cites the paper, algorithm and equations it implements.

use std::collections::BTreeMap;

use crate::cost::CostCache;
use crate::frontier::FrontierCluster;
use crate::grid::{Cell, CellRect, OccupancyGrid};
use crate::workers::Workers;

mod burgard;
mod burgard_joint;
mod colares;
mod greedy;
mod hungarian;
mod minpos;
mod nearest;
mod registry;
mod segmentation;
mod simmons;
mod tours;
mod unassigned;

pub use burgard::{Burgard, coverage_probability};
pub use burgard_joint::BurgardJoint;
pub use colares::{Colares, Commit, distance_factor, information_potential};
pub use greedy::Greedy;
pub use hungarian::Hungarian;
pub use minpos::MinPos;
pub use nearest::Nearest;
pub use registry::{ParamSpec, PolicyConfig, PolicyDescriptor, PolicyError, catalogue};
pub use segmentation::SegmentationPolicy;
pub use simmons::{Simmons, compute_bids};
pub use tours::{MAX_TOUR, Tours, first_stop_of_shortest_tour};
pub use unassigned::Unassigned;

/// A robot's identity, as the executive numbers them.
pub type RobotId = u64;

/// What a robot can do (Simmons et al. 2000 let bids reflect "their own
/// capabilities (sensor range, travel costs, etc.)"; Wurm et al. 2008, Eq. 4,
/// give infinite cost where a robot cannot pass).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Capabilities {
    /// Maximum sensor range, metres (Burgard et al. 2005's max_range of Eq. 2).
    pub sensor_range_m: f64,
    /// Sensor field of view, radians.
    pub field_of_view_rad: f64,
    /// Nominal speed, metres per second.
    pub speed_mps: f64,
    /// Radius of the circular footprint, metres.
    pub footprint_radius_m: f64,
}

/// The task a robot is working on when the policy runs.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CurrentTask {
    /// Its target cell.
    pub target: Cell,
    /// The information-gain region of that target, if known (Simmons et al. 2000, §4.2).
    pub gain_region: Option<CellRect>,
}

/// A robot as the policies see it.
#[derive(Debug, Clone, PartialEq)]
pub struct RobotView {
    /// Its identity.
    pub id: RobotId,
    /// The cell it stands on.
    pub cell: Cell,
    /// Its capabilities.
    pub capabilities: Capabilities,
    /// What it is doing, if anything.
    pub current: Option<CurrentTask>,
    /// Cells it must not be sent to: around targets blacklisted for it
    /// (reported unreachable, or stalled on). They cost it ∞, as cells it
    /// cannot reach do in Wurm et al. 2008, Eq. 4.
    pub excluded: Vec<CellRect>,
}

impl RobotView {
    /// Whether the robot may be sent to `cell`: not excluded for it (an
    /// excluded cell costs it ∞, Wurm et al. 2008, Eq. 4).
    pub fn may_target(&self, cell: Cell) -> bool {
        !self.excluded.iter().any(|r| r.contains(cell))
    }

    /// The robot's path cost to `cell` on `map`, its own cost map: `None`
    /// where it cannot go or must not be sent (Wurm et al. 2008, Eq. 4:
    /// infinite cost).
    pub fn cost_to(&self, map: &crate::cost::CostMap, cell: Cell) -> Option<f64> {
        if self.may_target(cell) { map.cost(cell) } else { None }
    }

    /// The free space the robot moves in: known free cells, obstacles
    /// inflated by its footprint.
    pub fn free_space(&self) -> crate::cost::TraversalKind {
        crate::cost::TraversalKind::free_space(self.capabilities.footprint_radius_m)
    }
}

/// Everything a policy may look at for one replanning.
#[derive(Debug, Clone, Copy)]
pub struct PlanningInput<'a> {
    /// The fused grid.
    pub grid: &'a OccupancyGrid,
    /// Frontier clusters of at least the policy's minimum size.
    pub clusters: &'a [FrontierCluster],
    /// The robots to assign, in a fixed order.
    pub robots: &'a [RobotView],
    /// The threads the policy may use for its searches, and their pace.
    pub workers: Workers<'a>,
    /// Each robot's latest bids (Simmons et al. 2000, §4.1), in the order of
    /// `robots`; an empty list where a robot sent none.
    pub bids: &'a [Vec<Bid>],
    /// Seed of the policy's random choices (randomized search).
    pub seed: u64,
    /// Targets already held by robots outside this planning (out of
    /// communication range: Burgard et al. 2005, §II-D, "each robot stores
    /// the latest target locations assigned to other robots"), with the
    /// sensor range of the robot holding each.
    pub reserved: &'a [(Cell, f64)],
    /// Rooms and corridors given with the mission, one label per cell of
    /// the grid's frame (0 for none), for policies that plan on a
    /// segmentation (Wurm et al. 2008, §VI).
    pub rooms: Option<&'a [u32]>,
}

/// A robot's estimate for one candidate target (Simmons et al. 2000, §4.1).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Bid {
    /// The candidate frontier cell.
    pub target: Cell,
    /// Path cost from the robot to it, metres.
    pub path_cost_m: f64,
    /// Expected information gain: unknown cells within sensor range reached by flood fill.
    pub information_gain: f64,
    /// Bounding rectangle of that information-gain region.
    pub gain_region: CellRect,
}

impl PlanningInput<'_> {
    /// Every frontier cell of every cluster, in cluster order.
    pub fn frontier_cells(&self) -> Vec<Cell> {
        self.clusters.iter().flat_map(|c| c.cells.iter().copied()).collect()
    }
}

/// Each robot's cost map over its own traversal kind, computed once per
/// replanning (cached) and in parallel on `input.workers` threads.
pub fn robot_cost_maps(
    input: &PlanningInput<'_>,
    costs: &mut CostCache<'_>,
    kinds: &[crate::cost::TraversalKind],
) -> Vec<std::sync::Arc<crate::cost::CostMap>> {
    let mut by_kind: BTreeMap<crate::cost::TraversalKind, Vec<Cell>> = BTreeMap::new();
    for (robot, kind) in input.robots.iter().zip(kinds) {
        by_kind.entry(*kind).or_default().push(robot.cell);
    }
    for (kind, sources) in &by_kind {
        costs.cost_maps(*kind, sources, input.workers);
    }
    input.robots.iter().zip(kinds).map(|(robot, kind)| costs.cost_map(*kind, robot.cell)).collect()
}

/// Each robot's path cost to each of `cells` over its traversal (of
/// `kinds`, one per robot); `None` where it cannot go or must not be sent.
/// The costs of complete searches, but each search goes towards `cells`
/// (A*) and stops once it has reached them all, leaving out the cells
/// behind the robot; on the planner's threads.
pub fn costs_to_cells(
    input: &PlanningInput<'_>,
    costs: &mut CostCache<'_>,
    kinds: &[crate::cost::TraversalKind],
    cells: &[Cell],
) -> Vec<Vec<Option<f64>>> {
    let towards = towards_goals(kinds, costs, cells);
    let pairs: Vec<(&RobotView, &Towards)> = input.robots.iter().zip(&towards).collect();
    costs.count_searches(pairs.len());
    crate::workers::in_parallel(&pairs, input.workers, |(robot, (traversal, goals))| {
        let mut search = crate::cost::GrowingCostMap::towards(traversal, robot.cell, goals);
        search.grow_to_reach(cells);
        cells.iter().map(|&c| if robot.may_target(c) { search.cost(c) } else { None }).collect()
    })
}

/// A traversal and its distance to the goals a search over it heads for.
pub type Towards = (std::sync::Arc<crate::cost::TraversalMap>, std::sync::Arc<crate::cost::GoalDistance>);

/// Each robot's traversal (of `kinds`, one per robot) with that traversal's
/// distance to the nearest of `goals`, computed once per kind: what a
/// search from the robot towards the goals is ordered by
/// ([`crate::cost::GrowingCostMap::towards`]).
pub fn towards_goals(kinds: &[crate::cost::TraversalKind], costs: &mut CostCache<'_>, goals: &[Cell]) -> Vec<Towards> {
    let mut by_kind: BTreeMap<crate::cost::TraversalKind, std::sync::Arc<crate::cost::GoalDistance>> = BTreeMap::new();
    kinds
        .iter()
        .map(|&kind| {
            let traversal = costs.traversal(kind);
            let distance = by_kind
                .entry(kind)
                .or_insert_with(|| std::sync::Arc::new(crate::cost::GoalDistance::new(&traversal, goals)))
                .clone();
            (traversal, distance)
        })
        .collect()
}

/// What reaching one frontier cluster costs a robot.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ClusterCost {
    /// The cell to go to: the cluster's cell cheapest to reach, or the
    /// robot's current target when it lies in the cluster. Read it through
    /// [`ClusterCosts::cell`]: from a cluster's wavefront it is found only
    /// for the pairs a policy picks (a descent per pair would cost more
    /// than the wavefronts).
    pub cell: Cell,
    /// The path cost to that cell.
    pub cost: f64,
    /// The cost the policy compares: `cost`, less the switch margin for the
    /// robot's current target (hysteresis).
    pub score: f64,
    /// `cell` is still to be found by descending the cluster's wavefront.
    descend: bool,
}

/// What reaching each cluster costs each robot (see [`cluster_cost_matrix`]).
#[derive(Debug)]
pub struct ClusterCosts {
    /// Per robot, per cluster; `None` where the robot cannot reach it.
    rows: Vec<Vec<Option<ClusterCost>>>,
    /// The clusters' wavefronts and the robots' cells, when the costs came
    /// from them.
    descent: Option<ClusterWavefronts>,
}

/// The traversal, one wavefront per cluster, and the robots' cells.
type ClusterWavefronts =
    (std::sync::Arc<crate::cost::TraversalMap>, Vec<std::sync::Arc<crate::cost::CostMap>>, Vec<Cell>);

impl std::ops::Deref for ClusterCosts {
    type Target = Vec<Vec<Option<ClusterCost>>>;

    fn deref(&self) -> &Self::Target {
        &self.rows
    }
}

impl ClusterCosts {
    /// The clusters' wavefronts, one per cluster in cluster order, when the
    /// costs were read from them. They answer for the robots' cells, the
    /// cells asked for when the matrix was made, and the paths to them.
    pub fn cluster_maps(&self) -> Option<&[std::sync::Arc<crate::cost::CostMap>]> {
        self.descent.as_ref().map(|(_, maps, _)| maps.as_slice())
    }

    /// The cell robot `i` goes to for cluster `j`.
    pub fn cell(&self, i: usize, j: usize) -> Option<Cell> {
        let c = self.rows.get(i)?.get(j).copied().flatten()?;
        match &self.descent {
            Some((traversal, maps, starts)) if c.descend => {
                // The cluster's cell nearest to the robot: where the wavefront's descent from the robot ends.
                maps[j].path_to(traversal, starts[i]).and_then(|p| p.first().copied())
            }
            _ => Some(c.cell),
        }
    }
}

/// Per cluster, what reaching it costs `robot` on `map`, its cost map; `None`
/// for clusters it cannot reach. A cluster holding its current target,
/// keeps that target and scores `margin` less, so that the robot switches
/// only for a frontier cheaper by more than the margin.
pub fn cluster_costs(
    map: &crate::cost::CostMap,
    clusters: &[FrontierCluster],
    robot: &RobotView,
    margin: f64,
) -> Vec<Option<ClusterCost>> {
    let current = current_target(robot);
    clusters
        .iter()
        .map(|cluster| {
            let kept = current
                .filter(|c| cluster.cells.contains(c))
                .and_then(|cell| robot.cost_to(map, cell).map(|cost| (cell, cost)));
            if let Some((cell, cost)) = kept {
                return Some(ClusterCost { cell, cost, score: cost - margin, descend: false });
            }
            cluster
                .cells
                .iter()
                .filter_map(|&c| robot.cost_to(map, c).map(|cost| (c, cost)))
                .min_by(|a, b| a.1.total_cmp(&b.1))
                .map(|(cell, cost)| ClusterCost { cell, cost, score: cost, descend: false })
        })
        .collect()
}

/// For every robot and cluster, what reaching the cluster costs (see
/// [`cluster_costs`]), from whichever is fewer: one wavefront per robot, or
/// one per cluster (its cells the sources) read at the robots' cells. Both
/// give the same costs on the free-space traversal, where paths are
/// reversible (Bautin et al. 2011 propagate one wavefront per frontier for
/// this reason); robots standing where the cluster's wavefront cannot enter
/// (inside an inflated obstacle), or teams of mixed footprints, use their
/// own wavefronts.
///
/// A cluster's wavefront goes only as far as the robots' cells and
/// `also_reach` (cells a policy reads in [`ClusterCosts::cluster_maps`]
/// besides the robots').
pub fn cluster_cost_matrix(
    input: &PlanningInput<'_>,
    costs: &mut CostCache<'_>,
    margin: f64,
    also_reach: &[Cell],
) -> ClusterCosts {
    let kinds: Vec<crate::cost::TraversalKind> = input.robots.iter().map(RobotView::free_space).collect();
    let one_kind = kinds.windows(2).all(|w| w[0] == w[1]);
    if kinds.is_empty() || !one_kind || input.clusters.len() >= input.robots.len() {
        let rows = free_space_cost_maps(input, costs)
            .iter()
            .zip(input.robots)
            .map(|(m, r)| cluster_costs(m, input.clusters, r, margin))
            .collect();
        return ClusterCosts { rows, descent: None };
    }
    let traversal = costs.traversal(kinds[0]);
    let reach: Vec<Cell> = input.robots.iter().map(|r| r.cell).chain(also_reach.iter().copied()).collect();
    let maps = crate::workers::in_parallel(input.clusters, input.workers, |cluster| {
        std::sync::Arc::new(crate::cost::cost_map_reaching(&traversal, &cluster.cells, &reach))
    });
    let rows = input
        .robots
        .iter()
        .map(|robot| {
            if !robot.excluded.is_empty() {
                // Exclusions are the robot's own: only its wavefront knows them.
                let own = costs.cost_map(kinds[0], robot.cell);
                return cluster_costs(&own, input.clusters, robot, margin);
            }
            // A robot keeping its current target is charged the cluster's
            // cost here, on its own wavefront its target's: they differ when
            // the target is not the cluster's nearest cell. Charging the
            // target exactly needs a search from each robot, 8–12 times this
            // matrix's cost in the replan bench, and changed no run of a
            // 40-run A/B (maze, minpos and greedy, 4 and 10 robots).
            let current = current_target(robot);
            let row: Vec<Option<ClusterCost>> = input
                .clusters
                .iter()
                .zip(&maps)
                .map(|(cluster, map)| {
                    let cost = map.cost(robot.cell)?;
                    if let Some(cell) = current.filter(|c| cluster.cells.contains(c)) {
                        return Some(ClusterCost { cell, cost, score: cost - margin, descend: false });
                    }
                    Some(ClusterCost { cell: robot.cell, cost, score: cost, descend: true })
                })
                .collect();
            if row.iter().all(Option::is_none) && !traversal.passable(robot.cell) {
                // Inside an inflated obstacle: only its own wavefront gets out.
                let own = costs.cost_map(kinds[0], robot.cell);
                return cluster_costs(&own, input.clusters, robot, margin);
            }
            row
        })
        .collect();
    let starts = input.robots.iter().map(|r| r.cell).collect();
    ClusterCosts { rows, descent: Some((traversal, maps, starts)) }
}

/// The robot's current target cell, if it has one.
pub fn current_target(robot: &RobotView) -> Option<Cell> {
    robot.current.map(|c| c.target)
}

/// Free-space cost maps for every robot (wavefronts over known free cells,
/// obstacles inflated by each robot's footprint).
pub fn free_space_cost_maps(
    input: &PlanningInput<'_>,
    costs: &mut CostCache<'_>,
) -> Vec<std::sync::Arc<crate::cost::CostMap>> {
    let kinds: Vec<crate::cost::TraversalKind> = input.robots.iter().map(RobotView::free_space).collect();
    robot_cost_maps(input, costs, &kinds)
}

/// A target chosen for one robot.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Target {
    /// The cell to go to.
    pub cell: Cell,
    /// The policy's figure of merit for this choice (policy-specific units).
    pub utility: f64,
    /// The path cost the policy computed from the robot to the target.
    pub path_cost: f64,
    /// The information-gain region the target is expected to reveal, if the policy estimates one.
    pub gain_region: Option<CellRect>,
}

/// The outcome of one replanning: a target or nothing for every robot, in
/// the order of [`PlanningInput::robots`].
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Plan {
    /// One entry per robot.
    pub targets: Vec<Option<Target>>,
    /// The segmentation the plan was made on (the `segmentation` policy).
    pub segmentation: Option<crate::segment::Segmentation>,
}

impl Plan {
    /// A plan of targets only.
    pub fn of(targets: Vec<Option<Target>>) -> Self {
        Self { targets, segmentation: None }
    }
}

/// A coordination policy.
pub trait Policy: Send + Sync + std::fmt::Debug {
    /// The name it is selected by.
    fn name(&self) -> &'static str;

    /// Chooses targets for all robots.
    fn plan(&self, input: &PlanningInput<'_>, costs: &mut CostCache<'_>) -> Plan;

    /// Whether robots bid (Simmons et al. 2000): the executive then passes a
    /// robot's bids only when they are new or the robot is idle, and plans
    /// again when bids arrive.
    fn uses_bids(&self) -> bool {
        false
    }

    /// Whether its plans carry a segmentation of the map into rooms and
    /// corridors (Wurm et al. 2008), which the executive keeps for
    /// `GetSegmentation`.
    fn keeps_segmentation(&self) -> bool {
        false
    }
}

#[cfg(test)]
pub(crate) mod testing {
    //! Fixtures shared by the policies' tests.
    use super::*;
    use crate::frontier::{FrontierMap, clusters};
    use crate::grid::testing::grid_from_picture;

    pub fn robot(id: RobotId, cell: Cell, sensor_range_m: f64) -> RobotView {
        RobotView {
            id,
            cell,
            capabilities: Capabilities {
                sensor_range_m,
                field_of_view_rad: std::f64::consts::TAU,
                speed_mps: 1.0,
                footprint_radius_m: 0.0,
            },
            current: None,
            excluded: Vec::new(),
        }
    }

    /// A corridor with a frontier at each end and a dead-end branch down
    /// from its left part: robot 0 in the corridor near the left end, robot 1
    /// at the bottom of the branch (2.4 from the left end, 11.4 from the
    /// right; robot 0 is 2 and 9 away). The cheapest pair of all is robot 0
    /// to the left end, which leaves robot 1 the far right (13.4 in all); the
    /// least total swaps them (11.4). Returns the grid, the robots and the
    /// left and right frontier cells.
    pub fn cheapest_pair_trap() -> (OccupancyGrid, [RobotView; 2], Cell, Cell) {
        let grid = grid_from_picture(&[
            "##############", //
            "?............?", //
            "##.###########", //
            "##.###########", //
            "##############", //
        ]);
        let robots = [robot(0, Cell::new(3, 3), 5.0), robot(1, Cell::new(2, 1), 5.0)];
        (grid, robots, Cell::new(1, 3), Cell::new(12, 3))
    }

    /// A `width` × `height` grid (0.5 m cells), unknown but for a random
    /// rectangle whose cells take `value(rng)`; and that rectangle's cells
    /// a robot may stand on (P(occ) of at most 60 %).
    pub fn random_known_rectangle(
        width: u32,
        height: u32,
        rng: &mut crate::rng::SplitMix64,
        mut value: impl FnMut(&mut crate::rng::SplitMix64) -> u8,
    ) -> (OccupancyGrid, Vec<Cell>) {
        let frame = crate::grid::GridFrame::new(0.5, crate::math::Point2::origin(), width, height);
        let mut grid = OccupancyGrid::unknown(frame);
        let (x0, y0) = (rng.below(u64::from(width / 2)) as i32, rng.below(u64::from(height / 2)) as i32);
        let x1 = x0 + 2 + rng.below(u64::from(width) - x0 as u64 - 1) as i32;
        let y1 = y0 + 2 + rng.below(u64::from(height) - y0 as u64 - 1) as i32;
        let mut free = Vec::new();
        for i in 0..frame.len() {
            let c = frame.cell(i);
            if (x0..x1).contains(&c.x) && (y0..y1).contains(&c.y) {
                let v = value(rng);
                grid.set(c, v);
                if v <= 60 {
                    free.push(c);
                }
            }
        }
        (grid, free)
    }

    /// [`random_known_rectangle`] of free cells (P(occ) 10 %) and walls,
    /// one cell in six.
    pub fn random_walled_rectangle(
        width: u32,
        height: u32,
        rng: &mut crate::rng::SplitMix64,
    ) -> (OccupancyGrid, Vec<Cell>) {
        random_known_rectangle(width, height, rng, |rng| if rng.below(6) == 0 { 95 } else { 10 })
    }

    /// `robots` robots on random cells of `free`; half of them hold a
    /// current target drawn from `targets`, and with `exclusions` a third
    /// must not be sent within a cell of some free cell.
    pub fn random_team(
        robots: usize,
        free: &[Cell],
        targets: &[Cell],
        exclusions: bool,
        rng: &mut crate::rng::SplitMix64,
    ) -> Vec<RobotView> {
        let pick = |cells: &[Cell], rng: &mut crate::rng::SplitMix64| cells[rng.below(cells.len() as u64) as usize];
        (0..robots as u64)
            .map(|id| {
                let mut r = robot(id, pick(free, rng), 0.5 + 3.0 * rng.next_f64());
                if rng.below(2) == 0 && !targets.is_empty() {
                    r.current = Some(CurrentTask { target: pick(targets, rng), gain_region: None });
                }
                if exclusions && rng.below(3) == 0 {
                    let c = pick(free, rng);
                    r.excluded.push(crate::grid::CellRect::new(c.x - 1, c.y - 1, 3, 3));
                }
                r
            })
            .collect()
    }

    /// Runs the named policy with its default parameters, as a mission that
    /// selects it without overrides would.
    pub fn plan_with_defaults(name: &str, grid: &OccupancyGrid, robots: &[RobotView]) -> Vec<Option<Cell>> {
        let policy = PolicyConfig::default_for(name).expect("a catalogued policy").build();
        plan_targets(policy.as_ref(), grid, robots)
    }

    /// Runs a policy on a grid and returns each robot's target cell.
    pub fn plan_targets(policy: &dyn Policy, grid: &OccupancyGrid, robots: &[RobotView]) -> Vec<Option<Cell>> {
        let plan = with_input(grid, robots, &vec![Vec::new(); robots.len()], |input| {
            policy.plan(input, &mut CostCache::new(grid))
        });
        assert_eq!(plan.targets.len(), robots.len());
        plan.targets.iter().map(|t| t.map(|t| t.cell)).collect()
    }

    /// Runs `f` on the input a mission would plan from: this grid's
    /// frontier clusters, these robots and their bids, one thread.
    pub fn with_input<R>(
        grid: &OccupancyGrid,
        robots: &[RobotView],
        bids: &[Vec<Bid>],
        f: impl FnOnce(&PlanningInput<'_>) -> R,
    ) -> R {
        let frontier = FrontierMap::detect(grid);
        let clusters = clusters(&frontier, 1);
        f(&PlanningInput {
            grid,
            clusters: &clusters,
            robots,
            workers: Workers::unpaced(1),
            bids,
            seed: 7,
            reserved: &[],
            rooms: None,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn configs_validate_names_and_ranges() {
        let err = PolicyConfig::default_for("teleport").unwrap_err();
        for name in catalogue().iter().map(|d| d.name) {
            assert!(err.to_string().contains(name), "{err}");
        }

        let mut overrides = BTreeMap::new();
        overrides.insert("beta".to_owned(), 2.5);
        let config = PolicyConfig::new("burgard", &overrides).unwrap();
        assert_eq!(config.get("beta"), 2.5);
        assert_eq!(config.get("occ_max"), 0.6);

        overrides.insert("beta".to_owned(), -1.0);
        let err = PolicyConfig::new("burgard", &overrides).unwrap_err();
        assert!(matches!(err, PolicyError::OutOfRange { name: "beta", .. }), "{err}");
        overrides.insert("beta".to_owned(), f64::NAN);
        assert!(PolicyConfig::new("burgard", &overrides).is_err());

        let mut unknown = BTreeMap::new();
        unknown.insert("gamma".to_owned(), 1.0);
        let err = PolicyConfig::new("burgard", &unknown).unwrap_err();
        assert!(err.to_string().contains("beta"), "{err}");
    }

    /// A known corridor 40 cells long, 5 high, open to unknown space at both ends.
    fn open_corridor() -> OccupancyGrid {
        let frame = crate::grid::GridFrame::new(0.1, crate::math::Point2::origin(), 60, 7);
        let mut grid = OccupancyGrid::unknown(frame);
        for y in 0..7 {
            for x in 10..50 {
                grid.set(Cell::new(x, y), if y == 0 || y == 6 { 100 } else { 0 });
            }
        }
        grid
    }

    #[test]
    fn no_policy_sends_a_robot_where_it_is_excluded() {
        let grid = open_corridor();
        // Nearer the left end, which is excluded for it: every policy must
        // send it to the right end instead (Wurm et al. 2008, Eq. 4).
        let mut robot = testing::robot(1, Cell::new(20, 3), 1.0);
        let left = CellRect::new(0, 0, 15, 7);
        robot.excluded = vec![left];
        for d in catalogue() {
            let policy = PolicyConfig::default_for(d.name).unwrap().build();
            let targets = testing::plan_targets(policy.as_ref(), &grid, std::slice::from_ref(&robot));
            let target = targets[0].unwrap_or_else(|| panic!("{} gave no target", d.name));
            assert!(!left.contains(target), "{} sent the robot to excluded {target:?}", d.name);
        }
        robot.excluded.clear();
        let nearest = PolicyConfig::default_for("nearest").unwrap().build();
        let target = testing::plan_targets(nearest.as_ref(), &grid, &[robot])[0].unwrap();
        assert!(left.contains(target), "without the exclusion the left end is nearer: {target:?}");
    }

    #[test]
    fn every_catalogued_policy_builds_under_its_name() {
        for d in catalogue() {
            let config = PolicyConfig::default_for(d.name).unwrap();
            assert_eq!(config.build().name(), d.name);
            for p in d.params {
                assert!(p.min <= p.default && p.default <= p.max, "{}.{}", d.name, p.name);
            }
        }
    }
}
