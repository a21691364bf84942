//! The skeleton of the free space: its exact Euclidean distance transform
//! (Felzenszwalb & Huttenlocher 2012) and distance-ordered homotopic
//! thinning (Pudney 1998), on which [`super::segment`] finds the critical
//! points of Wurm et al. 2008, §IV.

/// Squared Euclidean distance, in cells², from every `true` cell of a
/// row-major `width × height` mask to the nearest `false` cell; 0 on `false`
/// cells; `u32::MAX` where the mask holds no `false` cell at all. Cells
/// beyond the edge do not count as `false` (scipy's
/// `distance_transform_edt` convention).
///
/// Felzenszwalb & Huttenlocher 2012: a column pass, then the lower envelope
/// of parabolas along each row. Complexity: O(W·H).
pub fn distance_transform(mask: &[bool], width: usize, height: usize) -> Vec<u32> {
    assert_eq!(mask.len(), width * height, "one flag per cell");
    const FAR: u64 = u64::MAX / 4;
    // Column pass, as row sweeps: vertical distance to the nearest `false`.
    let mut vertical = vec![u32::MAX; mask.len()];
    let mut run = vec![u32::MAX; width];
    for y in 0..height {
        let row = &mask[y * width..(y + 1) * width];
        for (x, r) in run.iter_mut().enumerate() {
            *r = if row[x] { r.saturating_add(1) } else { 0 };
        }
        vertical[y * width..(y + 1) * width].copy_from_slice(&run);
    }
    run.fill(u32::MAX);
    for y in (0..height).rev() {
        let row = &mask[y * width..(y + 1) * width];
        let out = &mut vertical[y * width..(y + 1) * width];
        for x in 0..width {
            run[x] = if row[x] { run[x].saturating_add(1) } else { 0 };
            out[x] = out[x].min(run[x]);
        }
    }
    // Row pass: lower envelope of the parabolas (x − q)² + g(q).
    let mut out = vec![0u32; mask.len()];
    let mut g = vec![0u64; width];
    let mut hull = vec![0usize; width];
    let mut bounds = vec![0f64; width + 1];
    for y in 0..height {
        let vrow = &vertical[y * width..(y + 1) * width];
        for (gx, &v) in g.iter_mut().zip(vrow) {
            *gx = if v == u32::MAX { FAR } else { u64::from(v) * u64::from(v) };
        }
        let mut k = 0usize;
        let mut count = 0usize;
        for q in 0..width {
            if g[q] >= FAR {
                continue;
            }
            if count == 0 {
                hull[0] = q;
                bounds[0] = f64::NEG_INFINITY;
                bounds[1] = f64::INFINITY;
                count = 1;
                k = 0;
                continue;
            }
            loop {
                let p = hull[k];
                let s =
                    ((g[q] as f64 + (q * q) as f64) - (g[p] as f64 + (p * p) as f64)) / (2.0 * (q as f64 - p as f64));
                if s <= bounds[k] && k > 0 {
                    k -= 1;
                    continue;
                }
                if s <= bounds[k] {
                    // k == 0: the new parabola dominates everything.
                    hull[0] = q;
                    bounds[0] = f64::NEG_INFINITY;
                    bounds[1] = f64::INFINITY;
                    break;
                }
                k += 1;
                hull[k] = q;
                bounds[k] = s;
                bounds[k + 1] = f64::INFINITY;
                break;
            }
            count = k + 1;
        }
        let row_out = &mut out[y * width..(y + 1) * width];
        if count == 0 {
            row_out.fill(u32::MAX);
            continue;
        }
        let mut k = 0usize;
        for (x, o) in row_out.iter_mut().enumerate() {
            while bounds[k + 1] < x as f64 {
                k += 1;
            }
            let p = hull[k];
            let dx = x.abs_diff(p) as u64;
            *o = u32::try_from(dx * dx + g[p]).unwrap_or(u32::MAX);
        }
    }
    out
}

/// Whether the centre of a 3 × 3 neighbourhood is a simple point: removing
/// it changes neither the 8-connected foreground nor the 4-connected
/// background. Bit k of `code` is neighbour k in ring order (north, then
/// clockwise). The foreground ring must form one 8-connected arc and the
/// centre must touch the background through an edge.
fn simple_points() -> [bool; 256] {
    // Ring order: N, NE, E, SE, S, SW, W, NW; edges are the even positions.
    let mut table = [false; 256];
    for (code, simple) in table.iter_mut().enumerate() {
        let set = |k: usize| code >> (k % 8) & 1 == 1;
        let edge_background = (0..8).step_by(2).any(|k| !set(k));
        if !edge_background {
            continue;
        }
        // The foreground ring cells must be one 8-connected group.
        let mut visited = [false; 8];
        let mut components = 0;
        for start in 0..8 {
            if !set(start) || visited[start] {
                continue;
            }
            components += 1;
            let mut stack = vec![start];
            visited[start] = true;
            while let Some(k) = stack.pop() {
                // Neighbours on the ring that are 8-adjacent to ring cell k.
                let candidates: &[usize] = if k % 2 == 0 { &[1, 2, 6, 7] } else { &[1, 7] };
                for &d in candidates {
                    let m = (k + d) % 8;
                    if set(m) && !visited[m] {
                        visited[m] = true;
                        stack.push(m);
                    }
                }
            }
        }
        *simple = components == 1;
    }
    table
}

/// Thins the `true` region of a row-major mask to a one-pixel-wide skeleton
/// with the same topology, by distance-ordered homotopic thinning (Pudney
/// 1998): pixels are visited from the boundary inwards, in order of their
/// distance to the background, and removed when they are simple points and
/// not the end of a line. What remains runs along the ridge of the distance
/// transform, an approximation of the medial axis whose Voronoi graph
/// Wurm et al. 2008 (§IV) segment. Cells beyond the edge count as `false`.
///
/// Complexity: O(W·H): one distance transform, a counting sort, and each
/// pixel examined a small number of times.
pub fn skeletonize(mask: &[bool], width: usize, height: usize) -> Vec<bool> {
    assert_eq!(mask.len(), width * height, "one flag per cell");
    let stride = width + 2;
    let mut image = vec![false; stride * (height + 2)];
    for y in 0..height {
        image[(y + 1) * stride + 1..(y + 1) * stride + 1 + width].copy_from_slice(&mask[y * width..(y + 1) * width]);
    }
    // Distances with the border as background, so every pixel has one.
    let squared = distance_transform(&image, stride, height + 2);
    thin(&mut image, stride, &squared);
    let mut out = vec![false; width * height];
    for y in 0..height {
        out[y * width..(y + 1) * width].copy_from_slice(&image[(y + 1) * stride + 1..(y + 1) * stride + 1 + width]);
    }
    out
}

/// The thinning of [`skeletonize`] in place, on an image whose outermost
/// rows and columns are background, given its squared distance transform.
fn thin(image: &mut [bool], stride: usize, squared: &[u32]) {
    let simple = simple_points();
    let offsets: [isize; 8] = [
        -(stride as isize),
        -(stride as isize) + 1,
        1,
        stride as isize + 1,
        stride as isize,
        stride as isize - 1,
        -1,
        -(stride as isize) - 1,
    ];
    let code = |image: &[bool], i: usize| {
        offsets
            .iter()
            .enumerate()
            .fold(0usize, |acc, (k, &o)| acc | (usize::from(image[(i as isize + o) as usize]) << k))
    };
    // Counting sort of the foreground by squared distance.
    let max = squared.iter().zip(image.iter()).filter(|(_, f)| **f).map(|(d, _)| *d).max().unwrap_or(0) as usize;
    let mut starts = vec![0usize; max + 2];
    for (i, &f) in image.iter().enumerate() {
        if f {
            starts[squared[i] as usize + 1] += 1;
        }
    }
    for k in 1..starts.len() {
        starts[k] += starts[k - 1];
    }
    let mut order = vec![0u32; starts[max + 1]];
    let mut fill = starts.clone();
    for (i, &f) in image.iter().enumerate() {
        if f {
            let d = squared[i] as usize;
            order[fill[d]] = i as u32;
            fill[d] += 1;
        }
    }
    let mut queue: Vec<usize> = Vec::new();
    let mut again: Vec<usize> = Vec::new();
    for level in 0..=max {
        queue.clear();
        queue.extend(order[starts[level]..starts[level + 1]].iter().map(|&i| i as usize));
        // Within a level, repeat until nothing more goes: a removal can make
        // a neighbour simple.
        loop {
            let mut removed = false;
            again.clear();
            for &i in &queue {
                if !image[i] {
                    continue;
                }
                let c = code(image, i);
                let end = c.count_ones() == 1;
                if !end && simple[c] {
                    image[i] = false;
                    removed = true;
                } else {
                    again.push(i);
                }
            }
            if !removed {
                break;
            }
            std::mem::swap(&mut queue, &mut again);
        }
    }
}

/// The skeleton of a free-space mask and its squared distance transform,
/// both padded by one background cell on every side: the grid's edge is a
/// wall. What [`super::segment`] works on.
pub fn padded_skeleton(free: &[bool], width: usize, height: usize) -> (Vec<bool>, Vec<u32>) {
    let (pw, ph) = (width + 2, height + 2);
    let mut padded = vec![false; pw * ph];
    for y in 0..height {
        padded[(y + 1) * pw + 1..(y + 1) * pw + 1 + width].copy_from_slice(&free[y * width..(y + 1) * width]);
    }
    let squared = distance_transform(&padded, pw, ph);
    thin(&mut padded, pw, &squared);
    (padded, squared)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::grid::NEIGHBOURS_8;

    fn brute_force_squared(mask: &[bool], w: usize, h: usize) -> Vec<u32> {
        let background: Vec<(usize, usize)> = (0..w * h).filter(|&i| !mask[i]).map(|i| (i % w, i / w)).collect();
        (0..w * h)
            .map(|i| {
                if !mask[i] {
                    return 0;
                }
                let (x, y) = (i % w, i / w);
                background
                    .iter()
                    .map(|&(bx, by)| (bx.abs_diff(x) * bx.abs_diff(x) + by.abs_diff(y) * by.abs_diff(y)) as u32)
                    .min()
                    .unwrap_or(u32::MAX)
            })
            .collect()
    }

    proptest::proptest! {
        #![proptest_config(crate::testing::seeded_proptest(200))]
        /// The linear-time transform equals the brute-force minimum.
        #[test]
        fn distance_transform_is_exact(w in 1usize..20, h in 1usize..20, seed in 0u64..u64::MAX, density in 0u64..10) {
            let mut rng = crate::rng::SplitMix64::new(seed);
            let mask: Vec<bool> = (0..w * h).map(|_| rng.below(10) >= density).collect();
            proptest::prop_assert_eq!(distance_transform(&mask, w, h), brute_force_squared(&mask, w, h));
        }

        /// Thinning never adds a pixel and never splits a region in two.
        #[test]
        fn skeletons_never_split_a_region(w in 3usize..24, h in 3usize..24, seed in 0u64..u64::MAX) {
            let mut rng = crate::rng::SplitMix64::new(seed);
            let mask: Vec<bool> = (0..w * h).map(|_| rng.below(10) < 8).collect();
            let skeleton = skeletonize(&mask, w, h);
            proptest::prop_assert!(skeleton.iter().zip(&mask).all(|(&s, &m)| !s || m));
            let labels = |m: &[bool]| {
                let mut label = vec![0usize; m.len()];
                let mut n = 0;
                for s in 0..m.len() {
                    if !m[s] || label[s] != 0 { continue; }
                    n += 1;
                    let mut stack = vec![s];
                    label[s] = n;
                    while let Some(i) = stack.pop() {
                        let (x, y) = ((i % w) as i64, (i / w) as i64);
                        for (dx, dy) in NEIGHBOURS_8 {
                            let (nx, ny) = (x + i64::from(dx), y + i64::from(dy));
                            if nx < 0 || ny < 0 || nx >= w as i64 || ny >= h as i64 { continue; }
                            let j = ny as usize * w + nx as usize;
                            if m[j] && label[j] == 0 { label[j] = n; stack.push(j); }
                        }
                    }
                }
                label
            };
            let (regions, pieces) = (labels(&mask), labels(&skeleton));
            let mut piece_of_region = std::collections::HashMap::new();
            for i in 0..w * h {
                if skeleton[i] {
                    let piece = *piece_of_region.entry(regions[i]).or_insert(pieces[i]);
                    proptest::prop_assert_eq!(piece, pieces[i], "region {} split", regions[i]);
                }
            }
        }
    }

    #[test]
    fn a_thick_bar_thins_to_a_line() {
        let (w, h) = (20, 7);
        let mask: Vec<bool> = (0..w * h).map(|i| (1..6).contains(&(i / w)) && (1..19).contains(&(i % w))).collect();
        let skeleton = skeletonize(&mask, w, h);
        let cells: Vec<(usize, usize)> = (0..w * h).filter(|&i| skeleton[i]).map(|i| (i % w, i / w)).collect();
        let middle: Vec<usize> = cells.iter().filter(|c| c.1 == 3).map(|c| c.0).collect();
        // The middle row carries the skeleton from end to end; at most short
        // spurs reach into the corners, as the medial axis of a rectangle does.
        assert!((3..=16).all(|x| middle.contains(&x)), "{cells:?}");
        assert!(cells.len() <= middle.len() + 8, "{cells:?}");
    }
}
