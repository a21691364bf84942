//! Ray casting on grids, and the range-sensor model.
//!
//! One traversal serves both the executive and the simulator: Burgard et al.
//! 2005 (§II-B) set P(d) to zero when "there is an obstacle between two
//! frontier cells", found "by a ray-casting operation on the grid map", and
//! the simulated robots sense with the same rays. The traversal is the exact
//! grid walk of Amanatides & Woo (1987): a ray visits every cell it crosses.
//! Where a ray passes exactly through a cell corner it is blocked if both
//! cells beside the corner are opaque, the same rule that forbids a robot to
//! squeeze diagonally between two walls, so whatever a robot can see it can
//! also reach.

use crate::grid::Cell;

/// Walks the cells a ray crosses, from the centre of `from` towards the point
/// `to` (in cell units: cell (x, y) spans [x, x+1) × [y, y+1)), calling `visit`
/// on each cell, `from` included.
///
/// The walk stops after visiting the first cell for which `opaque` holds (the
/// start cell is never tested), when the ray squeezes diagonally between two
/// opaque cells, or past `to`. Returns `true` when it reached `to` unblocked.
///
/// Complexity: O(cells crossed).
pub fn walk_ray(from: Cell, to: (f64, f64), opaque: impl Fn(Cell) -> bool, mut visit: impl FnMut(Cell)) -> bool {
    let (x0, y0) = (f64::from(from.x) + 0.5, f64::from(from.y) + 0.5);
    let (dx, dy) = (to.0 - x0, to.1 - y0);
    let mut cell = from;
    visit(cell);
    let step_x = if dx > 0.0 { 1 } else { -1 };
    let step_y = if dy > 0.0 { 1 } else { -1 };
    let t_delta_x = if dx == 0.0 { f64::INFINITY } else { 1.0 / dx.abs() };
    let t_delta_y = if dy == 0.0 { f64::INFINITY } else { 1.0 / dy.abs() };
    // The start point is a cell centre, so the first boundary is half a cell away.
    let mut t_max_x = 0.5 * t_delta_x;
    let mut t_max_y = 0.5 * t_delta_y;
    const EPS: f64 = 1e-9;
    loop {
        let t_next = t_max_x.min(t_max_y);
        if t_next > 1.0 + EPS {
            return true;
        }
        if (t_max_x - t_max_y).abs() <= EPS {
            // Through a corner: blocked if both side cells are opaque.
            let side_x = Cell::new(cell.x + step_x, cell.y);
            let side_y = Cell::new(cell.x, cell.y + step_y);
            if opaque(side_x) && opaque(side_y) {
                return false;
            }
            cell = Cell::new(cell.x + step_x, cell.y + step_y);
            t_max_x += t_delta_x;
            t_max_y += t_delta_y;
        } else if t_max_x < t_max_y {
            cell.x += step_x;
            t_max_x += t_delta_x;
        } else {
            cell.y += step_y;
            t_max_y += t_delta_y;
        }
        visit(cell);
        if opaque(cell) {
            return false;
        }
    }
}

/// Whether `b` can be seen from `a`: no opaque cell strictly between their
/// centres and no diagonal squeeze between two opaque cells. The end cells
/// themselves may be opaque (a wall is visible).
///
/// Complexity: O(|a − b|).
pub fn line_of_sight(a: Cell, b: Cell, opaque: impl Fn(Cell) -> bool) -> bool {
    if a == b {
        return true;
    }
    let target = (f64::from(b.x) + 0.5, f64::from(b.y) + 0.5);
    walk_ray(a, target, |c| c != b && opaque(c), |_| {})
}

/// A planar range sensor: a fan of rays of limited range (Burgard et al. 2005
/// §IV-C use 360° sensors; §IV-B also a 180° laser).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RangeSensor {
    /// Maximum range, in cells.
    pub range_cells: f64,
    /// Field of view, radians, centred on the heading (2π for all around).
    pub field_of_view: f64,
}

impl RangeSensor {
    /// Casts rays from the centre of `origin` looking along `heading`, dense
    /// enough that every cell within range and view is crossed by at least
    /// one ray (angular step below 1/(2·range)). `visit(cell, hit)` is called
    /// for every cell a ray crosses, possibly more than once, with `hit` true
    /// for the opaque cell that stops a ray.
    ///
    /// Complexity: O(range²) cell visits.
    pub fn scan(&self, origin: Cell, heading: f64, opaque: impl Fn(Cell) -> bool, mut visit: impl FnMut(Cell, bool)) {
        let range = self.range_cells.max(0.0);
        if range < 0.5 {
            visit(origin, false);
            return;
        }
        let fov = self.field_of_view.clamp(0.0, std::f64::consts::TAU);
        let rays = ((fov * 2.0 * range).ceil() as usize).max(1) + 1;
        let full_circle = fov >= std::f64::consts::TAU - 1e-9;
        let start = if full_circle { 0.0 } else { heading - fov / 2.0 };
        let step = if full_circle { fov / rays as f64 } else { fov / (rays - 1) as f64 };
        let (cx, cy) = (f64::from(origin.x) + 0.5, f64::from(origin.y) + 0.5);
        let range_sq = range * range;
        for k in 0..rays {
            let angle = start + step * k as f64;
            let end = (cx + range * angle.cos(), cy + range * angle.sin());
            walk_ray(origin, end, &opaque, |cell| {
                let (ex, ey) = (f64::from(cell.x) + 0.5 - cx, f64::from(cell.y) + 0.5 - cy);
                if ex * ex + ey * ey <= range_sq {
                    visit(cell, cell != origin && opaque(cell));
                }
            });
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::collections::HashSet;

    #[test]
    fn a_ray_visits_every_cell_it_crosses() {
        let mut cells = Vec::new();
        let reached = walk_ray(Cell::new(0, 0), (4.5, 2.5), |_| false, |c| cells.push(c));
        assert!(reached);
        assert_eq!(cells.first(), Some(&Cell::new(0, 0)));
        assert_eq!(cells.last(), Some(&Cell::new(4, 2)));
        // 4-connected walk: each step changes one coordinate by one.
        for pair in cells.windows(2) {
            let d = (pair[1].x - pair[0].x).abs() + (pair[1].y - pair[0].y).abs();
            assert_eq!(d, 1, "{pair:?}");
        }
    }

    #[test]
    fn walls_block_and_diagonal_squeezes_are_closed() {
        let wall = |c: Cell| c == Cell::new(2, 0);
        assert!(!line_of_sight(Cell::new(0, 0), Cell::new(4, 0), wall));
        assert!(line_of_sight(Cell::new(0, 0), Cell::new(2, 0), wall), "a wall is itself visible");
        // Two walls touching at a corner close the diagonal between them.
        let corner = |c: Cell| c == Cell::new(1, 0) || c == Cell::new(0, 1);
        assert!(!line_of_sight(Cell::new(0, 0), Cell::new(2, 2), corner));
        let one_side = |c: Cell| c == Cell::new(1, 0);
        assert!(line_of_sight(Cell::new(0, 0), Cell::new(2, 2), one_side));
    }

    #[test]
    fn a_full_circle_scan_leaves_no_hole_in_open_space() {
        let sensor = RangeSensor { range_cells: 30.0, field_of_view: std::f64::consts::TAU };
        let origin = Cell::new(0, 0);
        let mut seen = HashSet::new();
        sensor.scan(
            origin,
            0.0,
            |_| false,
            |c, _| {
                seen.insert(c);
            },
        );
        for x in -30..=30 {
            for y in -30..=30 {
                let inside = f64::from(x * x + y * y) <= 29.0 * 29.0;
                if inside {
                    assert!(seen.contains(&Cell::new(x, y)), "({x}, {y}) was never crossed");
                }
                if f64::from(x * x + y * y) > 30.0 * 30.0 {
                    assert!(!seen.contains(&Cell::new(x, y)), "({x}, {y}) is out of range");
                }
            }
        }
    }

    #[test]
    fn a_half_circle_scan_sees_only_ahead_and_walls_cast_shadows() {
        let sensor = RangeSensor { range_cells: 10.0, field_of_view: std::f64::consts::PI };
        let wall = |c: Cell| c.x == 3 && (-1..=1).contains(&c.y);
        let mut seen = HashSet::new();
        let mut hits = HashSet::new();
        sensor.scan(Cell::new(0, 0), 0.0, wall, |c, hit| {
            seen.insert(c);
            if hit {
                hits.insert(c);
            }
        });
        assert!(seen.iter().all(|c| c.x >= 0), "a 180° sensor facing +x sees nothing behind");
        assert!(hits.contains(&Cell::new(3, 0)));
        assert!(!seen.contains(&Cell::new(6, 0)), "the wall hides what is behind it");
        assert!(seen.contains(&Cell::new(0, 8)));
    }
}
