//! The step loop of a run: in each step the robots, in a fixed order, hear
//! who is in range, move, sense, report and adopt what the executive
//! answers; after each step the run records its coverage and decides
//! whether to go on.

use std::collections::BTreeMap;
use std::time::{Duration, Instant};

use exploration::grid::Cell;
use exploration::rng::SplitMix64;

use super::{FromExecutive, RunConfig, RunReport, SimError};
use crate::robot::{Occupancy, SimRobot, TeamMap};
use crate::world::World;

/// Coverage levels of the milestones t50, t90, t95, t100.
const LEVELS: [f64; 4] = [0.5, 0.9, 0.95, 1.0];

/// What a run has measured so far, and the state the loop carries.
pub(super) struct Exploration {
    /// What the whole team knows.
    pub(super) team: TeamMap,
    /// Interference draws.
    rng: SplitMix64,
    /// Communication range in cells, when limited.
    range_cells: Option<f64>,
    /// Steps at which each coverage level was reached.
    milestones: [Option<u64>; 4],
    /// Coverage after each step.
    curve: Vec<f32>,
    /// Consecutive steps in which no robot had a task.
    idle_run: u64,
    /// Robot-steps without a task.
    idle_total: u64,
    /// The most cells known so far, and the step it was reached.
    last_progress: (usize, u64),
    /// The current step, from 0.
    step: u64,
}

/// What one step of the team came to.
#[derive(Default)]
struct StepOutcome {
    any_task: bool,
    executive_done: bool,
}

impl Exploration {
    pub(super) fn new(config: &RunConfig, world: &World) -> Self {
        Self {
            team: TeamMap::new(world.frame),
            rng: SplitMix64::new(config.seed ^ 0x494E_5445_5246),
            range_cells: config.comm_range.map(|r| r.metres(world) / world.frame.resolution),
            milestones: [None; 4],
            curve: Vec::new(),
            idle_run: 0,
            idle_total: 0,
            last_progress: (0, 0),
            step: 0,
        }
    }

    /// Steps the team until the run ends; returns why it ended.
    pub(super) async fn run(
        &mut self,
        robots: &mut [SimRobot],
        world: &World,
        config: &RunConfig,
        clock: Option<&coordinator::ManualClock>,
    ) -> Result<String, SimError> {
        loop {
            let outcome = self.step_team(robots, world, config).await?;
            let known = self.known(robots);
            self.record(known, world, config);
            if let Some(ended) = self.stop_reason(known, world, config, &outcome) {
                return Ok(ended);
            }
            self.step += 1;
            tick(clock, &world.frame).await;
            if let Some(pace) = config.pace {
                tokio::time::sleep(pace).await;
            }
            if self.step >= config.max_steps {
                return Ok(format!("step limit {} reached", config.max_steps));
            }
        }
    }

    /// Cells known: by the team, or under limited communication by the
    /// robot that knows most (Burgard et al. 2005 §IV-D).
    fn known(&self, robots: &[SimRobot]) -> usize {
        if self.range_cells.is_some() {
            robots.iter().map(|r| r.known_reachable).max().unwrap_or(0)
        } else {
            self.team.known_reachable
        }
    }

    /// One step of every robot, in order.
    async fn step_team(
        &mut self,
        robots: &mut [SimRobot],
        world: &World,
        config: &RunConfig,
    ) -> Result<StepOutcome, SimError> {
        // Limited communication: who is in range, and what they pass on.
        let clusters = self.range_cells.map(|range| communication_clusters(robots, range)).unwrap_or_default();
        let mut cluster_of = vec![None; robots.len()];
        for (c, cluster) in clusters.iter().enumerate() {
            for &k in cluster {
                cluster_of[k] = Some(c);
                gather(robots, cluster, k, world);
            }
        }
        for cluster in &clusters {
            let ids: Vec<u64> = cluster.iter().map(|&k| robots[k].id).collect();
            for &k in cluster {
                let peers = ids.iter().copied().filter(|id| *id != robots[k].id).collect();
                robots[k].hear_peers(peers, world, &self.team).await?;
            }
        }
        let mut outcome = StepOutcome::default();
        let cells: Vec<Cell> = robots.iter().map(|r| r.cell).collect();
        let mut occupied = Occupancy::of(cells.iter().copied());
        for i in 0..robots.len() {
            let robot = &mut robots[i];
            // Interference: a move near another robot succeeds with probability p.
            let blocked = config.interference.is_some_and(|f| {
                let near = cells
                    .iter()
                    .enumerate()
                    .any(|(j, c)| j != i && c.distance(robot.cell) * world.frame.resolution <= f.radius_m);
                near && !self.rng.chance(f.success)
            });
            let stepped = robot.step(world, &mut self.team, blocked, &mut occupied).await?;
            // Robots in range talk all the time: what one senses reaches its
            // sub-team at once, before any of them plans on its own map (the
            // executive plans the sub-team on the map they share), even one
            // that leaves the range before its next step.
            if let Some(c) = cluster_of[i] {
                scatter(robots, &clusters[c], i, world);
            }
            outcome.any_task |= stepped.has_task;
            if !stepped.has_task {
                self.idle_total += 1;
            }
            outcome.executive_done |= stepped.mission_completed;
        }
        Ok(outcome)
    }

    /// Coverage after this step, and the milestones it reached.
    fn record(&mut self, known: usize, world: &World, config: &RunConfig) {
        let coverage = known as f64 / world.reachable_cells.max(1) as f64;
        self.curve.push(coverage as f32);
        for (slot, level) in self.milestones.iter_mut().zip(LEVELS) {
            // On the base of `steps`: the number of steps taken when reached.
            if slot.is_none() && coverage >= level - 1e-12 {
                *slot = Some(self.step + 1);
            }
        }
        if config.progress && self.step.is_multiple_of(250) {
            crate::errln!("step {:>6}  coverage {:>5.1} %", self.step, 100.0 * coverage);
        }
    }

    /// Why the run ends after this step, if it does.
    fn stop_reason(
        &mut self,
        known: usize,
        world: &World,
        config: &RunConfig,
        outcome: &StepOutcome,
    ) -> Option<String> {
        if known >= world.reachable_cells {
            return Some("every reachable free cell is known".to_owned());
        }
        if outcome.executive_done && self.range_cells.is_none() {
            return Some("the executive reports no frontier left".to_owned());
        }
        self.idle_run = if outcome.any_task { 0 } else { self.idle_run + 1 };
        if self.idle_run >= config.stall_steps {
            return Some(format!("no robot had a task for {} steps", self.idle_run));
        }
        if known > self.last_progress.0 {
            self.last_progress = (known, self.step);
        } else if self.step - self.last_progress.1 >= 10 * config.stall_steps {
            return Some(format!("the team learnt nothing for {} steps", self.step - self.last_progress.1));
        }
        None
    }

    /// The run's report.
    #[allow(clippy::too_many_arguments)]
    pub(super) fn report(
        self,
        config: &RunConfig,
        world: World,
        robots: &[SimRobot],
        mission_id: u64,
        ended: String,
        home_steps: Option<u64>,
        from_executive: FromExecutive,
        started: Instant,
    ) -> RunReport {
        let known = self.known(robots);
        let sensed = self.team.sensed_by.iter().filter(|&&n| n > 0).count();
        let overlapping = self.team.sensed_by.iter().filter(|&&n| n > 1).count();
        let resolution = world.frame.resolution;
        RunReport {
            mission_id,
            map: world.name.clone(),
            policy: config.policy.clone(),
            robots: config.robots,
            seed: config.seed,
            completed: known >= world.reachable_cells,
            ended,
            steps: self.step + 1,
            coverage: known as f64 / world.reachable_cells.max(1) as f64,
            t50: self.milestones[0],
            t90: self.milestones[1],
            t95: self.milestones[2],
            t100: self.milestones[3],
            distance_per_robot: robots.iter().map(|r| r.distance_m).collect(),
            idle_steps: self.idle_total,
            target_switches: robots.iter().map(|r| r.target_switches).sum(),
            replans: from_executive.summary.replans,
            map_updates: from_executive.summary.map_updates,
            updates_acknowledged: robots.iter().map(|r| r.acknowledged_updates).sum(),
            reachable_cells: world.reachable_cells,
            cell_size: resolution,
            comm_range_m: self.range_cells.map(|r| r * resolution),
            overlap: if sensed == 0 { 0.0 } else { overlapping as f64 / sensed as f64 },
            stream_lags: robots.iter().map(|r| r.stream_lags).sum(),
            wall_time_s: started.elapsed().as_secs_f64(),
            trajectories: robots.iter().map(|r| r.trajectory.clone()).collect(),
            coverage_curve: self.curve,
            world: Some(world),
            segments: from_executive.segments,
            fault_record: from_executive.fault_record,
            home_steps,
        }
    }
}

/// Gives robot `to` what the other robots of its cluster integrated and
/// have not sent it yet (Burgard et al. 2005 §III: each robot logs what it
/// sent each peer, so nothing is integrated twice).
fn gather(robots: &mut [SimRobot], cluster: &[usize], to: usize, world: &World) {
    for &from in cluster.iter().filter(|&&from| from != to) {
        let (sender, receiver) = if from < to {
            let (low, high) = robots.split_at_mut(to);
            (&mut low[from], &mut high[0])
        } else {
            let (low, high) = robots.split_at_mut(from);
            (&mut high[0], &mut low[to])
        };
        sender.share_with(receiver, to, world);
    }
}

/// Robot `from` passes what it knows to the rest of its cluster.
fn scatter(robots: &mut [SimRobot], cluster: &[usize], from: usize, world: &World) {
    for &to in cluster.iter().filter(|&&to| to != from) {
        gather(robots, &[from, to], to, world);
    }
}

/// Robots in range of each other, through any chain of robots in range
/// (the ad-hoc network forwards within a cluster, Burgard et al. §III).
fn communication_clusters(robots: &[SimRobot], range_cells: f64) -> Vec<Vec<usize>> {
    let n = robots.len();
    let mut cluster: Vec<usize> = (0..n).collect();
    fn root(c: &mut [usize], mut k: usize) -> usize {
        while c[k] != k {
            c[k] = c[c[k]];
            k = c[k];
        }
        k
    }
    for i in 0..n {
        for j in i + 1..n {
            if robots[i].cell.distance(robots[j].cell) <= range_cells {
                let (a, b) = (root(&mut cluster, i), root(&mut cluster, j));
                cluster[a.max(b)] = a.min(b);
            }
        }
    }
    let mut groups: BTreeMap<usize, Vec<usize>> = BTreeMap::new();
    for i in 0..n {
        let r = root(&mut cluster, i);
        groups.entry(r).or_default().push(i);
    }
    groups.into_values().collect()
}

/// Moves the executive's simulated clock on by one step (the time a robot of
/// the reference speed takes for one cell), when it has one.
pub(super) async fn tick(clock: Option<&coordinator::ManualClock>, frame: &exploration::grid::GridFrame) {
    if let Some(clock) = clock {
        clock.step(Duration::from_secs_f64(frame.resolution / crate::robot::REFERENCE_SPEED_MPS)).await;
    }
}
