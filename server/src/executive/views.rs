//! What the executive shows: missions, robots, maps, events and tasks as
//! operators, watchers and the web view read them. Each read takes the
//! mission's lock only to copy what it returns, and changes nothing.

use std::sync::atomic::{AtomicU64, Ordering};

use tokio::sync::watch;

use exploration::grid::{CellRect, OccupancyGrid};
use exploration::math::Point2;

use super::mission::Mission;
use super::{BackupFile, Executive};
use crate::domain::{
    Assignment, MissionEvent, MissionId, MissionRecord, Region, RobotId, RobotRecord, StoredSegmentation, TaskKind,
    TaskRecord,
};
use crate::error::Error;
use crate::store::TaskFilter;

/// A mission with its live counters.
#[derive(Debug, Clone, PartialEq)]
pub struct MissionSummary {
    /// The stored record.
    pub record: MissionRecord,
    /// Registered robots.
    pub robots: usize,
    /// Known cells of the fused grid.
    pub known_cells: u64,
    /// Frontier cells of the fused grid.
    pub frontier_cells: u64,
    /// Its forbidden regions.
    pub forbidden: Vec<Region>,
    /// Whether it was given its rooms and corridors.
    pub given_segmentation: bool,
}

impl MissionSummary {
    /// A mission as stored, without the live figures of the replica that holds it.
    fn stored(record: MissionRecord) -> Self {
        Self { record, robots: 0, known_cells: 0, frontier_cells: 0, forbidden: Vec::new(), given_segmentation: false }
    }
}

/// A robot with its current target.
#[derive(Debug, Clone, PartialEq)]
pub struct RobotSummary {
    /// The stored record.
    pub record: RobotRecord,
    /// Where its current task leads.
    pub target: Option<Point2>,
    /// What its current task is.
    pub task_kind: Option<TaskKind>,
    /// Targets blacklisted for it.
    pub blacklisted: usize,
}

/// Frontier cells a [`MapView`] lists as points at most: the rest are in
/// its mask. A map whose every third cell is frontier (8 million on the
/// largest mission) would otherwise make a message of 190 MB, more than
/// any client reads.
pub const MOST_FRONTIER_POINTS: usize = 100_000;

/// `flags` a bit each, flag k at bit k % 8 of byte k / 8.
fn bits(flags: &[bool]) -> Vec<u8> {
    flags.chunks(8).map(|eight| eight.iter().rev().fold(0u8, |byte, &f| (byte << 1) | u8::from(f))).collect()
}

/// A copy of a mission's fused map.
#[derive(Debug, Clone)]
pub struct MapView {
    /// The fused grid.
    pub grid: OccupancyGrid,
    /// Frontier cell centres in row order, the first
    /// [`MOST_FRONTIER_POINTS`] of them.
    pub frontier: Vec<Point2>,
    /// Every frontier cell, a bit a cell, row-major, least significant
    /// bit first.
    pub frontier_mask: Vec<u8>,
    /// Robots and their targets.
    pub robots: Vec<RobotSummary>,
}

/// What changed in a mission's map since a watcher last looked.
#[derive(Debug, Clone)]
pub struct MapChanges {
    /// The map's version now: pass it back to get the next changes.
    pub version: u64,
    /// The map's frame.
    pub frame: exploration::grid::GridFrame,
    /// Whether `patches` is the whole map (the watcher's version was too
    /// old, from before a restart, or absent).
    pub full: bool,
    /// Changed rectangles with their cells' values, row-major from the bottom row.
    pub patches: Vec<(CellRect, Vec<u8>)>,
}

impl Executive {
    /// A mission's live figures.
    pub(super) fn summary(mission: &Mission) -> MissionSummary {
        MissionSummary {
            record: mission.record().clone(),
            robots: mission.robot_count(),
            known_cells: mission.known_cells(),
            frontier_cells: mission.frontier_cells() as u64,
            forbidden: mission.forbidden().to_vec(),
            given_segmentation: mission.has_rooms(),
        }
    }

    /// One mission.
    pub async fn mission(&self, id: MissionId) -> Result<MissionSummary, Error> {
        let handle = self.mission_handle(id).await?;
        let mission = handle.lock().await;
        Ok(Self::summary(&mission))
    }

    /// Every mission, oldest first.
    pub async fn missions(&self) -> Result<Vec<MissionSummary>, Error> {
        let mut out = Vec::new();
        self.missions_after(0, |mission| {
            out.push(mission);
            true
        })
        .await?;
        Ok(out)
    }

    /// The missions with an id above `after`, lowest first, each handed to
    /// `take` until it declines one. Returns the id of the last mission
    /// taken when `take` declined one (a page's end), `None` when it took
    /// every one; so that a page always moves on, `take` should accept the
    /// first it is offered. Summarising one at a time keeps a page of a
    /// few large missions from copying every mission's regions first.
    pub async fn missions_after(
        &self,
        after: MissionId,
        mut take: impl FnMut(MissionSummary) -> bool,
    ) -> Result<Option<MissionId>, Error> {
        enum Source {
            Held(std::sync::Arc<super::planner::MissionCell>),
            // Another replica holds it: its live figures (robots, known and
            // frontier cells) are its holder's to give.
            Stored(Box<MissionRecord>),
        }
        let mut sources: std::collections::BTreeMap<MissionId, Source> = self
            .missions
            .read()
            .unwrap_or_else(|e| e.into_inner())
            .range((std::ops::Bound::Excluded(after), std::ops::Bound::Unbounded))
            .map(|(&id, handle)| (id, Source::Held(handle.clone())))
            .collect();
        if self.ownership.is_some() {
            for record in self.store.missions().await? {
                if record.id > after {
                    sources.entry(record.id).or_insert(Source::Stored(Box::new(record)));
                }
            }
        }
        let mut last_taken = after;
        for (id, source) in sources {
            let summary = match source {
                Source::Held(handle) => Self::summary(&*handle.lock().await),
                Source::Stored(record) => MissionSummary::stored(*record),
            };
            if !take(summary) {
                return Ok(Some(last_taken));
            }
            last_taken = id;
        }
        Ok(None)
    }

    /// A mission's latest `limit` events, newest first.
    pub async fn latest_events(&self, mission_id: MissionId, limit: u32) -> Result<Vec<MissionEvent>, Error> {
        self.mission_handle(mission_id).await?;
        Ok(self.store.latest_events(mission_id, limit).await?)
    }

    /// A mission's first `limit` events after `after_id` (0: from the start), oldest first.
    pub async fn events(&self, mission_id: MissionId, after_id: u64, limit: u32) -> Result<Vec<MissionEvent>, Error> {
        self.mission_handle(mission_id).await?;
        Ok(self.store.events(mission_id, after_id, limit).await?)
    }

    /// A mission's latest segmentation, if one was computed.
    pub async fn segmentation(&self, mission_id: MissionId) -> Result<Option<StoredSegmentation>, Error> {
        self.mission_handle(mission_id).await?;
        Ok(self.store.segmentation(mission_id).await?)
    }

    /// A robot's current assignment.
    pub async fn assignment(&self, robot_id: RobotId) -> Result<Assignment, Error> {
        let handle = self.mission_of_robot(robot_id).await?;
        let mission = handle.lock().await;
        mission.assignment_told(robot_id)
    }

    /// A receiver of a robot's assignments: holds the current one, then sees every change.
    pub async fn watch(&self, robot_id: RobotId) -> Result<watch::Receiver<Assignment>, Error> {
        let handle = self.mission_of_robot(robot_id).await?;
        let mission = handle.lock().await;
        mission.watch(robot_id)
    }

    /// A mission's robots with their targets.
    pub async fn robots(&self, mission_id: MissionId) -> Result<Vec<RobotSummary>, Error> {
        let handle = self.mission_handle(mission_id).await?;
        let mission = handle.lock().await;
        Ok(Self::robot_summaries(&mission))
    }

    fn robot_summaries(mission: &Mission) -> Vec<RobotSummary> {
        mission
            .robots()
            .map(|r| RobotSummary {
                record: r.clone(),
                target: mission.target_of(r),
                task_kind: mission.task_kind_of(r),
                blacklisted: mission.blacklisted(r.id),
            })
            .collect()
    }

    /// Tasks with their transitions, newest first.
    pub async fn tasks(&self, filter: TaskFilter) -> Result<Vec<TaskRecord>, Error> {
        let handle = self.mission_handle(filter.mission_id).await?;
        if let Some(robot) = filter.robot_id {
            let mission = handle.lock().await;
            mission.robot(robot).map_err(|_| {
                Error::NotFound(format!("robot {robot} does not exist in mission {}", filter.mission_id))
            })?;
        }
        Ok(self.store.tasks(filter).await?)
    }

    /// A copy of a mission's fused map.
    pub async fn map(&self, mission_id: MissionId) -> Result<MapView, Error> {
        let handle = self.mission_handle(mission_id).await?;
        let mission = handle.lock().await;
        let frame = mission.record().spec.frame;
        let frontier = mission.frontier();
        Ok(MapView {
            grid: mission.grid().clone(),
            frontier: frontier
                .cells_in_row_order()
                .take(MOST_FRONTIER_POINTS)
                .map(|c| frame.world_from_cell(c))
                .collect(),
            frontier_mask: bits(frontier.mask()),
            robots: Self::robot_summaries(&mission),
        })
    }

    /// The cells of a mission's map that changed after version `since`
    /// (all of them without one), copied under the mission's lock at a
    /// cost proportional to what changed.
    pub async fn map_changes(&self, mission_id: MissionId, since: Option<u64>) -> Result<MapChanges, Error> {
        let handle = self.mission_handle(mission_id).await?;
        let mission = handle.lock().await;
        let grid = mission.grid();
        let frame = *grid.frame();
        let whole = frame.bounds();
        let changed = since
            .and_then(|v| mission.map_log().since(v))
            .filter(|rects| rects.iter().map(CellRect::area).sum::<u64>() < whole.area());
        let (full, rects) = match changed {
            Some(rects) => (false, rects),
            None => (true, vec![whole]),
        };
        let width = frame.width as usize;
        let patches = rects
            .iter()
            .filter_map(|r| frame.clip(r))
            .map(|r| {
                let (x0, x1) = (r.x as usize, r.x_end() as usize);
                let rows =
                    (r.y as usize..r.y_end() as usize).flat_map(|y| &grid.cells()[y * width + x0..y * width + x1]);
                (r, rows.copied().collect())
            })
            .collect();
        Ok(MapChanges { version: mission.map_log().version(), frame, full, patches })
    }

    /// A receiver that changes whenever an operator's view of the mission
    /// does.
    pub async fn subscribe(&self, mission_id: MissionId) -> Result<watch::Receiver<u64>, Error> {
        let handle = self.mission_handle(mission_id).await?;
        let mission = handle.lock().await;
        Ok(mission.subscribe())
    }

    /// A consistent copy of the whole store, taken while missions run, in a
    /// file beside the store that is removed when the copy is dropped.
    pub async fn backup(&self) -> Result<BackupFile, Error> {
        static TAKEN: AtomicU64 = AtomicU64::new(0);
        let name = format!(".backup-{}-{}.db", std::process::id(), TAKEN.fetch_add(1, Ordering::Relaxed));
        // The guard first: a copy that fails halfway is removed too.
        let file = BackupFile(self.store.backup_dir().join(name));
        self.store.backup(&file.0).await?;
        Ok(file)
    }
}
