//! Folding the patch log into a snapshot of the fused map.
//!
//! Every acknowledged map update is logged before it is acknowledged, and
//! a fleet of a thousand robots logs about 2.1 GB an hour of them. Left
//! alone, the log fills the disk, and a restart replays it all, holding it
//! all in memory. The compactor folds each mission's oldest patches into
//! the fused map they make (exactly that map, see
//! [`exploration::fusion::FusionParts`]); from the transaction that stores
//! the snapshot on, those patches are never read again, and they are then
//! removed a few hundred at a time. A mission's log is one snapshot and the
//! last few thousand patches, however long the mission runs.
//!
//! It works on what is durable only (the log as stored, never the
//! executive's live map), so it needs no lock of the executive's: the
//! patches logged while it folds come after the ones it folds, and a mission
//! reloaded meanwhile reads the old snapshot and its patches, or the new
//! one and the rest, in one read transaction.

use std::sync::Arc;
use std::time::{Duration, Instant};

use tokio_util::sync::CancellationToken;

use super::{Changeset, MapSnapshot, Store, StoreError, snapshot};
use crate::domain::{MissionId, MissionRecord};
use crate::metrics::Metrics;

/// When the compactor folds.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Compaction {
    /// Patches a mission's log may hold before its oldest are folded, and
    /// how many are folded at a time; 0: never fold.
    pub after_patches: u32,
    /// How often missions are looked at.
    pub period: Duration,
}

impl Default for Compaction {
    fn default() -> Self {
        Self { after_patches: 10_000, period: Duration::from_secs(10) }
    }
}

/// Which missions this executive folds: those it holds (replicas sharing a
/// database would otherwise all fold every mission).
pub type Holds = Arc<dyn Fn(MissionId) -> bool + Send + Sync>;

/// Folds the log of every mission `holds` whenever it passes
/// `compaction.after_patches`, until `stop`.
pub async fn run(
    store: Arc<dyn Store>,
    holds: Holds,
    compaction: Compaction,
    metrics: Arc<Metrics>,
    stop: CancellationToken,
) {
    if compaction.after_patches == 0 {
        return;
    }
    let mut tick = tokio::time::interval(compaction.period);
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    loop {
        tokio::select! {
            () = stop.cancelled() => return,
            _ = tick.tick() => {}
        }
        if let Err(e) = fold_all(&*store, &holds, compaction.after_patches, &metrics, &stop).await {
            tracing::warn!(error = %e, "the patch log could not be folded; tried again later");
        }
    }
}

/// Folded patches removed per changeset: a few hundred rows, a millisecond
/// or two of the writer's time, where removing 2 000 at once held every
/// other write back for about 35 ms.
const FORGET_BATCH: u32 = 256;

/// The pause after each fold and each batch removed: the compactor's work
/// comes in short bursts between the fleet's calls, never in one long one
/// (on two cores, folding twenty missions back to back delayed calls).
const PAUSE: Duration = Duration::from_millis(20);

/// One pass over every mission.
async fn fold_all(
    store: &dyn Store,
    holds: &Holds,
    after_patches: u32,
    metrics: &Metrics,
    stop: &CancellationToken,
) -> Result<(), StoreError> {
    for mission in store.missions().await?.into_iter().filter(|m| holds(m.id)) {
        while !stop.is_cancelled() && store.unfolded_patches(mission.id).await? >= u64::from(after_patches) {
            let folded = fold(store, &mission, after_patches).await?;
            if folded == 0 {
                break;
            }
            metrics.patches_folded.inc_by(folded as u64);
            tokio::time::sleep(PAUSE).await;
        }
        forget(store, mission.id, PAUSE, stop).await?;
    }
    Ok(())
}

/// Removes the patches a mission's snapshot folds from its log, a batch at
/// a time with `pause` between batches, until none is left or `stop`;
/// returns how many batches it wrote.
pub async fn forget(
    store: &dyn Store,
    mission_id: MissionId,
    pause: Duration,
    stop: &CancellationToken,
) -> Result<u64, StoreError> {
    let mut batches = 0;
    while !stop.is_cancelled() && store.folded_patches(mission_id).await? > 0 {
        store.commit(Changeset { forget_folded: Some((mission_id, FORGET_BATCH)), ..Changeset::default() }).await?;
        batches += 1;
        if !pause.is_zero() {
            tokio::time::sleep(pause).await;
        }
    }
    Ok(batches)
}

/// Folds the oldest `count` patches of a mission's log (all, if fewer) into
/// its snapshot; returns how many it folded.
pub async fn fold(store: &dyn Store, mission: &MissionRecord, count: u32) -> Result<usize, StoreError> {
    let log = store.stored_map(mission, Some(count)).await?;
    let folded = log.patches.len();
    if folded == 0 {
        return Ok(0);
    }
    let robots = store.robots(mission).await?.len();
    let frame = mission.spec.frame;
    let through_patch_id = log.last_patch_id;
    let before = log.snapshot.as_ref().map_or(0, |s| s.folded);
    // Decoding, replaying and compressing a map of a million cells takes
    // tens of milliseconds: not on the threads that answer calls.
    let started = Instant::now();
    let (bytes, raw_bytes) =
        tokio::task::spawn_blocking(move || log.fuse(&frame, robots).map(|fusion| snapshot::encode(&fusion)))
            .await
            .map_err(|e| StoreError::Corrupt(format!("folding the patch log failed: {e}")))??;
    let (size, fused) = (bytes.len(), started.elapsed());
    let snapshot =
        MapSnapshot { mission_id: mission.id, through_patch_id, folded: before + folded as u64, bytes, raw_bytes };
    store.commit(Changeset { snapshot: Some(snapshot), ..Changeset::default() }).await?;
    tracing::info!(
        mission = mission.id,
        folded,
        through_patch_id,
        snapshot_bytes = size,
        fuse_ms = fused.as_millis() as u64,
        commit_ms = (started.elapsed() - fused).as_millis() as u64,
        "patch log folded"
    );
    Ok(folded)
}
