//! `burgard-joint`: the best joint assignment, with squared costs.
//!
//! Burgard, Moors, Stachniss & Schneider 2005, Algorithm 2: choose targets
//! t_1 … t_n maximizing
//!
//! Σ_i [ U(t_i | t_1, …, t_{i−1}, t_{i+1}, …, t_n) − β · (V_{t_i}^i)² ]
//!
//! where U(t | others) = 1 − Σ_k P(‖t − t_k‖) (Eq. 1, with ray casting) and
//! V is Algorithm 1's value-iteration cost. Squaring the cost favours
//! balanced trajectories: the team finishes when its slowest robot does
//! (Fig. 7). There are T!/(T−n)! joint assignments; when that is at most
//! `exact_limit` they are all searched (branch and bound), otherwise each
//! robot keeps its best candidates by 1 − β·V², exhaustively while their
//! product stays within the limit, and beyond that "a randomized search
//! technique combined with hill-climbing" (§IV-C): restarts from Algorithm
//! 1's assignment and from seeded random ones, each improved one robot at a
//! time until no change helps. Whatever the branch, Algorithm 1's own
//! assignment is a candidate too, so the result is never worse than it by
//! this objective.
//!
//! β's meaning. V is in metres (× P(occ)) as in Algorithm 1, where β weighs
//! a metre of cost against the unit utility. V² is in square metres, which
//! would give the same β another meaning at every map size; the squared
//! cost here is V² / V̄, V̄ the mean cost of the plan's reachable pairs:
//! still convex (balanced trajectories win), in metres, and equal to
//! Algorithm 1's β·V at the mean distance.

use super::registry::{BETA, MIN_FRONTIER_SIZE, OCC_MAX, ParamSpec, PolicyDescriptor, SMOOTHING, SWITCH_UTILITY};
use std::collections::HashMap;

use super::burgard::covered;
use super::{Burgard, Plan, PlanningInput, Policy, Target, current_target};
use crate::cost::CostCache;
use crate::grid::Cell;
use crate::rng::SplitMix64;

pub(super) const NAME: &str = "burgard-joint";

/// The catalogue's entry: name, what it does, parameters with units, and
/// how it is built from a validated configuration.
pub(super) const DESCRIPTOR: PolicyDescriptor = PolicyDescriptor {
    name: NAME,
    description: "Burgard et al. 2005, Algorithm 2: the joint assignment maximizing the sum of U(t_i | others) - beta * V_i^2; exact for small teams, randomized search with hill climbing beyond",
    params: &[
        MIN_FRONTIER_SIZE,
        SWITCH_UTILITY,
        BETA,
        OCC_MAX,
        SMOOTHING,
        ParamSpec {
            name: "candidates",
            description: "targets considered per robot in the exact search: its best by U - beta * V^2",
            default: 6.0,
            min: 1.0,
            max: 64.0,
        },
        ParamSpec {
            name: "exact_limit",
            description: "largest number of joint assignments searched exhaustively; beyond it, randomized search",
            default: 50_000.0,
            min: 1.0,
            max: 10_000_000.0,
        },
        ParamSpec {
            name: "restarts",
            description: "random starting assignments of the randomized search (besides Algorithm 1's)",
            default: 8.0,
            min: 0.0,
            max: 1_000.0,
        },
    ],
    build: |c| {
        Box::new(BurgardJoint {
            burgard: Burgard {
                beta: c.get("beta"),
                occ_max: c.get("occ_max"),
                smoothing_sigma_m: c.get("smoothing_sigma_m"),
                switch_margin: c.get("switch_margin"),
            },
            candidates: c.get("candidates").round() as usize,
            exact_limit: c.get("exact_limit").round() as u64,
            restarts: c.get("restarts").round() as usize,
        })
    },
};

/// Burgard et al. 2005, Algorithm 2.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BurgardJoint {
    /// β, occ_max and smoothing, as for Algorithm 1.
    pub burgard: Burgard,
    /// Fewest candidate targets per robot in an exhaustive search.
    pub candidates: usize,
    /// Largest number of joint assignments searched exhaustively.
    pub exact_limit: u64,
    /// Random restarts of the hill climbing.
    pub restarts: usize,
}

/// The objective over a set of candidate cells, with P cached per pair.
struct Objective<'a> {
    input: &'a PlanningInput<'a>,
    frontier: &'a [Cell],
    values: &'a [Vec<Option<f64>>],
    beta: f64,
    /// V̄: the mean cost of the reachable pairs, metres.
    mean_cost: f64,
    margin: f64,
    pairs: HashMap<(usize, usize, usize), f64>,
}

impl<'a> Objective<'a> {
    /// The objective of `burgard`'s β and margin over these costs; V̄ is
    /// the mean over the reachable pairs (1 when there are none).
    fn new(
        input: &'a PlanningInput<'a>,
        frontier: &'a [Cell],
        values: &'a [Vec<Option<f64>>],
        burgard: &Burgard,
    ) -> Self {
        let (sum, count) = values.iter().flatten().flatten().fold((0.0, 0usize), |(s, n), v| (s + v, n + 1));
        let mean_cost = if count > 0 && sum > 0.0 { sum / count as f64 } else { 1.0 };
        Objective {
            input,
            frontier,
            values,
            beta: burgard.beta,
            mean_cost,
            margin: burgard.switch_margin,
            pairs: HashMap::new(),
        }
    }

    /// 1 − β·V²/V̄ of robot i at frontier cell t (see the module on V̄).
    fn own(&self, i: usize, t: usize) -> f64 {
        let v = self.values[i][t].unwrap_or(f64::INFINITY);
        let keep = if Some(self.frontier[t]) == current_target(&self.input.robots[i]) { self.margin } else { 0.0 };
        1.0 - self.beta * v * v / self.mean_cost + keep
    }

    /// P(‖t − u‖) for robot k's sensor at u.
    fn overlap(&mut self, t: usize, u: usize, k: usize) -> f64 {
        let (grid, frontier, range) =
            (self.input.grid, self.frontier, self.input.robots[k].capabilities.sensor_range_m);
        *self.pairs.entry((t, u, k)).or_insert_with(|| covered(grid, frontier[u], frontier[t], range))
    }

    /// J of a complete assignment (robot → frontier index).
    fn total(&mut self, assignment: &[(usize, usize)]) -> f64 {
        let mut sum = 0.0;
        for &(i, t) in assignment {
            sum += self.own(i, t);
            for &(k, u) in assignment {
                if k != i {
                    sum -= self.overlap(t, u, k);
                }
            }
        }
        sum
    }
}

impl BurgardJoint {
    /// The objective J of `targets` (one per robot of `input`), as the
    /// search measures it.
    #[cfg(test)]
    fn objective_of(&self, input: &PlanningInput<'_>, targets: &[Option<Cell>]) -> f64 {
        let frontier = input.frontier_cells();
        let values = self.burgard.cost_values(input, &mut CostCache::new(input.grid), &frontier);
        let mut objective = Objective::new(input, &frontier, &values, &self.burgard);
        let pairs: Vec<(usize, usize)> = targets
            .iter()
            .enumerate()
            .filter_map(|(i, t)| Some((i, frontier.iter().position(|c| Some(*c) == *t)?)))
            .collect();
        objective.total(&pairs)
    }

    fn search_exhaustively(
        objective: &mut Objective<'_>,
        lists: &[(usize, Vec<usize>)],
        depth: usize,
        chosen: &mut Vec<(usize, usize)>,
        partial: f64,
        best: &mut (f64, Vec<(usize, usize)>),
        bounds: &[f64],
    ) {
        if depth == lists.len() {
            if partial > best.0 {
                *best = (partial, chosen.clone());
            }
            return;
        }
        // Later robots can only add their own best term and subtract overlaps.
        if partial + bounds[depth] <= best.0 {
            return;
        }
        let (i, ref targets) = lists[depth];
        for &t in targets {
            if chosen.iter().any(|&(_, u)| u == t) {
                continue;
            }
            let mut gain = objective.own(i, t);
            for &(k, u) in chosen.iter() {
                gain -= objective.overlap(t, u, k) + objective.overlap(u, t, i);
            }
            chosen.push((i, t));
            Self::search_exhaustively(objective, lists, depth + 1, chosen, partial + gain, best, bounds);
            chosen.pop();
        }
    }

    /// Coordinate ascent: move one robot at a time to the target that helps
    /// most given the others, until no move helps.
    fn hill_climb(
        objective: &mut Objective<'_>,
        lists: &[(usize, Vec<usize>)],
        mut current: Vec<(usize, usize)>,
    ) -> (f64, Vec<(usize, usize)>) {
        loop {
            let mut improved = false;
            for slot in 0..current.len() {
                let (i, now) = current[slot];
                // What robot i's target contributes, given the others.
                let contribution = |objective: &mut Objective<'_>, t: usize| {
                    let mut c = objective.own(i, t);
                    for (other, &(k, u)) in current.iter().enumerate() {
                        if other != slot {
                            c -= objective.overlap(t, u, k) + objective.overlap(u, t, i);
                        }
                    }
                    c
                };
                let mut best = (contribution(objective, now), now);
                for &t in &lists[slot].1 {
                    if t == now || current.iter().any(|&(_, u)| u == t) {
                        continue;
                    }
                    let c = contribution(objective, t);
                    if c > best.0 + 1e-12 {
                        best = (c, t);
                    }
                }
                if best.1 != now {
                    current[slot] = (i, best.1);
                    improved = true;
                }
            }
            if !improved {
                return (objective.total(&current), current);
            }
        }
    }
}

impl Policy for BurgardJoint {
    fn name(&self) -> &'static str {
        NAME
    }

    fn plan(&self, input: &PlanningInput<'_>, costs: &mut CostCache<'_>) -> Plan {
        let frontier = input.frontier_cells();
        let values = self.burgard.cost_values(input, costs, &frontier);
        let n = input.robots.len();
        let mut objective = Objective::new(input, &frontier, &values, &self.burgard);
        // Each robot's reachable targets, best first by 1 − β·V².
        let ranked: Vec<(usize, Vec<usize>)> = (0..n)
            .map(|i| {
                let mut reachable: Vec<usize> = (0..frontier.len()).filter(|&t| values[i][t].is_some()).collect();
                reachable.sort_by(|&a, &b| objective.own(i, b).total_cmp(&objective.own(i, a)).then(a.cmp(&b)));
                (i, reachable)
            })
            .filter(|(_, r)| !r.is_empty())
            .collect();
        let active = ranked.len();
        let mut targets: Vec<Option<Target>> = vec![None; n];
        if active == 0 {
            return Plan::of(targets);
        }
        // Algorithm 1's assignment, as (robot, frontier index): a start for the
        // search and a candidate of its own.
        let greedy = self.burgard.assign(input, &frontier, &values);
        let index_of = |cell: Cell| frontier.iter().position(|&c| c == cell);
        let mut from_greedy: Vec<(usize, usize)> = Vec::new();
        for (i, _) in &ranked {
            match greedy[*i].and_then(|t| index_of(t.cell)).filter(|t| from_greedy.iter().all(|&(_, u)| u != *t)) {
                Some(t) => from_greedy.push((*i, t)),
                None => {
                    from_greedy.clear();
                    break;
                }
            }
        }
        let all = frontier.len() as f64;
        let everything = (active as f64) * all.ln() <= (self.exact_limit as f64).ln();
        let per_robot = ((self.exact_limit as f64).powf(1.0 / active as f64).floor() as usize).max(1);
        // Each robot's candidates: its best ones, and Algorithm 1's target for it.
        let lists_of = |keep: usize| -> Vec<(usize, Vec<usize>)> {
            ranked
                .iter()
                .map(|(i, r)| {
                    let mut list: Vec<usize> = r.iter().copied().take(keep).collect();
                    if let Some(&(_, t)) = from_greedy.iter().find(|(k, _)| k == i)
                        && !list.contains(&t)
                    {
                        list.push(t);
                    }
                    (*i, list)
                })
                .collect()
        };
        let searched = if everything || per_robot >= self.candidates {
            let lists = lists_of(if everything { usize::MAX } else { per_robot });
            let mut bounds = vec![0.0; lists.len() + 1];
            for d in (0..lists.len()).rev() {
                let (i, ref l) = lists[d];
                bounds[d] = bounds[d + 1] + l.iter().map(|&t| objective.own(i, t)).fold(f64::NEG_INFINITY, f64::max);
            }
            let mut best = (f64::NEG_INFINITY, Vec::new());
            Self::search_exhaustively(&mut objective, &lists, 0, &mut Vec::new(), 0.0, &mut best, &bounds);
            best
        } else {
            let lists = lists_of(4 * self.candidates);
            // Start from Algorithm 1's choice, then from random ones.
            let mut starts: Vec<Vec<(usize, usize)>> = Vec::new();
            if from_greedy.len() == lists.len() {
                starts.push(from_greedy.clone());
            }
            let mut rng = SplitMix64::new(input.seed);
            for _ in 0..self.restarts {
                let mut start = Vec::new();
                for (i, l) in &lists {
                    let free: Vec<usize> = l.iter().copied().filter(|t| start.iter().all(|&(_, u)| u != *t)).collect();
                    if let Some(&t) = free.get(rng.below(free.len().max(1) as u64) as usize) {
                        start.push((*i, t));
                    }
                }
                if start.len() == lists.len() {
                    starts.push(start);
                }
            }
            starts
                .into_iter()
                .map(|s| Self::hill_climb(&mut objective, &lists, s))
                .fold((f64::NEG_INFINITY, Vec::new()), |best, c| if c.0 > best.0 { c } else { best })
        };
        // Never worse than Algorithm 1 by this objective.
        let best = if from_greedy.len() == active {
            let greedy_total = objective.total(&from_greedy);
            if greedy_total > searched.0 || searched.1.len() < active { (greedy_total, from_greedy) } else { searched }
        } else {
            searched
        };
        // Fewer frontier cells than robots: the rest fall back on Algorithm 1.
        let fallback = if best.1.len() < active { Some(self.burgard.assign(input, &frontier, &values)) } else { None };
        for &(i, t) in &best.1 {
            let v = values[i][t].unwrap_or(0.0);
            targets[i] =
                Some(Target { cell: frontier[t], utility: objective.own(i, t), path_cost: v, gain_region: None });
        }
        if let Some(fallback) = fallback {
            for (i, slot) in targets.iter_mut().enumerate() {
                if slot.is_none() {
                    *slot = fallback[i];
                }
            }
        }
        Plan::of(targets)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::grid::testing::grid_from_picture;
    use crate::policy::testing::{plan_targets, plan_with_defaults, robot, with_input};

    fn joint(exact_limit: u64) -> BurgardJoint {
        BurgardJoint {
            burgard: Burgard { beta: 1.0, occ_max: 0.6, smoothing_sigma_m: 0.0, switch_margin: 0.0 },
            candidates: 2,
            exact_limit,
            restarts: 4,
        }
    }

    /// Burgard et al. 2005, Fig. 7: a corridor with two rooms. Algorithm 1
    /// gives robot 2 the room next to it (the cheapest pair of all) and sends
    /// robot 1 to the far room; Algorithm 2's squared costs send robot 1 to
    /// the near room and robot 2 on to the far one, so the slower of the two
    /// arrives sooner.
    #[test]
    fn the_joint_search_finds_the_balanced_assignment_algorithm_1_misses() {
        let grid = grid_from_picture(&[
            "###########?########?#", //
            "#....................#", //
            "######################", //
        ]);
        let (a, b) = (Cell::new(11, 1), Cell::new(20, 1));
        let robots = [robot(1, Cell::new(1, 1), 3.0), robot(2, Cell::new(10, 1), 3.0)];
        let algorithm_1 = plan_targets(&joint(1).burgard, &grid, &robots);
        assert_eq!(algorithm_1, vec![Some(b), Some(a)]);
        // Exhaustive (4 joint assignments) and randomized (limit 1) both find it.
        for limit in [50_000, 1] {
            let algorithm_2 = plan_targets(&joint(limit), &grid, &robots);
            assert_eq!(algorithm_2, vec![Some(a), Some(b)], "exact_limit {limit}");
        }
        // Closest frontier sends both to the near room; greedy is Algorithm 1 here.
        assert_eq!(plan_with_defaults("nearest", &grid, &robots), vec![Some(a), Some(a)]);
        assert_eq!(plan_with_defaults("greedy", &grid, &robots), vec![Some(b), Some(a)]);
    }

    /// Fig. 7 with a third room further on: 3 frontier cells, 6 joint
    /// assignments. A limit of 8 is too small to search them all but lets
    /// each robot keep its 2 best candidates (4 combinations), the pruned
    /// exhaustive branch; it still finds the balanced assignment.
    #[test]
    fn the_pruned_search_finds_the_balanced_assignment_too() {
        let grid = grid_from_picture(&[
            "###########?########?#########?#", //
            "#..............................#", //
            "################################", //
        ]);
        let (a, b) = (Cell::new(11, 1), Cell::new(20, 1));
        let robots = [robot(1, Cell::new(1, 1), 3.0), robot(2, Cell::new(10, 1), 3.0)];
        assert_eq!(plan_targets(&joint(1).burgard, &grid, &robots), vec![Some(b), Some(a)]);
        assert_eq!(plan_targets(&joint(8), &grid, &robots), vec![Some(a), Some(b)]);
    }

    /// Whatever branch the search takes (exhaustive, pruned or randomized),
    /// its objective is never below Algorithm 1's assignment's.
    #[test]
    fn the_joint_search_is_never_worse_than_algorithm_1() {
        use proptest::prelude::*;
        let mut runner = proptest::test_runner::TestRunner::new(crate::testing::seeded_proptest(96));
        let instance = (any::<u64>(), 2usize..6, 0u32..6);
        runner
            .run(&instance, |(seed, n, limit)| {
                let mut rng = SplitMix64::new(seed);
                // A 24 × 10 room, its upper rows unknown, random inner walls.
                let rows: Vec<String> = (0..10)
                    .map(|r| {
                        (0..24)
                            .map(|x| match (r, x) {
                                (0 | 9, _) | (_, 0 | 23) => '#',
                                (1..=3, _) => '?',
                                _ if rng.below(9) == 0 => '#',
                                _ => '.',
                            })
                            .collect()
                    })
                    .collect();
                let picture: Vec<&str> = rows.iter().map(String::as_str).collect();
                let grid = grid_from_picture(&picture);
                let free: Vec<Cell> = grid.frame().bounds().cells().filter(|&c| grid.value(c) == 10).collect();
                prop_assume!(free.len() > n);
                let robots: Vec<_> =
                    (0..n).map(|k| robot(k as u64, free[rng.below(free.len() as u64) as usize], 3.0)).collect();
                let policy = BurgardJoint { exact_limit: 10u64.pow(limit), ..joint(1) };
                let algorithm_1 = plan_targets(&policy.burgard, &grid, &robots);
                let algorithm_2 = plan_targets(&policy, &grid, &robots);
                let (one, two) = with_input(&grid, &robots, &vec![Vec::new(); robots.len()], |input| {
                    (policy.objective_of(input, &algorithm_1), policy.objective_of(input, &algorithm_2))
                });
                prop_assert!(two >= one - 1e-9, "Algorithm 2 {two} below Algorithm 1 {one}");
                Ok(())
            })
            .unwrap();
    }
}
