//! What the executive does on its own: the periodic sweep of leases and
//! stalls, writing what was written behind, closing, and the gauges.

use super::Executive;
use super::mission::Mission;
use crate::domain::Timestamp;
use crate::error::Error;

/// Rows of a deleted mission's largest tables removed in one transaction,
/// and such transactions per sweep: each is short, so the missions' own
/// writes never wait long behind a large mission's removal (at most 8 000
/// rows a second at the wall clock's sweeps; a mission of 10 000 map
/// patches was purged in 1.4–1.9 s while another's map updates went from
/// a p99 of 1.2–1.5 ms to 2.6–3.1 ms).
const PURGE_ROWS: u32 = 1_000;
const PURGE_BATCHES_PER_SWEEP: usize = 4;

impl Executive {
    /// Expires leases and detects stalls in every mission, then replans
    /// those that changed. Runs every [`SWEEP_PERIOD`](super::SWEEP_PERIOD) while serving.
    pub async fn sweep(&self) -> Result<(), Error> {
        let handles: Vec<_> = self.missions.read().unwrap_or_else(|e| e.into_inner()).values().cloned().collect();
        let mut failed = None;
        for handle in handles {
            let mut mission = handle.lock().await;
            // A replanning that could not be committed is tried again here,
            // so that it does not wait for the next request; missions
            // planned off the request path also get their time triggers
            // here. Lockstep missions plan only when a request or the
            // sweep changed something: a simulation stays reproducible.
            if mission.replan_failed() || !mission.record().spec.lockstep {
                self.planner.after_change(&handle, &mut mission).await;
            }
            self.flush_unsaved(&mut mission).await;
            let Some(changes) = mission.prepare_sweep(self.settings.clock.now(), Timestamp::now()) else {
                continue;
            };
            // One mission's failure does not keep the others from their sweep.
            let changes = match self.writer.write(&mut mission, changes).await {
                Ok(changes) => changes,
                Err(e) => {
                    failed = Some(e);
                    continue;
                }
            };
            for change in &changes.task_changes {
                tracing::info!(mission = mission.record().id, task = change.task_id, state = change.state.as_str(),
                    cause = %change.transition.cause, "task ended by the executive");
            }
            mission.apply(changes);
            self.planner.after_change(&handle, &mut mission).await;
        }
        if let Err(e) = self.purge_deleted().await {
            failed.get_or_insert(e);
        }
        match failed {
            Some(e) => Err(e),
            None => Ok(()),
        }
    }

    /// Removes some rows of deleted missions (see
    /// [`crate::store::Store::purge_deleted`]).
    async fn purge_deleted(&self) -> Result<(), Error> {
        for _ in 0..PURGE_BATCHES_PER_SWEEP {
            if !self.store.purge_deleted(PURGE_ROWS).await? {
                break;
            }
        }
        Ok(())
    }

    /// Stops the planners (plans being committed finish first) and writes
    /// what was written behind.
    pub async fn close(&self) {
        self.planner.shutdown().await;
        let handles: Vec<_> = self.missions.read().unwrap_or_else(|e| e.into_inner()).values().cloned().collect();
        for handle in handles {
            self.flush_unsaved(&mut *handle.lock().await).await;
        }
    }

    /// Writes the robot records changed by liveness reports only.
    async fn flush_unsaved(&self, mission: &mut Mission) {
        let Some(changes) = mission.take_unsaved() else { return };
        if let Err(e) = self.writer.write(mission, changes).await {
            tracing::warn!(mission = mission.record().id, error = %e, "robot poses not written; tried again at the next sweep");
            mission.keep_unsaved_again();
        }
    }

    /// The executive's metrics, with the gauges read from its missions now.
    pub async fn metrics(&self) -> String {
        self.refresh_gauges().await;
        self.metrics.encode()
    }

    async fn refresh_gauges(&self) {
        use crate::metrics::{Label, MissionLabel};
        let handles: Vec<_> = self.missions.read().unwrap_or_else(|e| e.into_inner()).values().cloned().collect();
        self.metrics.missions.clear();
        self.metrics.robots.clear();
        self.metrics.frontier_cells.clear();
        self.metrics.coverage.clear();
        for handle in handles {
            let mission = handle.lock().await;
            let record = mission.record();
            let state = if record.paused { "paused" } else { record.state.as_str() };
            self.metrics.missions.get_or_create(&Label { name: state.to_owned() }).inc();
            for robot in mission.robots() {
                let state = if robot.lost { "lost" } else { robot.state.as_str() };
                self.metrics.robots.get_or_create(&Label { name: state.to_owned() }).inc();
            }
            let key = MissionLabel { mission: record.id };
            self.metrics.frontier_cells.get_or_create(&key).set(mission.frontier_cells() as i64);
            let share = mission.known_cells() as f64 / record.spec.frame.len().max(1) as f64;
            self.metrics.coverage.get_or_create(&key).set(share);
        }
    }
}
