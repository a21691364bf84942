//! When exploration is over, and what it left behind.
//!
//! Burgard et al. 2005 end exploration when no frontier is left. On real maps
//! frontier remains that no robot can ever explore: seen through a window,
//! behind a gap narrower than every footprint, blacklisted for every robot
//! that tried it, or forbidden by an operator. Such clusters cost every robot
//! ∞ (Wurm et al. 2008, Eq. 4), and a mission whose remaining clusters all
//! cost ∞ is complete. [`remaining_frontier`] tells the clusters some robot
//! can still explore from those left, each with its reason.

use crate::cost::{CostCache, TraversalKind, cost_map};
use crate::frontier::FrontierCluster;
use crate::grid::{Cell, CellRect};
use crate::policy::RobotView;
use crate::workers::Workers;

/// Why a frontier cluster is left unexplored (the cases in which Wurm et
/// al. 2008, Eq. 4, give every robot infinite cost).
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub enum LeftReason {
    /// Fewer cells than the policy's minimum frontier size: not worth a trip.
    TooSmall,
    /// Every cell lies in a forbidden region.
    Forbidden,
    /// Robots can reach it, but it is excluded for each of them.
    Blacklisted,
    /// A point robot could reach it; no robot fits through the way there.
    TooNarrow,
    /// Not connected to any robot through known free space.
    Disconnected,
}

/// What is left of the frontier (Burgard et al. 2005, §II: exploration ends
/// when no reachable frontier remains).
#[derive(Debug, Clone, PartialEq, Default)]
pub struct RemainingFrontier {
    /// Indices of the clusters some robot can reach and may be sent to.
    pub open: Vec<usize>,
    /// The other clusters, by index, with why each is left.
    pub left: Vec<(usize, LeftReason)>,
}

impl RemainingFrontier {
    /// Whether exploration is over: no robot can explore any cluster
    /// (Burgard et al. 2005, §II: no reachable frontier is left).
    pub fn is_exhausted(&self) -> bool {
        self.open.is_empty()
    }
}

/// Sorts `clusters` into those some robot can still explore and those left,
/// with their reasons. A cluster counts as open when it has at least
/// `min_size` cells and one of its cells outside the `forbidden` rectangles
/// has a finite cost for some robot's free-space traversal (its footprint
/// inflating the obstacles) and is not excluded for that robot. With no
/// robots every cluster is `Disconnected`.
pub fn remaining_frontier(
    clusters: &[FrontierCluster],
    min_size: usize,
    robots: &[RobotView],
    forbidden: &[CellRect],
    costs: &mut CostCache<'_>,
    workers: Workers<'_>,
) -> RemainingFrontier {
    let kinds: Vec<TraversalKind> = robots.iter().map(RobotView::free_space).collect();
    let mut by_kind: std::collections::BTreeMap<TraversalKind, Vec<Cell>> = Default::default();
    for (robot, kind) in robots.iter().zip(&kinds) {
        by_kind.entry(*kind).or_default().push(robot.cell);
    }
    for (kind, sources) in &by_kind {
        costs.cost_maps(*kind, sources, workers);
    }
    let maps: Vec<_> = robots.iter().zip(&kinds).map(|(r, k)| costs.cost_map(*k, r.cell)).collect();
    // Reachability for a point robot from any robot: tells narrow passages
    // from disconnected space. Built only if some cluster needs it.
    let mut point_reach = None;
    let mut remaining = RemainingFrontier::default();
    for (index, cluster) in clusters.iter().enumerate() {
        if cluster.len() < min_size {
            remaining.left.push((index, LeftReason::TooSmall));
            continue;
        }
        let allowed: Vec<Cell> =
            cluster.cells.iter().copied().filter(|c| !forbidden.iter().any(|r| r.contains(*c))).collect();
        if allowed.is_empty() {
            remaining.left.push((index, LeftReason::Forbidden));
            continue;
        }
        let mut reachable = false;
        let mut open = false;
        for (robot, map) in robots.iter().zip(&maps) {
            for &cell in &allowed {
                if map.cost(cell).is_some() {
                    reachable = true;
                    if robot.may_target(cell) {
                        open = true;
                        break;
                    }
                }
            }
            if open {
                break;
            }
        }
        if open {
            remaining.open.push(index);
        } else if reachable {
            remaining.left.push((index, LeftReason::Blacklisted));
        } else {
            let reach = point_reach.get_or_insert_with(|| {
                let traversal = costs.traversal(TraversalKind::free_space(0.0));
                let sources: Vec<Cell> = robots.iter().map(|r| r.cell).collect();
                cost_map(&traversal, &sources)
            });
            let narrow = allowed.iter().any(|&c| reach.cost(c).is_some());
            remaining.left.push((index, if narrow { LeftReason::TooNarrow } else { LeftReason::Disconnected }));
        }
    }
    remaining
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::frontier::{FrontierMap, clusters};
    use crate::grid::{GridFrame, OccupancyGrid};

    const KNOWN_FREE: u8 = 0;
    const KNOWN_OCCUPIED: u8 = 100;
    use crate::math::Point2;
    use crate::policy::testing::robot;

    /// A 30 × 11 grid: a known room (x < 10) with the robot, a wall at x = 10
    /// with a one-cell gap at y = 5, a known corridor beyond (x 11..15), then
    /// unknown space. Another known pocket, walled off, touches unknown space
    /// at the top right.
    fn building() -> OccupancyGrid {
        let frame = GridFrame::new(0.1, Point2::origin(), 30, 11);
        let mut grid = OccupancyGrid::unknown(frame);
        for y in 0..11 {
            for x in 0..16 {
                let wall = x == 10 && y != 5 || y == 0 || y == 10 || x == 0;
                grid.set(Cell::new(x, y), if wall { KNOWN_OCCUPIED } else { KNOWN_FREE });
            }
        }
        // The walled-off pocket: free cells ringed by walls except towards unknown space.
        for y in 6..10 {
            for x in 20..25 {
                let wall = x == 20 || y == 6;
                grid.set(Cell::new(x, y), if wall { KNOWN_OCCUPIED } else { KNOWN_FREE });
            }
        }
        grid
    }

    #[test]
    fn frontier_beyond_the_gap_is_open_for_a_point_robot_and_too_narrow_for_a_wide_one() {
        let grid = building();
        let point = robot(1, Cell::new(5, 5), 2.0);
        let clusters = clusters(&FrontierMap::detect(&grid), 1);
        let mut cache = CostCache::new(&grid);
        let remaining =
            remaining_frontier(&clusters, 1, std::slice::from_ref(&point), &[], &mut cache, Workers::unpaced(1));
        assert!(!remaining.is_exhausted());
        assert!(remaining.left.iter().all(|(_, r)| *r == LeftReason::Disconnected), "{remaining:?}");

        let mut wide = point.clone();
        wide.capabilities.footprint_radius_m = 0.15;
        let mut cache = CostCache::new(&grid);
        let remaining = remaining_frontier(&clusters, 1, &[wide], &[], &mut cache, Workers::unpaced(1));
        assert!(remaining.is_exhausted(), "{remaining:?}");
        let reasons: Vec<LeftReason> = remaining.left.iter().map(|(_, r)| *r).collect();
        assert!(reasons.contains(&LeftReason::TooNarrow), "{reasons:?}");
        assert!(reasons.contains(&LeftReason::Disconnected), "{reasons:?}");
    }

    #[test]
    fn forbidden_and_blacklisted_clusters_are_left_with_their_reason() {
        let grid = building();
        let clusters = clusters(&FrontierMap::detect(&grid), 1);
        let frame = *grid.frame();
        let all = CellRect::new(0, 0, frame.width, frame.height);
        let mut cache = CostCache::new(&grid);
        let point = robot(1, Cell::new(5, 5), 2.0);
        let remaining =
            remaining_frontier(&clusters, 1, std::slice::from_ref(&point), &[all], &mut cache, Workers::unpaced(1));
        assert!(remaining.is_exhausted());
        assert!(remaining.left.iter().all(|(_, r)| *r == LeftReason::Forbidden));

        let mut blacklisted = point.clone();
        blacklisted.excluded = vec![all];
        let remaining = remaining_frontier(&clusters, 1, &[blacklisted.clone()], &[], &mut cache, Workers::unpaced(1));
        assert!(remaining.is_exhausted());
        assert!(remaining.left.iter().any(|(_, r)| *r == LeftReason::Blacklisted), "{remaining:?}");
        // A second robot, not blacklisted, keeps the frontier open.
        let other = robot(2, Cell::new(3, 3), 2.0);
        let remaining =
            remaining_frontier(&clusters, 1, &[blacklisted, other.clone()], &[], &mut cache, Workers::unpaced(1));
        assert!(!remaining.is_exhausted());
        // Clusters under the minimum size are left as too small.
        let remaining = remaining_frontier(&clusters, 10_000, &[other], &[], &mut cache, Workers::unpaced(1));
        assert!(remaining.is_exhausted());
        assert!(remaining.left.iter().all(|(_, r)| *r == LeftReason::TooSmall));
    }
}
