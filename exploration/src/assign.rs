//! Optimal assignment: the linear sum assignment problem.
//!
//! The Hungarian method (Kuhn 1955) as Wurm et al. 2008, §III and Ko et al.
//! (cited by Burgard et al. 2005, §V) use it to assign robots to frontier
//! targets or segments: minimize Σ C[i][a(i)] over assignments of rows
//! (robots) to distinct columns (targets). We solve it by shortest
//! augmenting paths with dual potentials (Jonker & Volgenant 1987; the
//! rectangular form of Crouse 2016, which scipy's `linear_sum_assignment`
//! implements; square matrices start from Jonker & Volgenant's column
//! reduction and reduction transfer), an O(n²·m) algorithm with the same optimum as the
//! Hungarian method and far less work in practice. Unequal counts need no
//! explicit dummy rows: with more columns than rows every row is assigned;
//! with more rows, the matrix is transposed and surplus rows stay
//! unassigned. Forbidden pairs are `f64::INFINITY` (Wurm et al. Eq. 4);
//! [`assign_with_dummies`] adds dummy columns so that rows with no finite
//! choice are left unassigned rather than making the problem infeasible.

/// An optimal assignment.
#[derive(Debug, Clone, PartialEq)]
pub struct Assignment {
    /// For each row, its column, or `None` when it got none.
    pub row_to_col: Vec<Option<usize>>,
    /// Σ of the assigned costs.
    pub total: f64,
}

/// Why no assignment exists.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum AssignError {
    /// The matrix does not hold rows × cols values.
    #[error("the cost matrix holds {got} values, not {rows}×{cols}")]
    Shape {
        /// Rows given.
        rows: usize,
        /// Columns given.
        cols: usize,
        /// Values given.
        got: usize,
    },
    /// A cost is NaN or −∞.
    #[error("cost ({row}, {col}) is {value}; costs must be finite or +∞")]
    BadCost {
        /// Its row.
        row: usize,
        /// Its column.
        col: usize,
        /// Its value.
        value: f64,
    },
    /// Forbidden pairs leave some row without a column.
    #[error("no assignment avoids every forbidden (infinite) pair")]
    Infeasible,
}

/// Minimum-cost assignment of rows to distinct columns of a row-major
/// `rows × cols` matrix; when `rows > cols`, every column gets a row and the
/// other rows none. Ties are broken towards lower column indices.
///
/// Complexity: O(k²·l) for k = min(rows, cols), l = max(rows, cols).
///
/// # Example
/// ```
/// use exploration::assign::linear_sum_assignment;
/// // Two robots, three targets.
/// let costs = [4.0, 1.0, 3.0, 2.0, 0.0, 5.0];
/// let a = linear_sum_assignment(&costs, 2, 3).unwrap();
/// assert_eq!(a.row_to_col, vec![Some(1), Some(0)]);
/// assert_eq!(a.total, 3.0);
/// ```
pub fn linear_sum_assignment(costs: &[f64], rows: usize, cols: usize) -> Result<Assignment, AssignError> {
    if costs.len() != rows * cols {
        return Err(AssignError::Shape { rows, cols, got: costs.len() });
    }
    if let Some((k, &value)) = costs.iter().enumerate().find(|(_, c)| c.is_nan() || **c == f64::NEG_INFINITY) {
        return Err(AssignError::BadCost { row: k / cols.max(1), col: k % cols.max(1), value });
    }
    if rows == 0 || cols == 0 {
        return Ok(Assignment { row_to_col: vec![None; rows], total: 0.0 });
    }
    if rows <= cols {
        let col4row = shortest_augmenting_paths(costs, rows, cols)?;
        let total = col4row.iter().enumerate().map(|(i, &j)| costs[i * cols + j]).sum();
        return Ok(Assignment { row_to_col: col4row.into_iter().map(Some).collect(), total });
    }
    // More rows than columns: solve the transpose, each column picks a row.
    let mut transposed = vec![0.0; costs.len()];
    for i in 0..rows {
        for j in 0..cols {
            transposed[j * rows + i] = costs[i * cols + j];
        }
    }
    let row4col = shortest_augmenting_paths(&transposed, cols, rows)?;
    let mut row_to_col = vec![None; rows];
    let mut total = 0.0;
    for (j, &i) in row4col.iter().enumerate() {
        row_to_col[i] = Some(j);
        total += costs[i * cols + j];
    }
    Ok(Assignment { row_to_col, total })
}

/// Like [`linear_sum_assignment`], but rows whose every finite choice is
/// taken or forbidden stay unassigned instead of failing: each row may fall
/// back on a dummy column (Wurm et al. 2008, §III's "dummy machines") that
/// costs more than any feasible assignment of the real ones.
pub fn assign_with_dummies(costs: &[f64], rows: usize, cols: usize) -> Result<Assignment, AssignError> {
    if costs.len() != rows * cols {
        return Err(AssignError::Shape { rows, cols, got: costs.len() });
    }
    let finite_total: f64 = costs.iter().filter(|c| c.is_finite()).map(|c| c.abs()).sum();
    let dummy = 2.0 * finite_total + 1.0;
    let wide = cols + rows;
    let mut padded = vec![dummy; rows * wide];
    for i in 0..rows {
        padded[i * wide..i * wide + cols].copy_from_slice(&costs[i * cols..(i + 1) * cols]);
    }
    let solved = linear_sum_assignment(&padded, rows, wide)?;
    let row_to_col: Vec<Option<usize>> = solved.row_to_col.into_iter().map(|c| c.filter(|&c| c < cols)).collect();
    let total = row_to_col.iter().enumerate().filter_map(|(i, c)| c.map(|c| costs[i * cols + c])).sum();
    Ok(Assignment { row_to_col, total })
}

/// Jonker & Volgenant 1987's initialization of a square matrix: column
/// reduction (each column's potential is its least cost; the row holding it
/// takes the column if it has none yet), then reduction transfer (a row that
/// won exactly one column moves the slack to its own potential). Leaves
/// feasible potentials with every assigned pair at zero reduced cost, so the
/// shortest augmenting paths only need to place the rows still free.
fn reduce_columns(costs: &[f64], n: usize, u: &mut [f64], v: &mut [f64], col4row: &mut [usize], row4col: &mut [usize]) {
    const NONE: usize = usize::MAX;
    let mut won = vec![0u32; n];
    for j in (0..n).rev() {
        let (mut best, mut at) = (f64::INFINITY, 0);
        for i in 0..n {
            let c = costs[i * n + j];
            if c < best {
                best = c;
                at = i;
            }
        }
        v[j] = best;
        won[at] += 1;
        if col4row[at] == NONE {
            col4row[at] = j;
            row4col[j] = at;
        }
    }
    for i in 0..n {
        let j1 = col4row[i];
        if won[i] != 1 || j1 == NONE {
            continue;
        }
        let row = &costs[i * n..(i + 1) * n];
        let slack = row
            .iter()
            .zip(v.iter())
            .enumerate()
            .filter(|(j, _)| *j != j1)
            .map(|(_, (c, vj))| c - vj)
            .fold(f64::INFINITY, f64::min);
        if slack.is_finite() {
            u[i] = slack;
            v[j1] -= slack;
        }
    }
}

/// Crouse 2016, Algorithm 1 (as in scipy): for each row in turn, a Dijkstra
/// search over reduced costs finds the shortest augmenting path; dual
/// potentials keep the reduced costs non-negative. Requires rows ≤ cols.
fn shortest_augmenting_paths(costs: &[f64], rows: usize, cols: usize) -> Result<Vec<usize>, AssignError> {
    const NONE: usize = usize::MAX;
    let mut u = vec![0.0f64; rows];
    let mut v = vec![0.0f64; cols];
    let mut col4row = vec![NONE; rows];
    let mut row4col = vec![NONE; cols];
    let mut shortest = vec![f64::INFINITY; cols];
    let mut path = vec![NONE; cols];
    let mut visited_rows = vec![false; rows];
    let mut visited_cols = vec![false; cols];
    let mut remaining: Vec<usize> = Vec::with_capacity(cols);
    let mut rows_seen: Vec<usize> = Vec::with_capacity(rows);
    let mut cols_seen: Vec<usize> = Vec::with_capacity(cols);
    if rows == cols && costs.iter().all(|c| c.is_finite()) {
        reduce_columns(costs, rows, &mut u, &mut v, &mut col4row, &mut row4col);
    }
    for current in 0..rows {
        if col4row[current] != NONE {
            continue;
        }
        shortest.fill(f64::INFINITY);
        remaining.clear();
        // Reverse order so that ties favour low column indices after swap_remove.
        remaining.extend((0..cols).rev());
        let mut min_value = 0.0f64;
        let mut i = current;
        let sink = loop {
            visited_rows[i] = true;
            rows_seen.push(i);
            let row = &costs[i * cols..(i + 1) * cols];
            let ui = u[i];
            let mut lowest = f64::INFINITY;
            let mut index = NONE;
            for (k, &j) in remaining.iter().enumerate() {
                let reduced = min_value + row[j] - ui - v[j];
                if reduced < shortest[j] {
                    path[j] = i;
                    shortest[j] = reduced;
                }
                let s = shortest[j];
                if s < lowest || (s == lowest && row4col[j] == NONE) {
                    lowest = s;
                    index = k;
                }
            }
            min_value = lowest;
            if !min_value.is_finite() {
                return Err(AssignError::Infeasible);
            }
            let j = remaining.swap_remove(index);
            visited_cols[j] = true;
            cols_seen.push(j);
            if row4col[j] == NONE {
                break j;
            }
            i = row4col[j];
        };
        // Update the dual potentials.
        u[current] += min_value;
        for &r in &rows_seen {
            visited_rows[r] = false;
            if r != current {
                u[r] += min_value - shortest[col4row[r]];
            }
        }
        for &c in &cols_seen {
            visited_cols[c] = false;
            v[c] -= min_value - shortest[c];
        }
        rows_seen.clear();
        cols_seen.clear();
        // Augment along the path back to the current row.
        let mut j = sink;
        loop {
            let i = path[j];
            row4col[j] = i;
            std::mem::swap(&mut col4row[i], &mut j);
            if i == current {
                break;
            }
        }
    }
    Ok(col4row)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::SplitMix64;

    /// Every injective assignment of the smaller side, by brute force.
    fn brute_force(costs: &[f64], rows: usize, cols: usize) -> Option<f64> {
        fn go(costs: &[f64], rows: usize, cols: usize, i: usize, used: &mut Vec<bool>, by_rows: bool) -> Option<f64> {
            let (outer, inner) = if by_rows { (rows, cols) } else { (cols, rows) };
            if i == outer {
                return Some(0.0);
            }
            let mut best: Option<f64> = None;
            for j in 0..inner {
                if used[j] {
                    continue;
                }
                let c = if by_rows { costs[i * cols + j] } else { costs[j * cols + i] };
                if !c.is_finite() {
                    continue;
                }
                used[j] = true;
                if let Some(rest) = go(costs, rows, cols, i + 1, used, by_rows) {
                    best = Some(best.map_or(c + rest, |b: f64| b.min(c + rest)));
                }
                used[j] = false;
            }
            best
        }
        let by_rows = rows <= cols;
        go(costs, rows, cols, 0, &mut vec![false; rows.max(cols)], by_rows)
    }

    #[test]
    fn a_small_square_case_by_hand() {
        // Kuhn's example shape: the optimum avoids the greedy first choice.
        let costs = [1.0, 2.0, 3.0, 2.0, 4.0, 6.0, 3.0, 6.0, 9.0];
        let a = linear_sum_assignment(&costs, 3, 3).unwrap();
        assert_eq!(a.total, 10.0);
        let mut cols: Vec<_> = a.row_to_col.iter().map(|c| c.unwrap()).collect();
        cols.sort_unstable();
        assert_eq!(cols, vec![0, 1, 2]);
    }

    #[test]
    fn more_rows_than_columns_leave_rows_unassigned() {
        // Three robots, two targets: the two cheapest distinct pairs win.
        let costs = [5.0, 9.0, 1.0, 8.0, 7.0, 2.0];
        let a = linear_sum_assignment(&costs, 3, 2).unwrap();
        assert_eq!(a.row_to_col, vec![None, Some(0), Some(1)]);
        assert_eq!(a.total, 3.0);
    }

    #[test]
    fn forbidden_pairs_are_avoided_or_reported() {
        let inf = f64::INFINITY;
        let costs = [inf, 1.0, 2.0, inf];
        let a = linear_sum_assignment(&costs, 2, 2).unwrap();
        assert_eq!(a.row_to_col, vec![Some(1), Some(0)]);
        let blocked = [inf, 1.0, inf, 1.0];
        assert_eq!(linear_sum_assignment(&blocked, 2, 2), Err(AssignError::Infeasible));
        let a = assign_with_dummies(&blocked, 2, 2).unwrap();
        assert_eq!(a.row_to_col.iter().filter(|c| c.is_some()).count(), 1);
        assert_eq!(a.total, 1.0);
        assert!(matches!(linear_sum_assignment(&[f64::NAN], 1, 1), Err(AssignError::BadCost { .. })));
        assert!(matches!(linear_sum_assignment(&[1.0], 1, 2), Err(AssignError::Shape { .. })));
    }

    proptest::proptest! {
        #![proptest_config(crate::testing::seeded_proptest(400))]
        /// The optimum equals brute force on small random matrices,
        /// rectangular both ways, with and without forbidden pairs.
        #[test]
        fn matches_brute_force(rows in 1usize..6, cols in 1usize..6, seed in 0u64..u64::MAX, forbid in 0u64..4) {
            let mut rng = SplitMix64::new(seed);
            let costs: Vec<f64> = (0..rows * cols)
                .map(|_| if rng.below(10) < forbid { f64::INFINITY } else { (rng.below(1000) as f64) / 10.0 })
                .collect();
            let expected = brute_force(&costs, rows, cols);
            match (linear_sum_assignment(&costs, rows, cols), expected) {
                (Ok(a), Some(best)) => {
                    proptest::prop_assert!((a.total - best).abs() < 1e-9, "{} vs {}", a.total, best);
                    let cols_used: Vec<usize> = a.row_to_col.iter().flatten().copied().collect();
                    let mut unique = cols_used.clone();
                    unique.sort_unstable();
                    unique.dedup();
                    proptest::prop_assert_eq!(unique.len(), cols_used.len());
                    proptest::prop_assert_eq!(cols_used.len(), rows.min(cols));
                }
                (Err(AssignError::Infeasible), None) => {}
                (got, want) => proptest::prop_assert!(false, "got {:?}, brute force {:?}", got, want),
            }
        }
    }
}
