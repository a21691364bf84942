//! How few steps any policy could take: a lower bound on a run's steps to
//! full coverage that holds whatever the executive decides, so that a
//! policy's steps can be read against what is possible, not only against
//! the other policies.
//!
//! What the simulator lets a robot do bounds it three ways
//! (`robot::SimRobot::step` and `exploration::visibility`); below, `r` is
//! the range in whole cells:
//!
//! - **Travel.** A robot makes at most `speed / REFERENCE_SPEED_MPS` moves a
//!   step, each to one of the eight neighbouring free cells, and senses a
//!   cell only from where the cell's centre lies within its range `r` (in
//!   cells) along a ray of free cells. Such a ray is a digital straight line,
//!   so a king's walk of at most max(|dx|, |dy|) ≤ r moves leads along it
//!   from the robot to the cell. Hence a robot that senses cell `c` has
//!   moved at least d(S, c) − r, where d is the king-move distance over the
//!   free cells (corners may be cut: a superset of the robots' moves) from
//!   the team's start cells S, and a run lasts at least
//!   max over reachable c of ⌈(d(S, c) − r) / speed⌉ steps.
//! - **Pairs** (pigeonhole): of n + 1 cells, some robot of n must sense two,
//!   c_i and then c_j, and so moves at least min(d(S, c_i), d(S, c_j)) +
//!   d(c_i, c_j) − 3r. The least of that over every pair bounds the run; the
//!   cells are picked far from the start and from each other (farthest
//!   points first). One robot in a corridor started in its middle must see
//!   both ends: this is exactly its best walk.
//! - **Sweep.** Standing on a cell a robot senses at most the |D| cells of
//!   its range disc; each move adds at most N cells to what it has swept,
//!   the most a disc gains by a move to a neighbour. So n robots need at
//!   least (R − n·|D|) / (n · N · speed) steps to sense R reachable cells.
//!   Walls cast shadows, so this is far from tight; it matters only for
//!   small teams on open maps.
//!
//! The travel bound is the time for the news of the farthest corner to
//! reach the team, with every robot heading for it at once. The larger the
//! team, the nearer the policies come to it: on the held-back maps of issue
//! 14 the best of them take 2.5 times it with 2 robots, 1.4 times with 16.

use std::collections::{BTreeMap, VecDeque};
use std::path::Path;

use exploration::grid::Cell;

use crate::experiment::{Experiment, RunSpec, matrix, run_config};
use crate::robot::{REFERENCE_SPEED_MPS, RobotModel};
use crate::runs::Row;
use crate::world::World;

/// A lower bound on the steps to full coverage, both ways.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct StepsBound {
    /// The farthest reachable cell's distance from the team, less the
    /// sensor's range, over the speed.
    pub travel: u64,
    /// Some robot must sense two of n + 1 cells far apart.
    pub pairs: u64,
    /// The reachable cells over what the team can sweep a step.
    pub sweep: u64,
}

impl StepsBound {
    /// The largest of the three: fewer steps are impossible.
    pub fn steps(&self) -> u64 {
        self.travel.max(self.pairs).max(self.sweep)
    }
}

/// The bound for a team starting on `starts` whose robots have `models`
/// (the best sensor range and speed among them are taken for every robot,
/// which keeps it a bound).
pub fn steps_lower_bound(world: &World, starts: &[Cell], models: &[RobotModel]) -> StepsBound {
    let range = models.iter().map(|m| m.sensor_range_m).fold(0.0, f64::max) / world.frame.resolution;
    let moves_per_step = models.iter().map(|m| m.speed_mps).fold(0.0, f64::max) / REFERENCE_SPEED_MPS;
    if starts.is_empty() || moves_per_step <= 0.0 {
        return StepsBound { travel: u64::MAX, pairs: u64::MAX, sweep: u64::MAX };
    }
    // A sensed cell is at most this many king moves from the robot.
    let reach = range.max(0.0).floor();
    let from_start = king_distances(world, starts);
    StepsBound {
        travel: travel_bound(world, &from_start, reach, moves_per_step),
        pairs: pairs_bound(world, &from_start, starts.len() + 1, reach, moves_per_step),
        sweep: sweep_bound(world.reachable_cells, starts.len(), range, moves_per_step),
    }
}

/// ⌈(max over reachable c of d(S, c) − reach) / moves_per_step⌉, with d the
/// king-move distance over the free cells (`from_start`).
fn travel_bound(world: &World, from_start: &[u32], reach: f64, moves_per_step: f64) -> u64 {
    let farthest = reachable_distances(world, from_start).map(|(_, d)| d).max().unwrap_or(0);
    steps_for(f64::from(farthest) - reach, moves_per_step)
}

/// The pigeonhole bound over `points` cells picked farthest first (see the
/// module).
fn pairs_bound(world: &World, from_start: &[u32], points: usize, reach: f64, moves_per_step: f64) -> u64 {
    let mut nearest_centre = from_start.to_vec();
    let mut picked: Vec<(usize, Vec<u32>)> = Vec::with_capacity(points);
    while picked.len() < points {
        let Some((far, _)) = reachable_distances(world, &nearest_centre).max_by_key(|&(i, d)| (d, usize::MAX - i))
        else {
            break;
        };
        let from_far = king_distances(world, &[world.frame.cell(far)]);
        for (m, &d) in nearest_centre.iter_mut().zip(&from_far) {
            *m = (*m).min(d);
        }
        picked.push((far, from_far));
    }
    let mut least = None::<u32>;
    for (k, (i, from_i)) in picked.iter().enumerate() {
        for (j, _) in &picked[k + 1..] {
            let moves = from_start[*i].min(from_start[*j]).saturating_add(from_i[*j]);
            least = Some(least.map_or(moves, |l| l.min(moves)));
        }
    }
    // Fewer reachable cells than points: no pair is forced.
    if picked.len() < points {
        return 0;
    }
    least.map_or(0, |moves| steps_for(f64::from(moves) - 3.0 * reach, moves_per_step))
}

/// The reachable cells' indices with their finite `distance`.
fn reachable_distances<'a>(world: &'a World, distance: &'a [u32]) -> impl Iterator<Item = (usize, u32)> + 'a {
    (0..world.frame.len()).filter(|&i| world.reachable[i] && distance[i] != u32::MAX).map(|i| (i, distance[i]))
}

/// Breadth-first king-move distances from `starts` over the cells that are
/// not blocked, corners cut; `u32::MAX` where none leads.
fn king_distances(world: &World, starts: &[Cell]) -> Vec<u32> {
    let frame = world.frame;
    let mut distance = vec![u32::MAX; frame.len()];
    let mut queue = VecDeque::new();
    for &start in starts.iter().filter(|&&c| !world.is_blocked(c)) {
        distance[frame.index(start)] = 0;
        queue.push_back(start);
    }
    while let Some(cell) = queue.pop_front() {
        let next = distance[frame.index(cell)] + 1;
        for (dx, dy) in [(1, 0), (-1, 0), (0, 1), (0, -1), (1, 1), (1, -1), (-1, 1), (-1, -1)] {
            let n = Cell::new(cell.x + dx, cell.y + dy);
            if !world.is_blocked(n) && distance[frame.index(n)] == u32::MAX {
                distance[frame.index(n)] = next;
                queue.push_back(n);
            }
        }
    }
    distance
}

/// ⌈(reachable − robots·|D|) / (robots · N · moves_per_step)⌉: |D| the cells
/// whose centres lie within `range` of a cell's centre (the sensor's test),
/// N the most of them a move to a neighbour adds.
fn sweep_bound(reachable: usize, robots: usize, range: f64, moves_per_step: f64) -> u64 {
    let disc = disc(range);
    let at_start = (robots * disc.len()) as f64;
    let gained = [(1, 0), (1, 1)]
        .iter()
        .map(|&(dx, dy)| disc.iter().filter(|&&(x, y)| !inside(x - dx, y - dy, range)).count())
        .max()
        .unwrap_or(0)
        .max(1);
    steps_for((reachable as f64 - at_start) / (robots * gained) as f64, moves_per_step)
}

/// The offsets of the cells whose centres lie within `range` of the origin's.
fn disc(range: f64) -> Vec<(i64, i64)> {
    let r = range.max(0.0).floor() as i64;
    (-r..=r).flat_map(|y| (-r..=r).map(move |x| (x, y))).filter(|&(x, y)| inside(x, y, range)).collect()
}

fn inside(x: i64, y: i64, range: f64) -> bool {
    ((x * x + y * y) as f64) <= range * range
}

/// Steps needed to make `moves` moves at `moves_per_step`, at least 0.
fn steps_for(moves: f64, moves_per_step: f64) -> u64 {
    if moves <= 0.0 { 0 } else { (moves / moves_per_step - 1e-9).ceil() as u64 }
}

/// The bound of one cell of an experiment's matrix: a world, a team size, a
/// communication range and a seed (every policy starts there alike).
#[derive(Debug, Clone, PartialEq)]
pub struct CellBound {
    /// The run of the first policy in the cell, for its world, size, range and seed.
    pub run: RunSpec,
    /// Its bound.
    pub bound: StepsBound,
}

/// The bound of every cell of `experiment`'s matrix (`config_dir` holds its
/// file, for maps given relative to it), built as the runs build their
/// worlds and teams.
pub fn matrix_bounds(experiment: &Experiment, config_dir: &Path) -> Result<Vec<CellBound>, String> {
    let mut cells: BTreeMap<(String, usize, String, u64), RunSpec> = BTreeMap::new();
    for run in matrix(experiment) {
        cells.entry((run.world.clone(), run.robots, run.comm.clone(), run.seed)).or_insert(run);
    }
    cells
        .into_values()
        .map(|run| {
            let config = run_config(experiment, config_dir, &run, None)?;
            let world = config
                .world
                .build(config.cell_size, config.start, config.seed)
                .map_err(|e| format!("{}: {e}", run.world))?;
            let starts = crate::fleet::start_cells(&world, &config);
            Ok(CellBound { bound: steps_lower_bound(&world, &starts, &config.models), run })
        })
        .collect()
}

/// One policy's steps against the bound, over the cells of one team size
/// where its run explored the whole map.
#[derive(Debug, Clone, PartialEq)]
pub struct AgainstBound {
    /// Policy label.
    pub label: String,
    /// Team size.
    pub robots: usize,
    /// Completed runs counted.
    pub runs: usize,
    /// Their mean steps.
    pub mean_steps: f64,
    /// The mean bound of their cells.
    pub mean_bound: f64,
}

/// Each label's completed runs in `runs` (rows of `runs.csv`) against the
/// bounds of their cells, by team size.
pub fn against_runs(bounds: &[CellBound], runs: &[Row]) -> Vec<AgainstBound> {
    let bound_of: BTreeMap<(&str, usize, &str, u64), u64> = bounds
        .iter()
        .map(|c| ((c.run.world.as_str(), c.run.robots, c.run.comm.as_str(), c.run.seed), c.bound.steps()))
        .collect();
    let mut sums: BTreeMap<(String, usize), (usize, f64, f64)> = BTreeMap::new();
    for row in runs {
        let field = |name: &str| row.get(name).map_or("", String::as_str);
        if field("status") != "ok" || field("completed") != "true" {
            continue;
        }
        let (Ok(robots), Ok(seed), Ok(steps)) =
            (field("robots").parse::<usize>(), field("seed").parse::<u64>(), field("steps").parse::<f64>())
        else {
            continue;
        };
        let Some(&bound) = bound_of.get(&(field("world"), robots, field("comm_range"), seed)) else { continue };
        let sum = sums.entry((field("label").to_owned(), robots)).or_default();
        *sum = (sum.0 + 1, sum.1 + steps, sum.2 + bound as f64);
    }
    sums.into_iter()
        .map(|((label, robots), (n, steps, bound))| AgainstBound {
            label,
            robots,
            runs: n,
            mean_steps: steps / n as f64,
            mean_bound: bound / n as f64,
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::fleet::DEFAULT_MODEL;
    use crate::world::StartChoice;
    use exploration::math::Point2;

    fn corridor(length: u32) -> World {
        // One row of free cells between two rows of wall.
        let (width, height) = (length, 3);
        let blocked: Vec<bool> = (0..width * height).map(|i| i / width != 1).collect();
        let frame = exploration::grid::GridFrame::new(1.0, Point2::new(0.0, 0.0), width, height);
        World::from_blocked("corridor", frame, blocked, StartChoice::At(Point2::new(0.5, 1.5)), 1).unwrap()
    }

    #[test]
    fn a_corridor_takes_its_length_less_the_range() {
        let world = corridor(40);
        let model = RobotModel { sensor_range_m: 5.0, speed_mps: REFERENCE_SPEED_MPS, ..DEFAULT_MODEL };
        let bound = steps_lower_bound(&world, &[world.start], &[model]);
        // The far end is 39 moves away; seen from 5 cells short of it.
        assert_eq!(bound.travel, 34);
        // A pair forces nothing more here: the start is at one end.
        assert!(bound.pairs <= 34 && bound.steps() == 34, "{bound:?}");
        // Twice the speed, half the steps.
        let fast = RobotModel { speed_mps: 2.0 * REFERENCE_SPEED_MPS, ..model };
        assert_eq!(steps_lower_bound(&world, &[world.start], &[fast]).travel, 17);
    }

    #[test]
    fn the_bound_is_what_a_robot_that_goes_straight_for_the_end_takes() {
        // A robot walking the corridor senses the far end first at step 34
        // (range 5): the bound is reached, so it cannot be raised.
        let world = corridor(40);
        let range = 5.0;
        let sensor = exploration::visibility::RangeSensor { range_cells: range, field_of_view: std::f64::consts::TAU };
        let far_end = Cell::new(39, 1);
        let first_seen = (0..40)
            .find(|&step| {
                let mut seen = false;
                sensor.scan(Cell::new(step, 1), 0.0, |c| world.is_blocked(c), |c, _| seen |= c == far_end);
                seen
            })
            .unwrap();
        let model = RobotModel { sensor_range_m: range, speed_mps: REFERENCE_SPEED_MPS, ..DEFAULT_MODEL };
        assert_eq!(steps_lower_bound(&world, &[world.start], &[model]).travel, first_seen as u64);
    }

    #[test]
    fn one_robot_in_the_middle_of_a_corridor_must_see_both_ends() {
        // 41 cells, the robot on the 21st, range 5: its best walk goes 15
        // moves towards one end, until it sees it, then 30 back until it sees
        // the other: 45 steps. Each end alone is only 15 away.
        let frame = exploration::grid::GridFrame::new(1.0, Point2::new(0.0, 0.0), 41, 3);
        let blocked: Vec<bool> = (0..41 * 3).map(|i| i / 41 != 1).collect();
        let world =
            World::from_blocked("corridor", frame, blocked, StartChoice::At(Point2::new(20.5, 1.5)), 1).unwrap();
        let model = RobotModel { sensor_range_m: 5.0, speed_mps: REFERENCE_SPEED_MPS, ..DEFAULT_MODEL };
        let bound = steps_lower_bound(&world, &[world.start], &[model]);
        assert_eq!((bound.travel, bound.pairs, bound.steps()), (15, 45, 45));
        // Two robots, one per end: no pair is forced on one robot, and the
        // pair bound falls to what the travel bound says.
        let both = steps_lower_bound(&world, &[world.start, Cell::new(19, 1)], &[model]);
        assert!(both.pairs <= 16 && both.steps() >= 15, "{both:?}");
    }

    #[test]
    fn the_sweep_bound_counts_the_cells_a_move_can_add() {
        // Range 1: the disc is the cell and its four neighbours; a move,
        // straight or diagonal, adds 3 cells.
        assert_eq!(disc(1.0).len(), 5);
        // 1 000 cells, one robot: (1 000 − 5) / 3 moves, rounded up.
        assert_eq!(sweep_bound(1_000, 1, 1.0, 1.0), 332);
        // Two robots share them: (1 000 − 10) / 6.
        assert_eq!(sweep_bound(1_000, 2, 1.0, 1.0), 165);
        // Range 3: 29 cells; a straight move adds 7, a diagonal 9.
        assert_eq!(disc(3.0).len(), 29);
        assert_eq!(sweep_bound(929, 1, 3.0, 1.0), 100);
    }

    #[test]
    fn policies_are_held_against_the_bounds_of_the_cells_they_completed() {
        let cell = |robots: usize, seed: u64, steps: u64| CellBound {
            run: RunSpec {
                id: String::new(),
                world: "w".into(),
                label: "a".into(),
                robots,
                comm: "unlimited".into(),
                seed,
            },
            bound: StepsBound { travel: steps, pairs: 0, sweep: 0 },
        };
        let bounds = [cell(2, 1, 100), cell(2, 2, 200), cell(4, 1, 50)];
        let row = |label: &str, robots: usize, seed: u64, steps: u64, completed: bool| -> Row {
            [
                ("world", "w".to_owned()),
                ("label", label.to_owned()),
                ("robots", robots.to_string()),
                ("comm_range", "unlimited".to_owned()),
                ("seed", seed.to_string()),
                ("steps", steps.to_string()),
                ("status", "ok".to_owned()),
                ("completed", completed.to_string()),
            ]
            .into_iter()
            .map(|(k, v)| (k.to_owned(), v))
            .collect()
        };
        let runs = [
            row("a", 2, 1, 120, true),
            row("a", 2, 2, 260, true),
            row("a", 4, 1, 80, false), // not completed: left out
            row("b", 2, 2, 300, true),
        ];
        let against = against_runs(&bounds, &runs);
        let a = AgainstBound { label: "a".into(), robots: 2, runs: 2, mean_steps: 190.0, mean_bound: 150.0 };
        // b is held against the bound of the one cell it completed.
        let b = AgainstBound { label: "b".into(), robots: 2, runs: 1, mean_steps: 300.0, mean_bound: 200.0 };
        assert_eq!(against, vec![a, b]);
    }

    #[test]
    fn no_start_no_bound_to_speak_of() {
        let world = corridor(10);
        assert_eq!(steps_lower_bound(&world, &[], &[DEFAULT_MODEL]).steps(), u64::MAX);
    }
}
