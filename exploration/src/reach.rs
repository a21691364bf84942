//! Costs from robots to a few cells (the frontier), from searches that stop
//! at a cost limit and are widened when a policy needs more.
//!
//! A policy that weighs every frontier cell against its travel cost, such
//! as Burgard et al. 2005's Algorithm 1, needs each robot's cost to every
//! frontier cell, and a full search per robot covers the whole known map:
//! about 1.5 million cells per robot on a large building. But a target's
//! score falls with its cost, so once a robot's search has passed the cost
//! at which even the best utility can no longer beat the best pair found,
//! the rest of its search cannot change the choice. Each search is
//! therefore run up to a limit, and run again with twice the limit for the
//! robots whose unsearched costs could still matter; in a plane, searches
//! that double their radius cost at most 4/3 of the last one.
//!
//! Labels below the limit are final and equal to a full search's
//! ([`crate::cost::cost_map`]): the same buckets settle them in the same order.

use crate::cost::{Settled, TraversalMap, padded, settle_within};
use crate::grid::Cell;

/// What one search found of the targets' costs.
#[derive(Debug, Clone, PartialEq)]
pub struct Reach {
    /// Per target: its cost, infinite where not reached.
    costs: Vec<f32>,
    settled: Settled,
    limit: f64,
}

impl Reach {
    /// The cost of target `k`, when final: `None` when it cannot be reached
    /// or was not settled (then it costs at least [`Reach::unknown_at_least`]).
    pub fn cost(&self, k: usize) -> Option<f64> {
        let c = self.costs[k];
        (c.is_finite() && self.settled.is_final(c)).then_some(f64::from(c))
    }

    /// A cost that every target not known yet reaches or exceeds; infinite
    /// when the search was complete (those targets are unreachable).
    pub fn unknown_at_least(&self) -> f64 {
        self.settled.lower_bound()
    }

    /// The limit the search ran to.
    pub fn limit(&self) -> f64 {
        self.limit
    }
}

/// Searches from each of `sources` over `traversal` (corners kept, like
/// [`crate::cost::cost_map`]) until every cell cheaper than its entry of
/// `limits` is settled, and reads the costs of `targets`; on up to
/// `threads` threads, each with one reused buffer.
///
/// Complexity: per source, the cells cheaper than its limit (and their
/// neighbours), plus one pass over `targets`.
pub fn reach(
    traversal: &TraversalMap,
    sources: &[Cell],
    targets: &[Cell],
    limits: &[f64],
    threads: usize,
) -> Vec<Reach> {
    assert_eq!(sources.len(), limits.len(), "one limit per source");
    let work: Vec<(Cell, f64)> = sources.iter().copied().zip(limits.iter().copied()).collect();
    let threads = threads.clamp(1, work.len().max(1));
    let chunk = work.len().div_ceil(threads).max(1);
    let run = |part: &[(Cell, f64)]| {
        let mut buffer = Buffer::new(traversal);
        part.iter().map(|&(source, limit)| buffer.reach(traversal, source, targets, limit)).collect::<Vec<_>>()
    };
    if threads == 1 {
        return run(&work);
    }
    std::thread::scope(|scope| {
        let handles: Vec<_> = work.chunks(chunk).map(|part| scope.spawn(move || run(part))).collect();
        handles.into_iter().flat_map(|h| h.join().unwrap_or_else(|e| std::panic::resume_unwind(e))).collect()
    })
}

/// A search's costs over the whole padded grid, reset after each search
/// where it was written (cheaper than clearing it all).
struct Buffer {
    cost: Vec<f32>,
    touched: Vec<u32>,
}

impl Buffer {
    fn new(traversal: &TraversalMap) -> Self {
        Self { cost: vec![f32::INFINITY; traversal.padded_len()], touched: Vec::new() }
    }

    fn reach(&mut self, traversal: &TraversalMap, source: Cell, targets: &[Cell], limit: f64) -> Reach {
        let frame = *traversal.frame();
        let settled = settle_within(traversal, source, limit as f32, &mut self.cost, &mut self.touched);
        let costs = targets
            .iter()
            .map(|&t| if frame.contains(t) { self.cost[padded(&frame, t)] } else { f32::INFINITY })
            .collect();
        for &i in &self.touched {
            self.cost[i as usize] = f32::INFINITY;
        }
        self.touched.clear();
        Reach { costs, settled, limit }
    }
}

#[cfg(test)]
mod tests {
    use proptest::prelude::*;

    use super::*;
    use crate::cost::cost_map;
    use crate::grid::GridFrame;

    /// A grid of random passability and cost per metre: uniform (mode 0),
    /// varying a little (1: Dial's buckets), or a lot (2: the binary heap).
    fn traversal(width: u32, height: u32, cells: &[(bool, u8)], mode: u8) -> TraversalMap {
        let frame = GridFrame::new(0.1, crate::math::Point2::origin(), width, height);
        let costs = (0..(width * height) as usize)
            .map(|k| {
                let (open, weight) = cells[k % cells.len()];
                match (open, mode) {
                    (false, _) => f32::INFINITY,
                    (true, 0) => 1.0,
                    (true, 1) => 1.0 + f32::from(weight) / 16.0,
                    (true, _) => 1.0 + f32::from(weight).powi(2),
                }
            })
            .collect();
        TraversalMap::from_costs(frame, costs)
    }

    proptest! {
        #![proptest_config(ProptestConfig { cases: 300, ..ProptestConfig::default() })]

        /// Below its limit a search knows exactly what a full search knows,
        /// and whatever it does not know costs at least its bound.
        #[test]
        fn bounded_costs_are_the_full_searchs(
            width in 2u32..24,
            height in 2u32..24,
            cells in proptest::collection::vec((prop::bool::weighted(0.8), 0u8..255), 1..64),
            mode in 0u8..3,
            source in (0i32..24, 0i32..24),
            limit in prop_oneof![0.0f64..4.0, 0.0f64..4000.0],
            threads in 1usize..3,
        ) {
            let map = traversal(width, height, &cells, mode);
            let source = Cell::new(source.0 % width as i32, source.1 % height as i32);
            let targets: Vec<Cell> =
                (0..height as i32).flat_map(|y| (0..width as i32).map(move |x| Cell::new(x, y))).collect();
            let full = cost_map(&map, &[source]);
            let reached = reach(&map, &[source, source], &targets, &[limit, f64::INFINITY], threads);
            for (k, &t) in targets.iter().enumerate() {
                match reached[0].cost(k) {
                    Some(c) => prop_assert_eq!(Some(c), full.cost(t), "{:?}", t),
                    None => prop_assert!(
                        full.cost(t).is_none_or(|c| c >= reached[0].unknown_at_least()),
                        "{:?} costs {:?}, below the bound {}", t, full.cost(t), reached[0].unknown_at_least()
                    ),
                }
                prop_assert_eq!(reached[1].cost(k), full.cost(t), "an unlimited search is a full one");
            }
            prop_assert!(reached[1].unknown_at_least().is_infinite());
        }
    }
}
