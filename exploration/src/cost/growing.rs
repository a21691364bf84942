//! A cost map that is searched only as far as its user needs.
//!
//! Policies that score a target by a bounded gain less a weighted path cost
//! (Burgard et al. 2005, Algorithm 1: U_t − β·V_t^i with U_t ≤ 1) never pick
//! a target whose cost alone rules it out. A [`GrowingCostMap`] settles
//! labels in Dijkstra's order up to a radius, answers for the cells inside
//! it, and resumes where it stopped when asked for more; its answers are the
//! full cost map's.

use super::{Buckets, Cell, TraversalMap, heap};

/// A cost map from one source, settled up to [`GrowingCostMap::radius`].
#[derive(Debug)]
pub struct GrowingCostMap<'t> {
    traversal: &'t TraversalMap,
    /// Over the traversal's window; final below the radius.
    cost: Vec<f32>,
    /// The paused search; `None` once every reachable cell is settled.
    search: Option<Buckets>,
    /// The source, when it lies outside the window (it reaches itself only).
    stranded: Option<Cell>,
}

impl<'t> GrowingCostMap<'t> {
    /// The search from `source`, nothing settled yet but the source.
    pub fn new(traversal: &'t TraversalMap, source: Cell) -> Self {
        let mut cost = vec![f32::INFINITY; traversal.padded.len()];
        let (starts, stranded) = traversal.seed(&[source], &mut cost, &mut []);
        let stranded = stranded.first().map(|&(cell, _)| cell);
        let search = if starts.is_empty() { None } else { Buckets::fitting(&starts, traversal.step_bounds()) };
        if search.is_none() && !starts.is_empty() {
            // Step costs too far apart for buckets: one full search with the heap.
            heap::<_, false>(&traversal.weighted(), &mut cost, &mut [], &starts);
        }
        Self { traversal, cost, search, stranded }
    }

    /// Every cell cheaper than this is answered by [`Self::cost`]; every
    /// cell it does not answer costs at least this, or is unreachable.
    /// Infinite once the search has settled every reachable cell.
    pub fn radius(&self) -> f64 {
        self.search.as_ref().map_or(f64::INFINITY, |s| f64::from(s.radius()))
    }

    /// Resumes the search until [`Self::radius`] is at least `radius`
    /// (everything, for an infinite one), and in any case a step further.
    pub fn grow_to(&mut self, radius: f64) {
        let Some(search) = &mut self.search else { return };
        // At least one bucket more, so that every call makes progress.
        let end = search.end_for(radius as f32).max(search.current + 1);
        if self.traversal.is_uniform() {
            search.drain::<_, false, false>(&self.traversal.uniform(), &mut self.cost, &mut [], end);
        } else {
            search.drain::<_, false, false>(&self.traversal.weighted(), &mut self.cost, &mut [], end);
        }
        if search.exhausted() {
            self.search = None;
        }
    }

    /// The cost of reaching `cell`, if it is below the radius; `None` for a
    /// cell beyond it or unreachable.
    pub fn cost(&self, cell: Cell) -> Option<f64> {
        if !self.traversal.frame.contains(cell) {
            return None;
        }
        if self.stranded == Some(cell) {
            return Some(0.0);
        }
        let c = f64::from(self.traversal.window.index(cell).map_or(f32::INFINITY, |i| self.cost[i]));
        (c < self.radius()).then_some(c)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cost::cost_map;
    use crate::grid::testing::grid_from_picture;

    #[test]
    fn it_answers_inside_its_radius_and_grows_to_the_full_map() {
        let grid = grid_from_picture(&[
            "..........", //
            ".########.", //
            "..........", //
        ]);
        let traversal = TraversalMap::free_space(&grid, 0.0);
        let source = Cell::new(0, 1);
        let full = cost_map(&traversal, &[source]);
        let mut growing = GrowingCostMap::new(&traversal, source);
        growing.grow_to(3.0);
        let radius = growing.radius();
        assert!((3.0..4.0).contains(&radius), "radius {radius}");
        assert_eq!(growing.cost(Cell::new(9, 1)), None, "beyond the radius");
        for cell in (0..grid.frame().len()).map(|i| grid.frame().cell(i)) {
            match growing.cost(cell) {
                Some(c) => assert_eq!(Some(c), full.cost(cell)),
                None => assert!(full.cost(cell).is_none_or(|c| c >= radius), "{cell:?} costs {:?}", full.cost(cell)),
            }
        }
        growing.grow_to(f64::INFINITY);
        assert_eq!(growing.radius(), f64::INFINITY);
        for cell in (0..grid.frame().len()).map(|i| grid.frame().cell(i)) {
            assert_eq!(growing.cost(cell), full.cost(cell), "{cell:?}");
        }
    }

    #[test]
    fn a_source_off_the_passable_cells_reaches_itself_only() {
        let grid = grid_from_picture(&[
            "....", //
            "####", //
            "####", //
            "####", //
            "####", //
        ]);
        let traversal = TraversalMap::free_space(&grid, 0.0);
        let mut growing = GrowingCostMap::new(&traversal, Cell::new(0, 0));
        growing.grow_to(100.0);
        assert_eq!(growing.cost(Cell::new(0, 0)), Some(0.0));
        assert_eq!(growing.cost(Cell::new(0, 4)), None);
        let off = GrowingCostMap::new(&traversal, Cell::new(-5, 0));
        assert_eq!(off.cost(Cell::new(-5, 0)), None);
    }
}
