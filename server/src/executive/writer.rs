//! How a mission's changesets reach the store: in order, and without holding
//! the mission while the disk works.
//!
//! A map update is the executive's most frequent write. Committed under the
//! mission's lock, each one kept every other request of the mission (fifty
//! robots' updates and heartbeats) waiting for the disk, so a mission could
//! take about one write per flush of the disk, however many the store groups
//! per flush. A map update is therefore applied to the live state as soon
//! as it is queued for writing, the lock is released, and the robot is
//! answered only once the write is durable (Redis does the same with
//! `appendfsync always`): nothing is acknowledged before it is durable, and
//! the next request of the mission is prepared while the disk works.
//! Heartbeats that change a task's state and plans made off the request
//! path are written the same way (each new target sets off several
//! transitions), and the assignments such a write moves reach the robots
//! only once it is durable (`Mission::apply_queued`). Other writes keep the
//! simpler order (write, then apply) under the lock.
//!
//! Every changeset of a mission follows the one before it ([`Store::submit`]),
//! so one prepared on a state that held an update the disk then refused is
//! never written either. The mission that holds such an update is reloaded
//! from the store: what was not acknowledged is gone, as after a restart.

use std::sync::Arc;
use std::time::Instant;

use crate::clock::Clock;
use crate::domain::{Assignment, MissionRecord};
use crate::error::Error;
use crate::metrics::Metrics;
use crate::store::{Changeset, Store, StoreError, Submitted};

use super::mission::{Mission, StoredMission};
use super::planner::MissionCell;

/// Writes missions' changesets and loads missions back.
#[derive(Debug, Clone)]
pub(crate) struct Writer {
    store: Arc<dyn Store>,
    clock: Clock,
    metrics: Arc<Metrics>,
}

/// A changeset queued behind its mission's earlier ones.
#[derive(Debug)]
pub(crate) struct Queued {
    submitted: Submitted,
    /// The mission's generation when it was queued (see [`Mission::generation`]).
    generation: u64,
    /// When it was queued.
    at: Instant,
    /// The assignments it moved, told once it is durable.
    moved: Vec<Assignment>,
}

impl Writer {
    pub(crate) fn new(store: Arc<dyn Store>, clock: Clock, metrics: Arc<Metrics>) -> Self {
        Self { store, clock, metrics }
    }

    /// Writes `changes` behind the mission's earlier changesets and returns
    /// them once durable; the caller applies them. A changeset refused on its
    /// own changed nothing; one refused because an earlier one was (which
    /// the mission may hold already) makes the mission reload.
    pub(crate) async fn write(&self, mission: &mut Mission, changes: Changeset) -> Result<Changeset, Error> {
        let queued = self.queue(mission, changes).await?;
        let written = queued.submitted.durable().await;
        self.metrics.store_durable_wait.observe(queued.at.elapsed().as_secs_f64());
        match written {
            Ok(changes) => Ok(changes),
            Err(e @ StoreError::Abandoned { .. }) => Err(self.recover(mission, queued.generation, e).await),
            Err(e) => {
                // Everything before it was written (it would have been
                // abandoned otherwise): the next changeset follows nothing.
                mission.chain_broken_by_own_failure();
                Err(e.into())
            }
        }
    }

    /// Queues `changes` behind the mission's earlier changesets and applies
    /// them at once ([`Mission::apply_queued`]); the caller may release the
    /// mission and wait with [`Writer::durable`], which tells the robots the
    /// assignments they moved.
    pub(crate) async fn queue_and_apply(&self, mission: &mut Mission, changes: Changeset) -> Result<Queued, Error> {
        let mut queued = self.queue(mission, changes.clone()).await?;
        queued.moved = mission.apply_queued(changes);
        Ok(queued)
    }

    async fn queue(&self, mission: &mut Mission, mut changes: Changeset) -> Result<Queued, Error> {
        // A request or plan that waited for the mission while it was deleted.
        if mission.is_deleted() {
            return Err(Error::NotFound(format!("mission {} was deleted", mission.record().id)));
        }
        changes.fence = mission.fence();
        let generation = mission.generation();
        let asked = Instant::now();
        let submitted = self.store.submit(changes, mission.last_commit()).await?;
        let at = Instant::now();
        self.metrics.store_queue_wait.observe((at - asked).as_secs_f64());
        mission.set_last_commit(submitted.id);
        Ok(Queued { submitted, generation, at, moved: Vec::new() })
    }

    /// Waits until a queued changeset is durable, then tells the robots the
    /// assignments it moved. If it is not durable, the mission (which holds
    /// it already) is reloaded from the store before this returns, so that
    /// nobody reads what was not written afterwards.
    pub(crate) async fn durable(&self, queued: Queued, cell: &MissionCell) -> Result<(), Error> {
        let Queued { submitted, generation, at, moved } = queued;
        let written = submitted.durable().await;
        self.metrics.store_durable_wait.observe(at.elapsed().as_secs_f64());
        match written {
            Ok(_) if moved.is_empty() => Ok(()),
            Ok(_) => {
                cell.lock().await.tell(moved);
                Ok(())
            }
            Err(e) => Err(self.recover(&mut *cell.lock().await, generation, e).await),
        }
    }

    /// After `error` refused a changeset of the mission's `generation`:
    /// reloads the mission from the store unless that was done already.
    async fn recover(&self, mission: &mut Mission, generation: u64, error: StoreError) -> Error {
        if mission.generation() == generation {
            let id = mission.record().id;
            match self.reload(mission).await {
                Ok(()) => {
                    tracing::warn!(mission = id, error = %error, "a write failed: mission reloaded from the store")
                }
                // It stays as it was; every write follows the failed one and
                // is refused, and the next refusal tries again.
                Err(e) => {
                    tracing::error!(mission = id, error = %e, "a write failed and the mission could not be reloaded")
                }
            }
        }
        error.into()
    }

    async fn reload(&self, mission: &mut Mission) -> Result<(), Error> {
        let id = mission.record().id;
        let record = self.store.mission(id).await?;
        let record = record.ok_or_else(|| Error::Internal(format!("mission {id} is no longer in the store")))?;
        let fresh = self.load(record).await?;
        mission.replace_after_failed_write(fresh);
        Ok(())
    }

    /// A mission as the store holds it.
    pub(crate) async fn load(&self, record: MissionRecord) -> Result<Mission, Error> {
        let store = &*self.store;
        let id = record.id;
        let robots = store.robots(&record).await?;
        let map = store.stored_map(&record, None).await?;
        let open_tasks = store.open_tasks(id).await?;
        let blacklist = store.blacklist(id).await?;
        let forbidden = store.forbidden_regions(id).await?;
        let rooms = store.given_segmentation(id).await?;
        tracing::info!(
            mission = id,
            robots = robots.len(),
            snapshot = map.snapshot.as_ref().map_or(0, |s| s.folded),
            patches = map.patches.len(),
            open_tasks = open_tasks.len(),
            "loading mission"
        );
        let mut bids = Vec::new();
        for robot in &robots {
            bids.push((robot.id, store.bids(robot.id).await?));
        }
        let mut mission = Mission::restore(
            record,
            StoredMission { robots, map, open_tasks, blacklist, forbidden, rooms },
            self.clock.now(),
        )?;
        for (robot, robot_bids) in bids {
            mission.set_bids(robot, &robot_bids);
        }
        Ok(mission)
    }
}
