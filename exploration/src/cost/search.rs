//! How a search steps from cell to cell and in which order it settles
//! them: the step masks, the three neighbourhoods (forward over per-cell
//! costs, forward over uniform costs, and reversed, from goals), Dial's
//! buckets and the binary heap they fall back to.

use std::collections::BinaryHeap;

use super::{TraversalMap, Window};

/// The eight steps of a padded grid in the order searches relax them:
/// orthogonal first, then diagonal, each diagonal with its two side cells.
pub(super) struct Moves;

impl Moves {
    /// Index offsets of the eight steps, for rows of `stride` cells.
    #[inline(always)]
    pub(super) fn offsets(stride: usize) -> [isize; 8] {
        let s = stride as isize;
        [1, -1, s, -s, s + 1, s - 1, -s + 1, -s - 1]
    }

    /// Calls `step(j, diagonal)` for each neighbour `j` of `i` whose bit is
    /// set in `mask`, in the order of [`Self::offsets`]. Written out step by
    /// step: searches over uniform steps ran an eighth faster than with a
    /// loop (the replan bench's office).
    #[inline(always)]
    fn each(mask: u8, i: usize, stride: usize, mut step: impl FnMut(usize, bool)) {
        let [o0, o1, o2, o3, o4, o5, o6, o7] = Self::offsets(stride);
        if mask & 1 != 0 {
            step(i.wrapping_add_signed(o0), false);
        }
        if mask & 2 != 0 {
            step(i.wrapping_add_signed(o1), false);
        }
        if mask & 4 != 0 {
            step(i.wrapping_add_signed(o2), false);
        }
        if mask & 8 != 0 {
            step(i.wrapping_add_signed(o3), false);
        }
        if mask & 16 != 0 {
            step(i.wrapping_add_signed(o4), true);
        }
        if mask & 32 != 0 {
            step(i.wrapping_add_signed(o5), true);
        }
        if mask & 64 != 0 {
            step(i.wrapping_add_signed(o6), true);
        }
        if mask & 128 != 0 {
            step(i.wrapping_add_signed(o7), true);
        }
    }

    /// Which steps from each cell land on a passable cell without cutting a
    /// corner, and which steps into each passable cell cut none. The outer
    /// ring of the window has neither: its neighbours would be out of
    /// bounds, and nothing there is passable.
    pub(super) fn of(bits: &[u64], window: Window) -> (Vec<u8>, Vec<u8>) {
        let s = window.stride as isize;
        let offsets = Self::offsets(window.stride);
        // The side cells of each diagonal step (offsets 4..8); a step and
        // its reverse have the same two.
        let sides: [(isize, isize); 4] = [(1, s), (-1, s), (1, -s), (-1, -s)];
        let passable = |i: isize| bit(bits, i as usize);
        let mut moves = vec![0u8; window.len()];
        let mut entries = vec![0u8; window.len()];
        for r in 1..window.rows.saturating_sub(1) {
            for c in 1..window.stride - 1 {
                let i = (r * window.stride + c) as isize;
                let (mut out, mut into) = (0u8, 0u8);
                for (k, &o) in offsets.iter().enumerate() {
                    let corners_free = k < 4 || {
                        let (a, b) = sides[k - 4];
                        passable(i + a) && passable(i + b)
                    };
                    if corners_free {
                        into |= 1 << k;
                        if passable(i + o) {
                            out |= 1 << k;
                        }
                    }
                }
                moves[i as usize] = out;
                entries[i as usize] = if passable(i) { into } else { 0 };
            }
        }
        (moves, entries)
    }

    /// The cells whose every step (of `moves`) enters a cell of exactly
    /// their own cost: there a weighted step costs what a uniform one at
    /// that cost does, to the bit, so searches take such cells' steps as
    /// uniform ones (on Burgard's smoothed map, every cell away from walls
    /// and the unknown).
    pub(super) fn flat(costs: &[f32], moves: &[u8], window: Window) -> Vec<u64> {
        let offsets = Self::offsets(window.stride);
        let mut flat = vec![0u64; costs.len().div_ceil(64)];
        for (i, &m) in moves.iter().enumerate() {
            let here = costs[i];
            if m != 0
                && offsets
                    .iter()
                    .enumerate()
                    .all(|(k, &o)| m >> k & 1 == 0 || costs[i.wrapping_add_signed(o)].to_bits() == here.to_bits())
            {
                flat[i / 64] |= 1 << (i % 64);
            }
        }
        flat
    }
}

impl TraversalMap {
    pub(super) fn inbound(&self) -> Inbound<'_> {
        Inbound(self.weighted())
    }

    /// [`Self::inbound`] where every passable cell costs the same per metre
    /// (only meaningful when [`Self::is_uniform`]): the same steps at the
    /// same costs, without reading a per-cell cost.
    pub(super) fn uniform_inbound(&self) -> Uniform<'_, true> {
        self.uniform_over(&self.entries)
    }

    pub(super) fn weighted(&self) -> Weighted<'_> {
        let (orthogonal, diagonal) = self.step_lengths();
        Weighted {
            costs: &self.padded,
            bits: &self.passable_bits,
            moves: &self.moves,
            entries: &self.entries,
            flat: &self.flat,
            stride: self.window.stride,
            orthogonal,
            diagonal,
        }
    }

    /// Only meaningful when [`Self::is_uniform`].
    pub(super) fn uniform(&self) -> Uniform<'_> {
        self.uniform_over(&self.moves)
    }

    fn uniform_over<'a, const REVERSED: bool>(&'a self, steps: &'a [u8]) -> Uniform<'a, REVERSED> {
        let (orthogonal, diagonal) = self.step_lengths();
        let per_metre = self.step_range.0;
        Uniform {
            bits: &self.passable_bits,
            steps,
            stride: self.window.stride,
            orthogonal: orthogonal * per_metre,
            diagonal: diagonal * per_metre,
        }
    }
}

/// Whether bit `i` is set.
#[inline(always)]
pub(super) fn bit(bits: &[u64], i: usize) -> bool {
    bits[i / 64] >> (i % 64) & 1 != 0
}

/// The eight neighbours of a cell of a padded grid and what stepping there costs.
pub(super) trait Neighbourhood {
    /// Calls `improve(j, c)` for each neighbour `j` of `i` reachable at cost
    /// `c`; diagonal steps need both side cells passable unless `CUT`.
    fn neighbours<const CUT: bool>(&self, i: usize, here: f32, improve: impl FnMut(usize, f32));
}

/// Per-cell costs per metre.
#[derive(Clone, Copy)]
pub(super) struct Weighted<'a> {
    pub(super) costs: &'a [f32],
    pub(super) bits: &'a [u64],
    pub(super) moves: &'a [u8],
    pub(super) entries: &'a [u8],
    /// See [`TraversalMap::flat`]; empty: no cell is taken as flat.
    pub(super) flat: &'a [u64],
    pub(super) stride: usize,
    pub(super) orthogonal: f32,
    pub(super) diagonal: f32,
}

impl Neighbourhood for Weighted<'_> {
    #[inline(always)]
    fn neighbours<const CUT: bool>(&self, i: usize, here: f32, mut improve: impl FnMut(usize, f32)) {
        if !CUT {
            let moves = self.moves[i];
            if !self.flat.is_empty() && bit(self.flat, i) {
                // Every neighbour costs what this cell does: the same sums
                // as below, bit for bit, without reading their costs.
                let per_metre = self.costs[i];
                let (straight, slanted) = (here + self.orthogonal * per_metre, here + self.diagonal * per_metre);
                Moves::each(moves, i, self.stride, |j, diagonal| improve(j, if diagonal { slanted } else { straight }));
                return;
            }
            // A loop, not [`Moves::each`]: written out, Burgard's office
            // search ran 45 % slower (the bench's office, 200 robots).
            for (k, o) in Moves::offsets(self.stride).into_iter().enumerate() {
                if moves >> k & 1 != 0 {
                    let j = i.wrapping_add_signed(o);
                    let length = if k < 4 { self.orthogonal } else { self.diagonal };
                    improve(j, here + length * self.costs[j]);
                }
            }
            return;
        }
        let s = self.stride;
        for j in [i + 1, i - 1, i + s, i - s] {
            if bit(self.bits, j) {
                improve(j, here + self.orthogonal * self.costs[j]);
            }
        }
        for (j, a, b) in
            [(i + s + 1, i + 1, i + s), (i + s - 1, i - 1, i + s), (i - s + 1, i + 1, i - s), (i - s - 1, i - 1, i - s)]
        {
            if bit(self.bits, j) && (CUT || (bit(self.bits, a) && bit(self.bits, b))) {
                improve(j, here + self.diagonal * self.costs[j]);
            }
        }
    }
}

/// The same cost per metre everywhere passable: only the step masks (or,
/// for searches that cut corners, the passability bits) are read, no
/// per-cell cost. `REVERSED`: the steps of [`Inbound`] over such a
/// traversal, from goals (a complete search from each open segment for
/// `segmentation`, over the whole known window).
pub(super) struct Uniform<'a, const REVERSED: bool = false> {
    bits: &'a [u64],
    /// Per cell, the steps out of it that cut no corner, or, reversed, the
    /// steps into it.
    steps: &'a [u8],
    stride: usize,
    orthogonal: f32,
    diagonal: f32,
}

impl<const REVERSED: bool> Neighbourhood for Uniform<'_, REVERSED> {
    #[inline(always)]
    fn neighbours<const CUT: bool>(&self, i: usize, here: f32, mut improve: impl FnMut(usize, f32)) {
        let straight = here + self.orthogonal;
        let slanted = here + self.diagonal;
        if !CUT {
            Moves::each(self.steps[i], i, self.stride, |j, diagonal| {
                improve(j, if diagonal { slanted } else { straight });
            });
            return;
        }
        let s = self.stride;
        if REVERSED {
            // Nothing enters an impassable cell; a passable one is off the
            // window's border, so its neighbours are in bounds.
            if !bit(self.bits, i) {
                return;
            }
            for j in [i + 1, i - 1, i + s, i - s] {
                improve(j, straight);
            }
            for j in [i + s + 1, i + s - 1, i - s + 1, i - s - 1] {
                improve(j, slanted);
            }
            return;
        }
        for j in [i + 1, i - 1, i + s, i - s] {
            if bit(self.bits, j) {
                improve(j, straight);
            }
        }
        for (j, a, b) in
            [(i + s + 1, i + 1, i + s), (i + s - 1, i - 1, i + s), (i - s + 1, i + 1, i - s), (i - s - 1, i - 1, i - s)]
        {
            if bit(self.bits, j) && (CUT || (bit(self.bits, a) && bit(self.bits, b))) {
                improve(j, slanted);
            }
        }
    }
}

/// The steps of [`Weighted`] taken backwards: relaxing from `i` offers each
/// neighbour `j` the cost of the step j → i (entering `i`). A search over
/// it from a set of goals gives every cell its cost to the nearest goal, on
/// the same steps and corner rule as the forward searches.
pub(super) struct Inbound<'a>(Weighted<'a>);

impl Neighbourhood for Inbound<'_> {
    #[inline(always)]
    fn neighbours<const CUT: bool>(&self, i: usize, here: f32, mut improve: impl FnMut(usize, f32)) {
        let Weighted { costs, bits, entries, stride: s, orthogonal, diagonal, .. } = self.0;
        if !CUT {
            // Nothing enters an impassable cell (no entries).
            let entries = entries[i];
            if entries == 0 {
                return;
            }
            let straight = here + orthogonal * costs[i];
            let slanted = here + diagonal * costs[i];
            Moves::each(entries, i, s, |j, diagonal| improve(j, if diagonal { slanted } else { straight }));
            return;
        }
        // Nothing enters an impassable cell. A passable one is off the
        // window's border, so its neighbours are in bounds.
        if !bit(bits, i) {
            return;
        }
        let straight = here + orthogonal * costs[i];
        for j in [i + 1, i - 1, i + s, i - s] {
            improve(j, straight);
        }
        let slanted = here + diagonal * costs[i];
        for (j, a, b) in
            [(i + s + 1, i + 1, i + s), (i + s - 1, i - 1, i + s), (i - s + 1, i + 1, i - s), (i - s - 1, i - 1, i - s)]
        {
            if CUT || (bit(bits, a) && bit(bits, b)) {
                improve(j, slanted);
            }
        }
    }
}

/// Settles every label from `starts`; `steps` is the cheapest and the
/// dearest single step. Buckets when a small ring holds the step range, a
/// binary heap otherwise.
pub(super) fn settle<N: Neighbourhood, const CUT: bool>(
    n: &N,
    cost: &mut [f32],
    labels: &mut [u32],
    starts: &[usize],
    steps: (f32, f32),
) {
    match Buckets::fitting(starts, steps) {
        Some(mut b) if labels.is_empty() => b.drain::<N, CUT, false>(n, cost, labels),
        Some(mut b) => b.drain::<N, CUT, true>(n, cost, labels),
        None => heap::<N, CUT>(n, cost, labels, starts),
    }
}

/// A ring of buckets as wide as the cheapest step (Dial 1969), kept between
/// drains so that a search towards goals can stop at a radius and resume
/// later (see [`GrowingCostMap`]).
#[derive(Debug)]
pub(super) struct Buckets {
    rings: Vec<Vec<u32>>,
    slot_mask: usize,
    per_bucket: f32,
    /// The bucket being drained: every cell of a lower bucket is settled.
    pub(super) current: usize,
    pending: usize,
    batch: Vec<u32>,
}

impl Buckets {
    /// Buckets for steps between `steps.0` and `steps.1`, when a ring of at
    /// most 4 096 holds that range.
    pub(super) fn fitting(starts: &[usize], steps: (f32, f32)) -> Option<Self> {
        // Slightly narrower than the cheapest step, so rounding never puts a
        // relaxed cell into the bucket being drained.
        let width = steps.0 * (1.0 - 1e-5);
        if !(width > 0.0 && width.is_finite()) {
            return None;
        }
        let ring = ((steps.1 / width).ceil() as usize).saturating_add(2);
        (ring <= 4096).then(|| Self::new(starts, width, ring))
    }

    fn new(starts: &[usize], width: f32, ring: usize) -> Self {
        // A power-of-two ring turns the bucket's slot into a mask.
        let ring = ring.next_power_of_two();
        let mut rings: Vec<Vec<u32>> = vec![Vec::new(); ring];
        rings[0].extend(starts.iter().map(|&i| i as u32));
        Self {
            rings,
            slot_mask: ring - 1,
            per_bucket: 1.0 / width,
            current: 0,
            pending: starts.len(),
            batch: Vec::new(),
        }
    }

    /// Whether every reachable cell is settled.
    pub(super) fn exhausted(&self) -> bool {
        self.pending == 0
    }

    /// Every cell cheaper than this is settled, and every cell not yet
    /// settled costs at least this. One bucket short of the bucket being
    /// drained, so that rounding a cost to its bucket cannot break either.
    pub(super) fn radius(&self) -> f32 {
        if self.exhausted() { f32::INFINITY } else { self.current.saturating_sub(1) as f32 / self.per_bucket }
    }

    /// The first bucket not to drain for [`Self::radius`] to reach `radius`.
    pub(super) fn end_for(&self, radius: f32) -> usize {
        let buckets = (radius * self.per_bucket).ceil();
        if buckets.is_finite() && buckets < (usize::MAX / 2) as f32 { buckets as usize + 1 } else { usize::MAX }
    }

    /// Settles every bucket.
    pub(super) fn drain<N: Neighbourhood, const CUT: bool, const LABELLED: bool>(
        &mut self,
        n: &N,
        cost: &mut [f32],
        labels: &mut [u32],
    ) {
        self.drain_until::<N, CUT, LABELLED>(n, cost, labels, |_, _| false);
    }

    /// Settles buckets until `done(cost, radius)` holds after one, with
    /// [`Self::radius`] as it then stands, or until every bucket is.
    pub(super) fn drain_until<N: Neighbourhood, const CUT: bool, const LABELLED: bool>(
        &mut self,
        n: &N,
        cost: &mut [f32],
        labels: &mut [u32],
        mut done: impl FnMut(&[f32], f32) -> bool,
    ) {
        let Self { rings, slot_mask, per_bucket, current, pending, batch } = self;
        let (slot_mask, per_bucket) = (*slot_mask, *per_bucket);
        while *pending > 0 {
            let slot = *current & slot_mask;
            while !rings[slot].is_empty() {
                std::mem::swap(batch, &mut rings[slot]);
                *pending -= batch.len();
                for &i in batch.iter() {
                    let i = i as usize;
                    let here = cost[i];
                    // Stale entry: the cell was improved into an earlier bucket.
                    if (here * per_bucket) as usize != *current {
                        continue;
                    }
                    n.neighbours::<CUT>(i, here, |j, c| {
                        if c < cost[j] {
                            cost[j] = c;
                            if LABELLED {
                                labels[j] = labels[i];
                            }
                            rings[(c * per_bucket) as usize & slot_mask].push(j as u32);
                            *pending += 1;
                        }
                    });
                }
                batch.clear();
            }
            *current += 1;
            // The radius as `Self::radius` reads it, checked once per bucket.
            if *pending > 0 && done(cost, (*current - 1) as f32 / per_bucket) {
                break;
            }
        }
    }
}

impl Buckets {
    /// Buckets for a search ordered by cost plus a consistent estimate of
    /// the cost still to go (A*: Hart, Nilsson & Raphael 1968), from `start`
    /// whose estimate is `estimate`. Along a step the key grows by at most
    /// the step there and back: the ring must hold twice the dearest step.
    pub(super) fn guided(start: usize, estimate: f32, steps: (f32, f32)) -> Option<Self> {
        // Rounding can make a key a hair larger than consistency allows.
        let mut buckets = Self::fitting(&[start], (steps.0, 2.0 * steps.1 * 1.001))?;
        let first = (estimate * buckets.per_bucket) as usize;
        buckets.rings.swap(0, first & buckets.slot_mask);
        buckets.current = first;
        Some(buckets)
    }

    /// Settles the buckets before `end` in order of cost plus `estimate`,
    /// never expanding a cell whose estimate is infinite (it reaches no
    /// goal). A cell may be expanded again when a cell of the same bucket
    /// improves it (keys within a bucket are not in order); `open` marks
    /// the cells whose present cost is still to be expanded.
    pub(super) fn drain_guided<N: Neighbourhood>(
        &mut self,
        n: &N,
        cost: &mut [f32],
        estimate: &[f32],
        open: &mut [u64],
        end: usize,
    ) {
        let Self { rings, slot_mask, per_bucket, current, pending, batch } = self;
        let (slot_mask, per_bucket) = (*slot_mask, *per_bucket);
        while *pending > 0 && *current < end {
            let slot = *current & slot_mask;
            let floor = *current;
            while !rings[slot].is_empty() {
                std::mem::swap(batch, &mut rings[slot]);
                *pending -= batch.len();
                for &i in batch.iter() {
                    let i = i as usize;
                    if !bit(open, i) {
                        continue;
                    }
                    open[i / 64] &= !(1 << (i % 64));
                    n.neighbours::<false>(i, cost[i], |j, c| {
                        if c < cost[j] {
                            cost[j] = c;
                            let h = estimate[j];
                            if h.is_finite() {
                                open[j / 64] |= 1 << (j % 64);
                                // Never behind the bucket being drained, whatever the rounding.
                                let b = (((c + h) * per_bucket) as usize).max(floor);
                                rings[b & slot_mask].push(j as u32);
                                *pending += 1;
                            }
                        }
                    });
                }
                batch.clear();
            }
            *current += 1;
        }
    }
}

pub(super) fn heap<N: Neighbourhood, const CUT: bool>(n: &N, cost: &mut [f32], labels: &mut [u32], starts: &[usize]) {
    let labelled = !labels.is_empty();
    let mut heap = BinaryHeap::new();
    for &i in starts {
        heap.push(std::cmp::Reverse(key(0.0, i)));
    }
    while let Some(std::cmp::Reverse(k)) = heap.pop() {
        let (here, i) = unkey(k);
        if here > cost[i] {
            continue;
        }
        n.neighbours::<CUT>(i, here, |j, c| {
            if c < cost[j] {
                cost[j] = c;
                if labelled {
                    labels[j] = labels[i];
                }
                heap.push(std::cmp::Reverse(key(c, j)));
            }
        });
    }
}

/// Orders by cost, then by index: non-negative floats order like their bits.
#[inline]
pub(super) fn key(cost: f32, index: usize) -> u64 {
    (u64::from(cost.to_bits()) << 32) | index as u64
}

#[inline]
pub(super) fn unkey(k: u64) -> (f32, usize) {
    (f32::from_bits((k >> 32) as u32), (k & 0xFFFF_FFFF) as usize)
}
