//! The benchmark inputs of `../shared/bench/peers.py`, generator "gen v1",
//! regenerated bit for bit so that our figures and the peers' are measured
//! on the same problems.

#![allow(dead_code)]

use exploration::rng::SplitMix64;

/// ROS map_server values of the occupancy grids.
pub const FREE: u8 = 254;
/// Occupied.
pub const OCC: u8 = 0;
/// Unknown.
pub const UNKNOWN: u8 = 205;

/// `obstacles(H, W, seed)`: row-major, true = occupied.
pub fn obstacles(h: usize, w: usize, seed: u64) -> Vec<bool> {
    let mut occ = vec![false; h * w];
    let mut rng = SplitMix64::new(seed);
    for _ in 0..(h * w) / 5000 {
        let y0 = rng.below(h as u64) as usize;
        let x0 = rng.below(w as u64) as usize;
        let rh = 4 + rng.below(57) as usize;
        let rw = 4 + rng.below(57) as usize;
        for y in y0..(y0 + rh).min(h) {
            occ[y * w + x0..y * w + (x0 + rw).min(w)].fill(true);
        }
    }
    let (cy, cx) = (h / 2, w / 2);
    for y in cy.saturating_sub(10)..(cy + 11).min(h) {
        occ[y * w + cx.saturating_sub(10)..y * w + (cx + 11).min(w)].fill(false);
    }
    occ
}

/// `occupancy(H, W, seed)`: half-explored grid of FREE / OCC / UNKNOWN.
pub fn occupancy(h: usize, w: usize, seed: u64) -> Vec<u8> {
    let truth = obstacles(h, w, seed);
    let mut known = vec![false; h * w];
    let mut n_known = 0usize;
    let mut rng = SplitMix64::new(seed.wrapping_add(1));
    let (mut y, mut x) = ((h / 2) as i64, (w / 2) as i64);
    while 2 * n_known < h * w {
        let r = 40 + rng.below(81) as i64;
        let (ya, yb) = ((y - r).max(0), (y + r).min(h as i64 - 1));
        let (xa, xb) = ((x - r).max(0), (x + r).min(w as i64 - 1));
        for yy in ya..=yb {
            for xx in xa..=xb {
                if (yy - y) * (yy - y) + (xx - x) * (xx - x) <= r * r {
                    let i = yy as usize * w + xx as usize;
                    if !known[i] {
                        known[i] = true;
                        n_known += 1;
                    }
                }
            }
        }
        y = (y + rng.below(241) as i64 - 120).clamp(0, h as i64 - 1);
        x = (x + rng.below(241) as i64 - 120).clamp(0, w as i64 - 1);
    }
    (0..h * w)
        .map(|i| match (known[i], truth[i]) {
            (false, _) => UNKNOWN,
            (true, true) => OCC,
            (true, false) => FREE,
        })
        .collect()
}

/// `lsap_cost(R, C, seed)`: the integer costs q (31-bit) and the float costs q / 2^31.
pub fn lsap(rows: usize, cols: usize, seed: u64) -> (Vec<i64>, Vec<f64>) {
    let mut rng = SplitMix64::new(seed ^ ((rows as u64) << 32) ^ cols as u64);
    let q: Vec<i64> = (0..rows * cols).map(|_| (rng.next_u64() >> 33) as i64).collect();
    let f = q.iter().map(|&v| v as f64 / f64::from(1u32 << 31)).collect();
    (q, f)
}
