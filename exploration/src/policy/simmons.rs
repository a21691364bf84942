//! `simmons`: robots bid, the executive assigns greedily on net utility.
//!
//! Simmons, Apfelbaum, Burgard, Fox, Moors, Thrun & Younes 2000.
//!
//! Bids (§4.1, [`compute_bids`]): frontier cells at least a robot radius
//! apart; for each, the path cost from the robot and the expected
//! information gain, the number of unknown cells within sensor range of the
//! cell reached by flood fill (propagation stops at clear and obstacle
//! cells, and beyond the sensor range), with the bounding rectangle of that
//! region. Robots compute their own bids and send them (`SubmitBids`); for a
//! robot that sent none, the executive computes them from the fused map.
//!
//! Assignment (§4.2): the bid of highest net utility
//!
//! u_j = (1 − d_j) · I_j − c_j,  d_j = Area(IGR_j ∩ ∪ IGR_assigned) / Area(IGR_j)
//!
//! is assigned first; the bids of the remaining robots are discounted by the
//! overlap d_j of their gain rectangles with those already assigned, and so
//! on until every robot has a task or no bid's discounted gain reaches the
//! minimum threshold (those robots stay idle). Hysteresis: a frontier cell
//! inside the gain region of the robot's current task has its gain divided
//! by the hysteresis ratio (usually 0.85). Only robots that are idle or have
//! sent new bids are tasked (§4.2: "leaving the currently active ones to
//! continue"); the regions of those that continue count as assigned. A bid
//! whose target is no longer a frontier cell of the current map is dropped.
//!
//! Units. The paper counts I_j in unknown cells and c_j as a path cost
//! without a scale between them; counted in cells, the gain of an open room
//! (thousands of cells) swamps any path (tens of cells), and a robot crosses
//! the building for the largest unknown area it can see. Here both are in
//! metres of travel: a robot driving d metres sweeps a strip as wide as its
//! sensor, 2r, so revealing A m² is worth A / 2r metres of driving. I_j is
//! converted so (times `gain_scale`, a calibration the paper does not give;
//! see docs/results.md) and c_j is the path length in metres.

use super::registry::{MIN_FRONTIER_SIZE, ParamSpec, PolicyDescriptor};
use super::{Bid, Capabilities, Plan, PlanningInput, Policy, RobotView, Target, costs_to_cells};
use crate::cost::{CostCache, CostMap, TraversalKind};
use crate::grid::{Cell, CellRect, GridFrame, NEIGHBOURS_8, OccupancyGrid, UNKNOWN};

pub(super) const NAME: &str = "simmons";

/// The catalogue's entry: name, what it does, parameters with units, and
/// how it is built from a validated configuration.
pub(super) const DESCRIPTOR: PolicyDescriptor = PolicyDescriptor {
    name: NAME,
    description: "Simmons et al. 2000: greedy on bids' net utility (1 - d) * I - c, d the overlap of gain rectangles with those already assigned; minimum gain; hysteresis ratio",
    params: &[
        MIN_FRONTIER_SIZE,
        ParamSpec {
            name: "hysteresis_ratio",
            description: "a frontier inside the gain region of the robot's current task has its gain divided by this (§4.2; usually 0.85)",
            default: 0.85,
            min: 0.01,
            max: 1.0,
        },
        ParamSpec {
            name: "min_gain",
            description: "a robot whose best discounted gain is below this many cells stays idle (§4.2)",
            default: 1.0,
            min: 0.0,
            max: 1_000_000.0,
        },
        ParamSpec {
            name: "gain_scale",
            description: "u = gain_scale * (1 - d) * I - c, both in metres: I, the unknown area in reach, as metres of driving that reveal it (area / sensor width 2r), c the path; 1 counts a metre of revealing driving as a metre of path",
            default: 1.0,
            min: 0.0,
            max: 1_000.0,
        },
        ParamSpec {
            name: "spacing_m",
            description: "bid frontier cells are at least this far apart (§4.1: about a robot radius, 30 cm)",
            default: 0.3,
            min: 0.0,
            max: 10.0,
        },
    ],
    build: |c| {
        Box::new(Simmons {
            hysteresis_ratio: c.get("hysteresis_ratio"),
            min_gain: c.get("min_gain"),
            gain_scale: c.get("gain_scale"),
            spacing_m: c.get("spacing_m"),
        })
    },
};

/// Simmons et al. 2000, §4.2.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Simmons {
    /// The gain of a frontier inside the current task's gain region is divided by this.
    pub hysteresis_ratio: f64,
    /// Robots whose best discounted gain is below this (cells) stay idle.
    pub min_gain: f64,
    /// How much a metre of revealing driving (area / sensor width) is worth
    /// against a metre of path: 1 counts both alike.
    pub gain_scale: f64,
    /// Bid frontier cells are at least this far apart, metres.
    pub spacing_m: f64,
}

/// Frontier cells at least `spacing_cells` apart, chosen greedily in the
/// given order (§4.1: "each frontier cell must be at least some minimum
/// distance from all other frontier cells").
pub fn spaced(cells: &[Cell], spacing_cells: f64) -> Vec<Cell> {
    if spacing_cells <= 1.0 {
        return cells.to_vec();
    }
    let bucket = spacing_cells.ceil() as i32;
    let mut grid: std::collections::HashMap<(i32, i32), Vec<Cell>> = std::collections::HashMap::new();
    let mut kept = Vec::new();
    let min_sq = spacing_cells * spacing_cells;
    for &c in cells {
        let (bx, by) = (c.x.div_euclid(bucket), c.y.div_euclid(bucket));
        let clear = (-1..=1).all(|dy| {
            (-1..=1).all(|dx| {
                grid.get(&(bx + dx, by + dy)).is_none_or(|v| v.iter().all(|o| (o.distance_squared(c) as f64) >= min_sq))
            })
        });
        if clear {
            grid.entry((bx, by)).or_default().push(c);
            kept.push(c);
        }
    }
    kept
}

/// The information-gain region of a frontier cell (§4.1): the unknown
/// cells within `range_cells` of it reached by a 4-connected flood fill
/// through unknown cells, as a count and a bounding rectangle.
///
/// Complexity: O(range²).
pub fn gain_region(grid: &OccupancyGrid, at: Cell, range_cells: f64) -> (f64, CellRect) {
    let frame = grid.frame();
    let range_sq = range_cells * range_cells;
    let mut seen = Marks::around(frame, at, range_sq);
    let mut stack: Vec<Cell> = NEIGHBOURS_8[..4]
        .iter()
        .map(|&(dx, dy)| Cell::new(at.x + dx, at.y + dy))
        .filter(|c| frame.contains(*c) && grid.value(*c) == UNKNOWN)
        .collect();
    for c in &stack {
        seen.insert(*c);
    }
    let mut rect = CellRect::new(at.x, at.y, 1, 1);
    let mut count = 0usize;
    while let Some(c) = stack.pop() {
        count += 1;
        rect = rect.including(c);
        for &(dx, dy) in &NEIGHBOURS_8[..4] {
            let n = Cell::new(c.x + dx, c.y + dy);
            if frame.contains(n)
                && grid.value(n) == UNKNOWN
                && (n.distance_squared(at) as f64) <= range_sq
                && seen.insert(n)
            {
                stack.push(n);
            }
        }
    }
    (count as f64, rect)
}

/// The cells a gain region's flood fill has seen: a flag per cell of the
/// only square the fill can reach (on the grid, within the range of its
/// frontier cell or next to it) instead of a hashed set, since the fill
/// runs for every candidate cell at every replanning.
struct Marks {
    window: CellRect,
    seen: Vec<bool>,
}

impl Marks {
    fn around(frame: &GridFrame, at: Cell, range_sq: f64) -> Self {
        // At least the four neighbours the fill starts from; NaN gives 1.
        let reach = if range_sq >= 1.0 { range_sq.sqrt().min(f64::from(u32::MAX)) as u32 } else { 1 };
        let window = frame.clip(&CellRect::new(at.x, at.y, 1, 1).grown(reach)).unwrap_or(CellRect::new(0, 0, 0, 0));
        Self { window, seen: vec![false; window.area() as usize] }
    }

    /// Marks `cell`; whether it was not marked before. Every cell the fill
    /// offers lies in the window; one off it is never taken.
    fn insert(&mut self, cell: Cell) -> bool {
        if !self.window.contains(cell) {
            return false;
        }
        let i = (cell.y - self.window.y) as usize * self.window.width as usize + (cell.x - self.window.x) as usize;
        !std::mem::replace(&mut self.seen[i], true)
    }
}

/// A robot's bids (§4.1): for spaced frontier cells it can reach, the path
/// cost (from `cost_map`, the robot's own) and the information gain of its
/// sensor there.
pub fn compute_bids(
    grid: &OccupancyGrid,
    frontier: &[Cell],
    cost_map: &CostMap,
    capabilities: &Capabilities,
    spacing_m: f64,
) -> Vec<Bid> {
    let resolution = grid.frame().resolution;
    let candidates = spaced(frontier, spacing_m / resolution);
    let range_cells = capabilities.sensor_range_m / resolution;
    candidates
        .into_iter()
        .filter_map(|target| {
            let cost = cost_map.cost(target)?;
            let (gain, region) = gain_region(grid, target, range_cells);
            Some(Bid { target, path_cost_m: cost, information_gain: gain, gain_region: region })
        })
        .collect()
}

/// The union of the gain rectangles assigned so far, with a summed-area
/// table so that the covered share of any rectangle takes four lookups.
struct Coverage {
    bounds: CellRect,
    covered: Vec<u8>,
    /// (width + 1) × (height + 1) prefix sums of `covered`.
    sums: Vec<u32>,
}

impl Coverage {
    fn new(bounds: CellRect) -> Self {
        let (w, h) = (bounds.width as usize, bounds.height as usize);
        Self { bounds, covered: vec![0; w * h], sums: vec![0; (w + 1) * (h + 1)] }
    }

    fn add(&mut self, rect: &CellRect) {
        let Some(r) = rect.intersection(&self.bounds) else { return };
        let (w, h) = (self.bounds.width as usize, self.bounds.height as usize);
        let (x0, x1) = ((r.x - self.bounds.x) as usize, (r.x_end() - self.bounds.x) as usize);
        let y0 = (r.y - self.bounds.y) as usize;
        for y in y0..(r.y_end() - self.bounds.y) as usize {
            self.covered[y * w + x0..y * w + x1].fill(1);
        }
        // Only the sums right of and above the rectangle's lower-left corner
        // change; a row's run up to column x0 is read from the sums left of it.
        let stride = w + 1;
        for y in y0..h {
            let mut run = self.sums[(y + 1) * stride + x0] - self.sums[y * stride + x0];
            for x in x0..w {
                run += u32::from(self.covered[y * w + x]);
                self.sums[(y + 1) * stride + x + 1] = self.sums[y * stride + x + 1] + run;
            }
        }
    }

    /// d_j of §4.2: the share of `rect` inside the union. `bounds` holds
    /// every region's part on the map, so the share is of that part.
    fn overlap(&self, rect: &CellRect) -> f64 {
        let Some(r) = rect.intersection(&self.bounds) else { return 0.0 };
        let stride = self.bounds.width as usize + 1;
        let (x0, x1) = ((r.x - self.bounds.x) as usize, (r.x_end() - self.bounds.x) as usize);
        let (y0, y1) = ((r.y - self.bounds.y) as usize, (r.y_end() - self.bounds.y) as usize);
        let inside = self.sums[y1 * stride + x1] + self.sums[y0 * stride + x0]
            - self.sums[y0 * stride + x1]
            - self.sums[y1 * stride + x0];
        f64::from(inside) / r.area() as f64
    }
}

impl Policy for Simmons {
    fn name(&self) -> &'static str {
        NAME
    }

    fn plan(&self, input: &PlanningInput<'_>, costs: &mut CostCache<'_>) -> Plan {
        let grid = input.grid;
        let resolution = grid.frame().resolution;
        // §4.2: a robot with a task and no new bids continues.
        let continues = |i: usize| input.bids.get(i).is_none_or(Vec::is_empty) && input.robots[i].current.is_some();
        let bidders: Vec<usize> =
            (0..input.robots.len()).filter(|&i| input.bids.get(i).is_none_or(Vec::is_empty) && !continues(i)).collect();
        // Bids for idle robots that sent none: computed here from the fused
        // map, with cost maps for those robots only. Candidate cells and
        // gains do not depend on the robot, only costs do.
        let mut computed: Vec<Vec<Bid>> = vec![Vec::new(); input.robots.len()];
        if !bidders.is_empty() {
            let frontier = spaced(&input.frontier_cells(), self.spacing_m / resolution);
            let robots: Vec<RobotView> = bidders.iter().map(|&i| input.robots[i].clone()).collect();
            let kinds: Vec<TraversalKind> = robots.iter().map(RobotView::free_space).collect();
            let path_costs = costs_to_cells(&PlanningInput { robots: &robots, ..*input }, costs, &kinds, &frontier);
            let mut gains: std::collections::HashMap<(Cell, u64), (f64, CellRect)> = std::collections::HashMap::new();
            for ((&i, robot), row) in bidders.iter().zip(&robots).zip(&path_costs) {
                let range = robot.capabilities.sensor_range_m / resolution;
                computed[i] = frontier
                    .iter()
                    .zip(row)
                    .filter_map(|(&target, &cost)| {
                        let cost = cost?;
                        let (gain, region) =
                            *gains.entry((target, range.to_bits())).or_insert_with(|| gain_region(grid, target, range));
                        Some(Bid { target, path_cost_m: cost, information_gain: gain, gain_region: region })
                    })
                    .collect();
            }
        }
        let bids: Vec<&[Bid]> = (0..input.robots.len())
            .map(|i| match input.bids.get(i) {
                Some(b) if !b.is_empty() => &b[..],
                _ => &computed[i][..],
            })
            .collect();
        let mut targets: Vec<Option<Target>> = vec![None; input.robots.len()];
        let frame = grid.frame();
        // Regions come from robots: only the part on the map counts, so the
        // coverage below is never larger than the grid.
        let continuing = (0..input.robots.len()).filter(|&i| continues(i));
        let kept_regions = continuing.clone().filter_map(|i| input.robots[i].current.and_then(|c| c.gain_region));
        let Some(bounds) = bids
            .iter()
            .flat_map(|b| b.iter().map(|b| b.gain_region))
            .chain(kept_regions.clone())
            .filter_map(|r| frame.clip(&r))
            .reduce(|a, b| a.union(&b))
        else {
            return Plan::of(self.continued(input, targets));
        };
        let mut assigned = Coverage::new(bounds);
        for region in kept_regions {
            assigned.add(&region);
        }
        targets = self.continued(input, targets);
        // A bid on what is no longer frontier is stale; the map does not
        // change while the robots are assigned, so neither does that.
        let live: Vec<Vec<usize>> = bids
            .iter()
            .zip(input.robots)
            .map(|(robot_bids, robot)| {
                (0..robot_bids.len())
                    .filter(|&b| {
                        let target = robot_bids[b].target;
                        robot.may_target(target) && crate::frontier::is_frontier(grid, target)
                    })
                    .collect()
            })
            .collect();
        loop {
            let mut best: Option<(f64, usize, usize)> = None;
            for (i, robot_bids) in bids.iter().enumerate() {
                if targets[i].is_some() {
                    continue;
                }
                let robot = &input.robots[i];
                let current_region = robot.current.and_then(|c| c.gain_region);
                let metres_per_cell = resolution * resolution / (2.0 * robot.capabilities.sensor_range_m);
                for &b in &live[i] {
                    let bid = &robot_bids[b];
                    let mut gain = (1.0 - assigned.overlap(&bid.gain_region)) * bid.information_gain;
                    if current_region.is_some_and(|r| r.contains(bid.target)) {
                        gain /= self.hysteresis_ratio;
                    }
                    if gain < self.min_gain || gain <= 0.0 {
                        continue;
                    }
                    let utility = self.gain_scale * gain * metres_per_cell - bid.path_cost_m;
                    // Ties: the lower robot, then its earlier bid (the paper is silent).
                    if best.is_none_or(|(u, ..)| utility > u) {
                        best = Some((utility, i, b));
                    }
                }
            }
            let Some((utility, i, b)) = best else { break };
            let bid = bids[i][b];
            assigned.add(&bid.gain_region);
            targets[i] = Some(Target {
                cell: bid.target,
                utility,
                path_cost: bid.path_cost_m,
                gain_region: Some(bid.gain_region),
            });
        }
        Plan::of(targets)
    }

    fn uses_bids(&self) -> bool {
        true
    }
}

impl Simmons {
    /// `targets` with the robots that continue (a task, no new bids) kept on it.
    fn continued(&self, input: &PlanningInput<'_>, mut targets: Vec<Option<Target>>) -> Vec<Option<Target>> {
        for (i, robot) in input.robots.iter().enumerate() {
            if input.bids.get(i).is_none_or(Vec::is_empty)
                && let Some(current) = robot.current
            {
                targets[i] = Some(Target {
                    cell: current.target,
                    utility: 0.0,
                    path_cost: 0.0,
                    gain_region: current.gain_region,
                });
            }
        }
        targets
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::grid::testing::grid_from_picture;
    use crate::policy::testing::{plan_with_defaults, robot, with_input};
    use crate::policy::{CurrentTask, RobotView};

    fn simmons() -> Simmons {
        Simmons { hysteresis_ratio: 0.85, min_gain: 1.0, gain_scale: 1.0, spacing_m: 0.0 }
    }

    fn plan(policy: &Simmons, grid: &OccupancyGrid, robots: &[RobotView]) -> Vec<Option<Target>> {
        with_input(grid, robots, &vec![Vec::new(); robots.len()], |input| {
            policy.plan(input, &mut CostCache::new(grid)).targets
        })
    }

    #[test]
    fn gain_regions_stop_at_walls_and_sensor_range() {
        let grid = grid_from_picture(&[
            "#?????#??????", //
            "#?????#??????", //
            "#.....#......", //
        ]);
        let (gain, rect) = gain_region(&grid, Cell::new(3, 0), 10.0);
        // The unknown space of the left room only: 5 × 2 cells.
        assert_eq!(gain, 10.0);
        assert_eq!(rect, CellRect::new(1, 0, 5, 3));
        let (near, _) = gain_region(&grid, Cell::new(3, 0), 1.0);
        assert_eq!(near, 1.0, "only the cell right above is within range");
    }

    /// The worst ranges a robot's capabilities could give, and a frontier
    /// cell on the grid's edge: the fill stays on the grid and within range.
    #[test]
    fn gain_regions_take_any_range() {
        let grid = grid_from_picture(&[
            "??????", //
            "?.....", //
        ]);
        let at = Cell::new(1, 0);
        assert_eq!(gain_region(&grid, at, f64::INFINITY).0, 7.0, "every unknown cell");
        assert_eq!(gain_region(&grid, at, 1e12).0, 7.0);
        assert_eq!(gain_region(&grid, at, 2.0).0, 4.0, "(0, 0), (0, 1), (1, 1) and (2, 1)");
        for start_only in [1.0, 0.5, 0.0, f64::NAN] {
            assert_eq!(gain_region(&grid, at, start_only).0, 2.0, "range {start_only}: the neighbours it starts from");
        }
        assert_eq!(gain_region(&grid, at, -3.0), gain_region(&grid, at, 3.0), "only the range's square counts");
    }

    /// The summed-area table kept up to date one region at a time answers
    /// as counting the covered cells does.
    #[test]
    fn coverage_answers_as_counting_cells_does() {
        let bounds = CellRect::new(-3, 2, 17, 11);
        let mut rng = crate::rng::SplitMix64::new(7);
        let mut rect = || {
            let (x, y) = (rng.below(24) as i32 - 6, rng.below(18) as i32 - 2);
            CellRect::new(x, y, 1 + rng.below(8) as u32, 1 + rng.below(8) as u32)
        };
        let mut coverage = Coverage::new(bounds);
        let mut added: Vec<CellRect> = Vec::new();
        for _ in 0..40 {
            let region = rect();
            coverage.add(&region);
            added.push(region);
            for _ in 0..20 {
                let probe = rect();
                let Some(inside) = probe.intersection(&bounds) else { continue };
                let covered = inside.cells().filter(|&c| added.iter().any(|r| r.contains(c))).count();
                assert_eq!(
                    coverage.overlap(&probe),
                    covered as f64 / inside.area() as f64,
                    "{probe:?} after {added:?}"
                );
            }
        }
    }

    /// Simmons et al. 2000, §4.2: "two robots are tasked to explore adjacent
    /// rooms": a known wall separates their gain regions, so neither
    /// discounts the other and both keep their own room.
    #[test]
    fn robots_in_adjacent_rooms_keep_their_rooms() {
        // The rooms connect through the bottom row.
        let grid = grid_from_picture(&[
            "###########", //
            "#????#????#", //
            "#????#????#", //
            "#....#....#", //
            "#.........#", //
            "###########", //
        ]);
        let robots = [robot(0, Cell::new(2, 1), 5.0), robot(1, Cell::new(7, 1), 5.0)];
        let targets = plan(&simmons(), &grid, &robots);
        let left = targets[0].unwrap().cell;
        let right = targets[1].unwrap().cell;
        assert!(left.x < 5 && right.x > 5, "{left:?} {right:?}");
    }

    /// §4.2's hysteresis: once a robot has seen most of its room, the rest
    /// of the room is worth less than a frontier elsewhere; dividing the gain
    /// inside its current task's region by 0.85 keeps it on its room.
    #[test]
    fn hysteresis_keeps_a_robot_on_its_room() {
        // Left: a room with 10 unknown cells left; right, behind a door, 11.
        let grid = grid_from_picture(&[
            "#############", //
            "#?????#??????", //
            "#?????#?????#", //
            "#.....#.....#", //
            "#...........#", //
            "#############", //
        ]);
        let at = Cell::new(3, 1);
        let mut r = robot(0, at, 10.0);
        let fresh = plan(&Simmons { gain_scale: 1e6, ..simmons() }, &grid, std::slice::from_ref(&r));
        let elsewhere = fresh[0].unwrap().cell;
        assert!(elsewhere.x > 6, "without hysteresis the bigger region wins: {elsewhere:?}");
        r.current = Some(CurrentTask { target: Cell::new(3, 2), gain_region: Some(CellRect::new(1, 2, 5, 3)) });
        let kept = plan(&Simmons { gain_scale: 1e6, ..simmons() }, &grid, &[r]);
        assert!(kept[0].unwrap().cell.x < 6, "hysteresis keeps the room: {:?}", kept[0]);
    }

    #[test]
    fn overlapping_gain_regions_are_discounted_and_small_gains_leave_robots_idle() {
        // One small unknown pocket: the second robot's bid there is fully
        // covered by the first's region, so it stays idle.
        let grid = grid_from_picture(&[
            "#####", //
            "#???#", //
            "#...#", //
            "#...#", //
            "#####", //
        ]);
        let robots = [robot(0, Cell::new(1, 1), 5.0), robot(1, Cell::new(3, 1), 5.0)];
        let targets = plan(&simmons(), &grid, &robots);
        assert_eq!(targets.iter().filter(|t| t.is_some()).count(), 1, "{targets:?}");
        assert_eq!(plan_with_defaults("simmons", &grid, &robots).iter().filter(|t| t.is_some()).count(), 1);
        // Closest frontier sends both.
        assert!(plan_with_defaults("nearest", &grid, &robots).iter().all(Option::is_some));
    }

    /// §4.2: only idle robots without bids are bid for, so only they need
    /// searches: a robot on its way to a task costs the replanning none.
    #[test]
    fn only_robots_that_need_bids_get_cost_maps() {
        let grid = grid_from_picture(&[
            "#?????????#", //
            "#.........#", //
            "#.........#", //
            "###########", //
        ]);
        let mut busy = robot(0, Cell::new(2, 1), 5.0);
        busy.current = Some(CurrentTask { target: Cell::new(2, 2), gain_region: Some(CellRect::new(1, 2, 4, 2)) });
        let bid = Bid {
            target: Cell::new(8, 2),
            path_cost_m: 1.0,
            information_gain: 5.0,
            gain_region: CellRect::new(6, 2, 4, 2),
        };
        let robots = [busy, robot(1, Cell::new(5, 1), 5.0), robot(2, Cell::new(8, 1), 5.0)];
        let bids = vec![Vec::new(), Vec::new(), vec![bid]];
        let mut costs = CostCache::new(&grid);
        let targets = with_input(&grid, &robots, &bids, |input| simmons().plan(input, &mut costs).targets);
        assert_eq!(costs.computed(), 1, "one idle robot without bids");
        assert_eq!(targets[0].map(|t| t.cell), Some(Cell::new(2, 2)), "the busy robot continues");
        assert!(targets[1].is_some(), "the idle robot is bid for: {targets:?}");
    }

    /// A robot's bid region is its own claim: one spanning the whole `i32`
    /// plane once made the coverage below allocate petabytes. Only the part
    /// on the map counts.
    #[test]
    fn bid_regions_beyond_the_map_count_only_on_the_map() {
        let grid = grid_from_picture(&[
            "#####", //
            "#???#", //
            "#...#", //
            "#####", //
        ]);
        let robots = [robot(0, Cell::new(1, 1), 5.0), robot(1, Cell::new(3, 1), 5.0)];
        let everywhere = CellRect::spanning(Cell::new(i32::MIN, i32::MIN), Cell::new(i32::MAX, i32::MAX));
        let bid =
            |x| Bid { target: Cell::new(x, 1), path_cost_m: 0.1, information_gain: 100.0, gain_region: everywhere };
        let bids = vec![vec![bid(1)], vec![bid(3)]];
        let targets =
            with_input(&grid, &robots, &bids, |input| simmons().plan(input, &mut CostCache::new(&grid)).targets);
        // The first region covers the whole map, so the second bid is fully discounted.
        assert_eq!(targets.iter().filter(|t| t.is_some()).count(), 1, "{targets:?}");
    }

    #[test]
    fn spacing_thins_bid_cells() {
        let cells: Vec<Cell> = (0..10).map(|x| Cell::new(x, 0)).collect();
        assert_eq!(spaced(&cells, 3.0), vec![Cell::new(0, 0), Cell::new(3, 0), Cell::new(6, 0), Cell::new(9, 0)]);
    }
}
