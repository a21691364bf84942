//! The snapshot a plan is made on and the policy run over it: a
//! [`PlanningJob`] copies what the policy reads out of the mission (the
//! robots in its pool, the map of each coordination scope, bids, forbidden
//! regions) so that it runs off the mission's lock, on the planner's
//! threads; its [`JobOutcome`] goes back to [`Mission::prepare_plan`].

use std::collections::BTreeMap;
use std::sync::Arc;

use exploration::cost::CostCache;
use exploration::frontier::{FrontierCluster, FrontierMap, clusters};
use exploration::grid::{Cell, CellRect, OccupancyGrid};
use exploration::policy::{Bid as PolicyBid, CurrentTask, Plan, PlanningInput, Policy, RobotView};
use exploration::workers::{Unpaced, Workers};

use super::{Mission, RobotSlot, lifecycle};
use crate::domain::{Leftover, Leftovers, RobotId, Rooms, TaskKind};
use crate::executive::planner::SharedPace;

/// Everything needed to run a policy off the mission's lock.
#[derive(Debug)]
pub(crate) struct PlanningJob {
    /// The robots in the policy's pool, in the mission's order: the plan's order.
    order: Vec<RobotId>,
    /// One part per coordination scope: the whole team, or each connected
    /// sub-team when the mission is scoped by communication.
    parts: Vec<PlanningPart>,
    /// Forbidden regions, in cells.
    forbidden: Vec<CellRect>,
    /// Blacklist entries found expired: the map around them changed.
    expired: Vec<(RobotId, Cell)>,
    min_frontier_size: usize,
    policy: Arc<dyn Policy>,
    /// The rooms given with the mission, if any.
    rooms: Option<Rooms>,
    /// No robot has sent a map yet: finding no frontier means nothing.
    nothing_known: bool,
    threads: usize,
    /// What holds its threads back (see `planner::budget`).
    pace: SharedPace,
    seed: u64,
}

/// What a planning job produced.
#[derive(Debug)]
pub(crate) struct JobOutcome {
    /// The robots planned for, in the order of `plan.targets`.
    pub(super) order: Vec<RobotId>,
    /// The targets that were frontier cells of the map the plan was made on.
    pub(super) frontier_targets: std::collections::HashSet<Cell>,
    /// Targets of the robots in the pool.
    pub(crate) plan: Plan,
    /// For robots exploring an operator's region: the region's next frontier,
    /// `None` when no reachable frontier is left inside.
    pub(super) region_targets: Vec<(RobotId, Option<exploration::policy::Target>)>,
    /// No robot can explore anything more: the map of some scope has no
    /// frontier left (Burgard et al. 2005 §VI-D: as soon as the known area
    /// in the map of one robot covers the whole environment), or no robot
    /// can reach or may be sent to what is left.
    pub(crate) complete: bool,
    /// Nobody was in the pool (every robot lost or overridden) and the map
    /// has frontier: whether the mission is complete cannot be told, so it
    /// keeps its state.
    pub(super) undecided: bool,
    /// What is left at completion, and why.
    pub(super) leftovers: Leftovers,
    pub(super) expired: Vec<(RobotId, Cell)>,
}

/// One coordination scope: its robots and the map they hold.
#[derive(Debug)]
struct PlanningPart {
    grid: OccupancyGrid,
    /// Every frontier cluster of the map.
    all_clusters: Vec<FrontierCluster>,
    /// The clusters the policy may choose from: large enough, forbidden
    /// cells and pinned frontiers taken out.
    clusters: Vec<FrontierCluster>,
    /// The robots in the policy's pool.
    robots: Vec<RobotView>,
    bids: Vec<Vec<PolicyBid>>,
    /// Targets of robots outside the scope, with their sensor ranges.
    reserved: Vec<(Cell, f64)>,
    /// Robots exploring an operator's region, with the region.
    regions: Vec<(RobotView, CellRect)>,
    /// The map holds known cells and no frontier.
    explored: bool,
}

impl PlanningJob {
    /// The same job, its threads held back by `pace`.
    pub(crate) fn paced_by(self, pace: SharedPace) -> Self {
        Self { pace, ..self }
    }

    /// Runs the policy on every part; CPU-bound.
    pub(crate) fn run(self) -> JobOutcome {
        let workers = Workers { threads: self.threads, pace: &*self.pace };
        let mut targets = vec![None; self.order.len()];
        let mut segmentation = None;
        let mut largest = 0;
        let mut region_targets = Vec::new();
        let mut caches: Vec<CostCache<'_>> = self.parts.iter().map(|part| CostCache::new(&part.grid)).collect();
        for (part, cache) in self.parts.iter().zip(&mut caches) {
            if !part.robots.is_empty() {
                let input = PlanningInput {
                    grid: &part.grid,
                    clusters: &part.clusters,
                    robots: &part.robots,
                    workers,
                    bids: &part.bids,
                    seed: self.seed,
                    reserved: &part.reserved,
                    rooms: self.rooms.as_deref(),
                };
                let plan = self.policy.plan(&input, cache);
                for (robot, target) in part.robots.iter().zip(plan.targets) {
                    if let Some(slot) = self.order.iter().position(|id| *id == robot.id) {
                        targets[slot] = target;
                    }
                }
                if part.robots.len() > largest {
                    largest = part.robots.len();
                    segmentation = plan.segmentation;
                }
            }
            for (robot, region) in &part.regions {
                let target = lifecycle::region_target(&part.all_clusters, robot, *region, &self.forbidden, cache);
                region_targets.push((robot.id, target));
            }
        }
        let explored = self.parts.iter().any(|part| part.explored);
        let idle_pool = !self.order.is_empty() && targets.iter().all(Option::is_none);
        let mut complete = explored;
        let mut leftovers = Vec::new();
        // A mission that knows nothing has no frontier yet, not none left.
        if !explored && idle_pool && !self.nothing_known {
            // The policy found nothing for anyone: is anything left that some robot could explore?
            complete = true;
            for (part, cache) in self.parts.iter().zip(&mut caches) {
                if part.robots.is_empty() {
                    continue;
                }
                let remaining = exploration::completion::remaining_frontier(
                    &part.all_clusters,
                    self.min_frontier_size,
                    &part.robots,
                    &self.forbidden,
                    cache,
                    workers,
                );
                complete &= remaining.is_exhausted();
                let frame = part.grid.frame();
                leftovers.extend(remaining.left.iter().map(|&(i, reason)| Leftover {
                    reason: lifecycle::leftover_reason(reason),
                    cells: part.all_clusters[i].len(),
                    position: frame.world_from_cell(part.all_clusters[i].representative),
                }));
            }
            if !complete {
                leftovers.clear();
            }
        }
        let undecided = (self.order.is_empty() || self.nothing_known) && !explored;
        let frontier_targets = self
            .parts
            .iter()
            .flat_map(|part| {
                targets
                    .iter()
                    .flatten()
                    .map(|t| t.cell)
                    .filter(|&cell| exploration::frontier::is_frontier(&part.grid, cell))
            })
            .collect();
        JobOutcome {
            frontier_targets,
            order: self.order,
            plan: Plan { targets, segmentation },
            region_targets,
            complete,
            undecided,
            leftovers: Leftovers::keep_largest(leftovers),
            expired: self.expired,
        }
    }
}

impl Mission {
    /// The inputs of a replanning.
    pub(crate) fn planning_job(&self, threads: usize) -> PlanningJob {
        let frame = &self.record.spec.frame;
        let expired = self.expired_blacklist();
        let view = |slot: &RobotSlot| {
            let r = &slot.record;
            RobotView {
                id: r.id,
                cell: frame.cell_from_world_unchecked(&r.pose.position),
                capabilities: r.capabilities,
                current: r.current_task.and_then(|t| self.open_tasks.get(&t)).and_then(|task| {
                    frame
                        .cell_from_world(&task.target)
                        .map(|target| CurrentTask { target, gain_region: task.gain_region })
                }),
                excluded: {
                    let live: Vec<Cell> = slot
                        .blacklist
                        .iter()
                        .map(|b| b.entry.cell)
                        .filter(|cell| !expired.contains(&(r.id, *cell)))
                        .collect();
                    live.iter().map(|&cell| lifecycle::exclusion(frame, cell, &live)).collect()
                },
            }
        };
        let forbidden: Vec<CellRect> = self.forbidden.iter().filter_map(|r| self.cell_rect(r.min, r.max)).collect();
        // Frontier pinned to a robot is not offered to the others.
        let pinned: Vec<Cell> = self
            .open_tasks
            .values()
            .filter(|t| t.kind == TaskKind::Pin)
            .filter_map(|t| frame.cell_from_world(&t.target))
            .collect();
        let min_size = self.record.spec.policy.min_frontier_size();
        let choosable = |all: &[FrontierCluster]| -> Vec<FrontierCluster> {
            all.iter()
                .filter(|c| c.len() >= min_size && !pinned.iter().any(|p| c.cells.contains(p)))
                .filter_map(|c| c.retain(|cell| !forbidden.iter().any(|r| r.contains(cell))))
                .collect()
        };
        let allowed = |cell: Cell| !forbidden.iter().any(|r| r.contains(cell));
        // Simmons et al. 2000, §4.2: a robot's bids count when they are new
        // or it is idle; a robot with a task and no new bids continues.
        let bids_of = |id: &RobotId| {
            let busy = self.robots[id].record.current_task.is_some();
            if busy && !self.fresh_bids.contains(id) {
                return Vec::new();
            }
            let mut bids = self.bids.get(id).cloned().unwrap_or_default();
            bids.retain(|b| allowed(b.target));
            bids
        };
        let part = |members: &[RobotId], grid: OccupancyGrid, frontier: &FrontierMap| {
            let all_clusters = clusters(frontier, 1);
            let pool: Vec<&RobotSlot> =
                members.iter().map(|id| &self.robots[id]).filter(|s| self.in_pool(&s.record)).collect();
            let regions = members
                .iter()
                .map(|id| &self.robots[id])
                .filter(|s| !s.record.lost)
                .filter_map(|s| {
                    let task = s.record.current_task.and_then(|t| self.open_tasks.get(&t))?;
                    let region = task.gain_region.filter(|_| task.kind == TaskKind::Goto)?;
                    Some((view(s), region))
                })
                .collect();
            let reserved = self
                .robots
                .values()
                .filter(|s| !members.contains(&s.record.id))
                .filter_map(|s| {
                    let target = self.target_of(&s.record)?;
                    Some((frame.cell_from_world(&target)?, s.record.capabilities.sensor_range_m))
                })
                .collect();
            PlanningPart {
                clusters: choosable(&all_clusters),
                explored: frontier.is_empty() && grid.cells().iter().any(|&c| c != exploration::grid::UNKNOWN),
                all_clusters,
                grid,
                robots: pool.iter().map(|s| view(s)).collect(),
                bids: pool.iter().map(|s| bids_of(&s.record.id)).collect(),
                reserved,
                regions,
            }
        };
        let parts = if self.record.spec.scoped_by_communication {
            self.sub_teams()
                .into_iter()
                .map(|members| {
                    let grid = self.fusion.grid_of(&members);
                    let frontier = FrontierMap::detect(&grid);
                    part(&members, grid, &frontier)
                })
                .collect()
        } else {
            let members: Vec<RobotId> = self.robots.keys().copied().collect();
            let mut whole = part(&members, self.fusion.grid().clone(), &self.frontier);
            whole.reserved.clear();
            whole.explored = self.known_cells > 0 && self.frontier.is_empty();
            vec![whole]
        };
        PlanningJob {
            order: self.robots.values().filter(|s| self.in_pool(&s.record)).map(|s| s.record.id).collect(),
            parts,
            forbidden,
            expired,
            min_frontier_size: min_size,
            policy: self.policy.clone(),
            rooms: self.rooms.clone(),
            nothing_known: self.known_cells == 0,
            threads,
            pace: Arc::new(Unpaced),
            // Randomized policies draw from the mission and its replanning count: reproducible.
            seed: self.record.id.wrapping_mul(0x9E37_79B9_7F4A_7C15) ^ self.record.replans,
        }
    }

    /// The connected sub-teams of the communication graph the robots
    /// reported, each in robot order; robots that reported no peers are alone.
    fn sub_teams(&self) -> Vec<Vec<RobotId>> {
        let ids: Vec<RobotId> = self.robots.keys().copied().collect();
        let mut team: BTreeMap<RobotId, usize> = ids.iter().enumerate().map(|(k, id)| (*id, k)).collect();
        let root = |team: &BTreeMap<RobotId, usize>, mut k: usize| {
            while ids[k] != ids[team[&ids[k]]] {
                k = team[&ids[k]];
            }
            k
        };
        for slot in self.robots.values() {
            for peer in &slot.peers {
                if team.contains_key(peer) {
                    let (a, b) = (root(&team, team[&slot.record.id]), root(&team, team[peer]));
                    if a != b {
                        let (low, high) = (a.min(b), a.max(b));
                        team.insert(ids[high], low);
                    }
                }
            }
        }
        let mut groups: BTreeMap<usize, Vec<RobotId>> = BTreeMap::new();
        for (k, id) in ids.iter().enumerate() {
            groups.entry(root(&team, k)).or_default().push(*id);
        }
        groups.into_values().collect()
    }
}
