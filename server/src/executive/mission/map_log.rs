//! Which parts of a mission's map changed lately, so that a watcher (the
//! web view) is sent the changed cells, not the whole map, at each update.

use std::collections::VecDeque;

use exploration::grid::CellRect;

/// Changes remembered: a watcher further behind is sent the whole map.
const KEPT: usize = 512;

/// The map's version (one per applied patch that changed a cell) and the
/// rectangles the latest versions changed.
#[derive(Debug, Default)]
pub(crate) struct MapLog {
    version: u64,
    recent: VecDeque<(u64, CellRect)>,
}

impl MapLog {
    /// A log that goes on from `version` of another, remembering nothing:
    /// every watcher is sent the whole map next.
    pub(crate) fn after(version: u64) -> Self {
        Self { version: version + 1, recent: VecDeque::new() }
    }

    /// A patch changed the cells inside `rect`.
    pub(crate) fn record(&mut self, rect: CellRect) {
        self.version += 1;
        if self.recent.len() == KEPT {
            self.recent.pop_front();
        }
        self.recent.push_back((self.version, rect));
    }

    /// The current version.
    pub(crate) fn version(&self) -> u64 {
        self.version
    }

    /// The rectangles changed after version `since`, overlapping ones
    /// merged; `None` when they are no longer all remembered, or `since` is
    /// not a version of this log (the executive restarted since).
    pub(crate) fn since(&self, since: u64) -> Option<Vec<CellRect>> {
        if since > self.version {
            return None;
        }
        if since == self.version {
            return Some(Vec::new());
        }
        let oldest = self.recent.front().map_or(self.version + 1, |(v, _)| *v);
        if since + 1 < oldest {
            return None;
        }
        Some(merged(self.recent.iter().filter(|(v, _)| *v > since).map(|(_, r)| *r)))
    }
}

/// Rectangles with every pair that overlaps replaced by its union (which
/// may then overlap others: repeated until none does).
fn merged(rects: impl Iterator<Item = CellRect>) -> Vec<CellRect> {
    let mut out: Vec<CellRect> = Vec::new();
    for rect in rects {
        let mut rect = rect;
        while let Some(k) = out.iter().position(|o| o.intersection(&rect).is_some()) {
            rect = rect.union(&out.swap_remove(k));
        }
        out.push(rect);
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_watcher_gets_what_changed_since_its_version_merged() {
        let mut log = MapLog::default();
        log.record(CellRect::new(0, 0, 4, 4));
        let seen = log.version();
        log.record(CellRect::new(10, 10, 2, 2));
        log.record(CellRect::new(11, 11, 3, 3));
        log.record(CellRect::new(30, 0, 1, 1));
        let mut changed = log.since(seen).unwrap();
        changed.sort_by_key(|r| r.x);
        assert_eq!(changed, vec![CellRect::new(10, 10, 4, 4), CellRect::new(30, 0, 1, 1)]);
        assert_eq!(log.since(log.version()), Some(Vec::new()));
    }

    #[test]
    fn a_watcher_too_far_behind_or_from_before_a_restart_gets_everything() {
        let mut log = MapLog::default();
        for k in 0..(KEPT as i32 + 5) {
            log.record(CellRect::new(k, 0, 1, 1));
        }
        assert_eq!(log.since(0), None, "versions 1..=5 are forgotten");
        assert_eq!(log.since(5).map(|r| r.len()), Some(KEPT), "everything after 5 is remembered");
        assert_eq!(log.since(log.version() + 1), None, "a version this log never had");
    }
}
