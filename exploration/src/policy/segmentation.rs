//! `segmentation`: one robot per room.
//!
//! Wurm, Stachniss & Burgard 2008, Algorithm 1:
//! 1. segment the explored map (Voronoi graph, critical points; see
//!    [`crate::segment`]), or, when the mission was given its rooms and
//!    corridors, take those as far as they are known (§VI: "we assumed a
//!    given segmentation of the environment into rooms and corridors in our
//!    simulation experiments"; [`crate::segment::given`]);
//! 2. the frontier targets of each segment;
//! 3. the cost C_s^i of segment s for robot i: the path cost to its nearest
//!    frontier cell,
//! 4. discounted by a constant factor if robot i is already in s (so robots
//!    stay in their segment until it is explored);
//! 5. robots to segments by the Hungarian method, with infinite cost where
//!    a robot cannot enter a segment (Eq. 4, heterogeneous teams: each
//!    robot's costs come from its own configuration space);
//! 6. within each segment, its robots to its frontier cells by the
//!    Hungarian method on path costs (lines 6–8).
//!
//! More robots than unexplored segments: the segments are offered again to
//! the robots left over (§III, "duplicating existing targets").

use std::sync::Arc;

use super::registry::{MIN_FRONTIER_SIZE, ParamSpec, PolicyDescriptor, SWITCH_METRES};
use super::{Plan, PlanningInput, Policy, RobotView, Target, current_target, free_space_cost_maps};
use crate::assign::assign_with_dummies;
use crate::cost::{CostCache, CostMap, GoalDistance, GrowingCostMap, TraversalKind, TraversalMap};
use crate::grid::Cell;
use crate::segment::{Segment, given, segment};
use crate::workers::in_parallel;

pub(super) const NAME: &str = "segmentation";

/// The catalogue's entry: name, what it does, parameters with units, and
/// how it is built from a validated configuration.
pub(super) const DESCRIPTOR: PolicyDescriptor = PolicyDescriptor {
    name: NAME,
    description: "Wurm et al. 2008, Algorithm 1: Voronoi segmentation of the explored map (or the rooms given with the mission), Hungarian assignment of robots to segments, then to frontiers inside each segment",
    params: &[
        MIN_FRONTIER_SIZE,
        SWITCH_METRES,
        ParamSpec {
            name: "inside_discount",
            description: "a segment's cost is multiplied by this for a robot already inside it (Algorithm 1, line 4)",
            default: 0.5,
            min: 0.0,
            max: 1.0,
        },
        ParamSpec {
            name: "min_drop_m",
            description: "a critical point's clearance is at least this much below the passage on both its sides, metres",
            default: crate::segment::DEFAULT_MIN_DROP_M,
            min: 0.0,
            max: 10.0,
        },
        ParamSpec {
            name: "min_segment_m2",
            description: "smaller segments merge into a neighbour, square metres",
            default: crate::segment::DEFAULT_MIN_SEGMENT_M2,
            min: 0.0,
            max: 10_000.0,
        },
    ],
    build: |c| {
        Box::new(SegmentationPolicy {
            switch_margin: c.get("switch_margin"),
            inside_discount: c.get("inside_discount"),
            min_drop_m: c.get("min_drop_m"),
            min_segment_m2: c.get("min_segment_m2"),
        })
    },
};

/// Wurm et al. 2008, Algorithm 1.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SegmentationPolicy {
    /// Hysteresis: the segment and the cell of a robot's current target cost it this much less, metres.
    pub switch_margin: f64,
    /// Factor on a segment's cost for a robot inside it (line 4).
    pub inside_discount: f64,
    /// How far a critical point's clearance lies below both sides, metres.
    pub min_drop_m: f64,
    /// Smaller segments merge into a neighbour, square metres.
    pub min_segment_m2: f64,
}

/// Rounds of optimal assignment of `rows` to columns: each round gives every
/// column to at most one waiting row; rows left over wait for the next.
fn assign_in_rounds(costs: &[Vec<f64>], columns: usize) -> Vec<Option<usize>> {
    let mut result = vec![None; costs.len()];
    loop {
        let waiting: Vec<usize> =
            (0..costs.len()).filter(|&i| result[i].is_none() && costs[i].iter().any(|c| c.is_finite())).collect();
        if waiting.is_empty() || columns == 0 {
            return result;
        }
        let matrix: Vec<f64> = waiting.iter().flat_map(|&i| costs[i].iter().copied()).collect();
        let Ok(solution) = assign_with_dummies(&matrix, waiting.len(), columns) else {
            return result;
        };
        let mut progressed = false;
        for (row, col) in solution.row_to_col.iter().enumerate() {
            if let Some(c) = col {
                result[waiting[row]] = Some(*c);
                progressed = true;
            }
        }
        if !progressed {
            return result;
        }
    }
}

impl Policy for SegmentationPolicy {
    fn name(&self) -> &'static str {
        NAME
    }

    fn keeps_segmentation(&self) -> bool {
        true
    }

    fn plan(&self, input: &PlanningInput<'_>, costs: &mut CostCache<'_>) -> Plan {
        let grid = input.grid;
        let resolution = grid.frame().resolution;
        let frontier = input.frontier_cells();
        // Line 1–2: segments and their frontier targets.
        let segmentation = input.rooms.and_then(|rooms| given(grid, rooms, &frontier)).unwrap_or_else(|| {
            segment(
                grid,
                &frontier,
                self.min_drop_m / resolution,
                (self.min_segment_m2 / (resolution * resolution)).ceil() as usize,
            )
        });
        let open: Vec<&Segment> = segmentation.segments.iter().filter(|s| !s.frontier.is_empty()).collect();
        let reach = Reach::new(input, costs, &open);
        // Lines 3–4: C_s^i, infinite where robot i cannot reach segment s (Eq. 4).
        let segment_costs: Vec<Vec<f64>> = input
            .robots
            .iter()
            .enumerate()
            .map(|(i, robot)| {
                let home = segmentation.segment_of(robot.cell);
                let current = current_target(robot);
                let target_segment = current.and_then(|c| segmentation.segment_of(c));
                open.iter()
                    .enumerate()
                    .map(|(k, s)| {
                        let nearest = reach.nearest(i, robot, k, s);
                        let inside = if home == Some(s.id) { nearest * self.inside_discount } else { nearest };
                        if target_segment == Some(s.id) { inside - self.switch_margin } else { inside }
                    })
                    .collect()
            })
            .collect();
        // Line 5: robots to segments.
        let chosen = assign_in_rounds(&segment_costs, open.len());
        // Lines 6–8: within each segment, its robots to its frontier cells,
        // each robot's costs to its segment's cells computed in parallel.
        let everyone: Vec<usize> = (0..input.robots.len()).collect();
        let path_costs: Vec<Vec<f64>> = in_parallel(&everyone, input.workers, |&i| match chosen[i] {
            Some(k) => reach.to_cells(i, &input.robots[i], k, &open[k].frontier),
            None => Vec::new(),
        });
        let mut targets: Vec<Option<Target>> = vec![None; input.robots.len()];
        for (k, s) in open.iter().enumerate() {
            let robots: Vec<usize> = (0..chosen.len()).filter(|&i| chosen[i] == Some(k)).collect();
            if robots.is_empty() {
                continue;
            }
            let cell_costs: Vec<Vec<f64>> = robots
                .iter()
                .map(|&i| {
                    let current = current_target(&input.robots[i]);
                    s.frontier
                        .iter()
                        .zip(&path_costs[i])
                        .map(|(&c, &cost)| if Some(c) == current { cost - self.switch_margin } else { cost })
                        .collect()
                })
                .collect();
            let within = assign_in_rounds(&cell_costs, s.frontier.len());
            for (row, col) in within.iter().enumerate() {
                let i = robots[row];
                if let Some(c) = col {
                    targets[i] = Some(Target {
                        cell: s.frontier[*c],
                        utility: -segment_costs[i][k],
                        path_cost: path_costs[i][*c],
                        gain_region: None,
                    });
                }
            }
        }
        Plan { targets, segmentation: Some(segmentation) }
    }
}

/// What reaching the open segments and their frontier cells costs the robots.
enum Reach {
    /// Each robot's complete cost map.
    Own(Vec<Arc<CostMap>>),
    /// One search from each open segment's frontier cells, when there are
    /// fewer segments than robots, the robots share one footprint and none
    /// has cells it must not be sent to. On free space a path reversed
    /// costs the same, so a segment's search gives every robot C_s^i (to
    /// rounding: the steps are added in the other order), as a cluster's
    /// wavefront does for MinPos (Bautin et al. 2011); and it orders each
    /// robot's search towards its segment's cells (lines 6–8).
    FromSegments { traversal: Arc<TraversalMap>, goals: Vec<GoalDistance> },
}

impl Reach {
    fn new(input: &PlanningInput<'_>, costs: &mut CostCache<'_>, open: &[&Segment]) -> Self {
        let kinds: Vec<TraversalKind> = input.robots.iter().map(RobotView::free_space).collect();
        let one_kind = kinds.windows(2).all(|w| w[0] == w[1]);
        if let Some(&kind) = kinds.first().filter(|_| one_kind && open.len() < input.robots.len()) {
            let traversal = costs.traversal(kind);
            let plain = |r: &RobotView| r.excluded.is_empty() && traversal.starts_inside(r.cell);
            if input.robots.iter().all(plain) {
                let goals = in_parallel(open, input.workers, |s| GoalDistance::new(&traversal, &s.frontier));
                return Self::FromSegments { traversal, goals };
            }
        }
        Self::Own(free_space_cost_maps(input, costs))
    }

    /// C_s^i (line 3): robot `i`'s cost to the nearest frontier cell of
    /// `segment` (the `k`-th open one); infinite where it cannot reach it.
    fn nearest(&self, i: usize, robot: &RobotView, k: usize, segment: &Segment) -> f64 {
        match self {
            Self::Own(maps) => {
                segment.frontier.iter().filter_map(|&c| robot.cost_to(&maps[i], c)).fold(f64::INFINITY, f64::min)
            }
            Self::FromSegments { traversal, goals } => goals[k].cost(traversal, robot.cell).unwrap_or(f64::INFINITY),
        }
    }

    /// Robot `i`'s path cost to each of `cells`, the frontier of the `k`-th
    /// open segment; infinite where it cannot go or must not be sent.
    fn to_cells(&self, i: usize, robot: &RobotView, k: usize, cells: &[Cell]) -> Vec<f64> {
        match self {
            Self::Own(maps) => cells.iter().map(|&c| robot.cost_to(&maps[i], c).unwrap_or(f64::INFINITY)).collect(),
            Self::FromSegments { traversal, goals } => {
                let mut search = GrowingCostMap::towards(traversal, robot.cell, &goals[k]);
                search.grow_to_reach(cells);
                cells.iter().map(|&c| search.cost(c).unwrap_or(f64::INFINITY)).collect()
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::grid::Cell;
    use crate::grid::testing::grid_from_picture;
    use crate::policy::Greedy;
    use crate::policy::testing::{plan_targets, plan_with_defaults, robot, with_input};

    /// Wurm et al. 2008, §V: two robots in a corridor, two rooms off it. Room
    /// A has two frontiers (a pillar splits its unexplored part), so the
    /// frontier-based greedy assignment sends both robots into A; segment by
    /// segment, one robot goes to each room.
    #[test]
    fn two_robots_two_rooms_one_robot_per_room() {
        let grid = grid_from_picture(&[
            "#######################", //
            "#???#???#####?????????#", //
            "#???#???#####?????????#", //
            "#...#...#####.........#", //
            "#.......#####.........#", //
            "#.......#####.........#", //
            "#.......#####.........#", //
            "####.##########.#######", //
            "#.....................#", //
            "#.....................#", //
            "#.....................#", //
            "#######################", //
        ]);
        let in_room_a = |c: Cell| c.x < 8 && c.y >= 4;
        let in_room_b = |c: Cell| c.x > 12 && c.y >= 4;
        let robots = [robot(0, Cell::new(3, 2), 3.0), robot(1, Cell::new(5, 2), 3.0)];
        let greedy = plan_targets(&Greedy::default(), &grid, &robots);
        assert!(greedy.iter().all(|t| t.is_some_and(in_room_a)), "greedy: {greedy:?}");
        let nearest = plan_with_defaults("nearest", &grid, &robots);
        assert!(nearest.iter().all(|t| t.is_some_and(in_room_a)), "nearest: {nearest:?}");
        let policy =
            SegmentationPolicy { switch_margin: 0.0, inside_discount: 0.5, min_drop_m: 0.5, min_segment_m2: 1.0 };
        let targets = plan_targets(&policy, &grid, &robots);
        let a = targets.iter().filter(|t| t.is_some_and(in_room_a)).count();
        let b = targets.iter().filter(|t| t.is_some_and(in_room_b)).count();
        assert_eq!((a, b), (1, 1), "segmentation: {targets:?}");
    }

    /// Wurm et al. 2008, §VI: with rooms given, a hall the online
    /// segmentation cannot cut (no narrow passage) is two rooms, and the
    /// robots split between them; online, and under `nearest`, both take
    /// the near end.
    #[test]
    fn given_rooms_split_a_hall_the_online_segmentation_cannot() {
        let grid = grid_from_picture(&[
            "######################", //
            "?....................?", //
            "?....................?", //
            "######################", //
        ]);
        let robots = [robot(0, Cell::new(3, 1), 1.0), robot(1, Cell::new(4, 2), 1.0)];
        let frame = *grid.frame();
        let rooms: Vec<u32> = (0..frame.len()).map(|i| if frame.cell(i).x < 11 { 1 } else { 2 }).collect();
        let policy =
            SegmentationPolicy { switch_margin: 0.0, inside_discount: 0.5, min_drop_m: 0.5, min_segment_m2: 1.0 };
        let far_end = |t: &Option<Cell>| t.is_some_and(|c| c.x > 11);
        let online = plan_targets(&policy, &grid, &robots);
        assert_eq!(online.iter().filter(|t| far_end(t)).count(), 0, "online: {online:?}");
        let nearest = plan_with_defaults("nearest", &grid, &robots);
        assert_eq!(nearest.iter().filter(|t| far_end(t)).count(), 0, "nearest: {nearest:?}");
        let plan = with_input(&grid, &robots, &[Vec::new(), Vec::new()], |input| {
            policy.plan(&PlanningInput { rooms: Some(&rooms), ..*input }, &mut CostCache::new(&grid))
        });
        let targets: Vec<Option<Cell>> = plan.targets.iter().map(|t| t.map(|t| t.cell)).collect();
        assert_eq!(targets.iter().filter(|t| far_end(t)).count(), 1, "given rooms: {targets:?}");
        let segmentation = plan.segmentation.expect("the plan keeps its segmentation");
        assert_eq!(segmentation.segments.len(), 2);
        assert!(segmentation.critical_points.is_empty());
    }

    proptest::proptest! {
        #![proptest_config(crate::testing::seeded_proptest(256))]
        /// Searching from the segments gives each robot the segment costs
        /// of its own complete cost map (to rounding) and exactly its costs
        /// to the cells of a segment, over random rooms, walls and teams.
        #[test]
        fn searches_from_segments_cost_what_the_robots_own_searches_do(
            width in 4u32..30,
            height in 4u32..30,
            seed in 0u64..1_000_000,
            robots in 1usize..6,
        ) {
            use crate::policy::testing::{random_team, random_walled_rectangle};
            use crate::rng::SplitMix64;

            let mut rng = SplitMix64::new(seed);
            let (grid, free) = random_walled_rectangle(width, height, &mut rng);
            proptest::prop_assume!(!free.is_empty());
            let team = random_team(robots, &free, &free, false, &mut rng);
            let frontier = with_input(&grid, &team, &[], |input| input.frontier_cells());
            let segmentation = segment(&grid, &frontier, 1.0, 4);
            let open: Vec<&Segment> = segmentation.segments.iter().filter(|s| !s.frontier.is_empty()).collect();
            let mut costs = CostCache::new(&grid);
            let traversal = costs.traversal(TraversalKind::free_space(team[0].capabilities.footprint_radius_m));
            proptest::prop_assume!(team.iter().all(|r| traversal.starts_inside(r.cell)));
            let goals = open.iter().map(|s| GoalDistance::new(&traversal, &s.frontier)).collect();
            let from_segments = Reach::FromSegments { traversal, goals };
            let own = Reach::Own(with_input(&grid, &team, &[], |input| free_space_cost_maps(input, &mut costs)));
            for (i, robot) in team.iter().enumerate() {
                for (k, s) in open.iter().enumerate() {
                    let (a, b) = (from_segments.nearest(i, robot, k, s), own.nearest(i, robot, k, s));
                    proptest::prop_assert!(a == b || (a - b).abs() < 1e-4, "robot {} segment {}: {} vs {}", i, k, a, b);
                    proptest::prop_assert_eq!(
                        from_segments.to_cells(i, robot, k, &s.frontier),
                        own.to_cells(i, robot, k, &s.frontier)
                    );
                }
            }
        }
    }
}
