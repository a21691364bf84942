//! Executive replicas sharing one database: which missions this one holds.
//!
//! Each mission is held by one replica at a time, through a lease in the
//! store ([`crate::store::lease`]). This replica claims the missions it
//! creates, and any mission nobody holds (never claimed, or whose holder
//! stopped renewing more than a grace period ago) that a request asks for
//! or that its lease keeper finds; it loads a claimed mission from the
//! store, as after a restart, and every write it makes for it carries the
//! claim's fencing token. A mission held by another replica is answered
//! with that replica's address ([`Error::Elsewhere`]), which the project's
//! clients follow. The lease keeper renews the held leases a few times per
//! lease period and lets go of any mission whose lease another replica has
//! taken (a write fenced meanwhile fails and is retried there).
//!
//! The replicas share the missions evenly. Each round the keeper also
//! announces its replica alive in the store and learns how many are alive;
//! a replica claims missions nobody holds only while it holds fewer than
//! its fair share (the missions divided by the replicas, rounded up) and
//! hands on, by releasing their leases, those it holds beyond it, so that a
//! replica that starts, or comes back, takes its part instead of idling
//! while another carries every mission. A mission that stays unclaimed for
//! a whole lease period (its fair shares are full, or a replica cannot load
//! it) is taken by any replica, share or not: no mission is left without a
//! holder.

use std::collections::{BTreeMap, HashMap};
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, Instant};

use tokio_util::sync::CancellationToken;

use super::planner::MissionCell;
use super::{Executive, Mission};
use crate::domain::{MissionId, MissionRecord, Timestamp};
use crate::error::Error;
use crate::store::{Claimant, Fence, Lease};

/// How this executive shares its database with other replicas.
#[derive(Debug, Clone)]
pub struct ReplicaSettings {
    /// Its name and the address clients reach it at.
    pub claimant: Claimant,
    /// How long a claim or a renewal lasts; renewed every third of it.
    pub lease: Duration,
    /// How long after a lease ran out before another replica may claim the
    /// mission (room for clocks that disagree a little).
    pub grace: Duration,
}

/// The leases this executive holds.
#[derive(Debug)]
pub(super) struct Ownership {
    pub(super) settings: ReplicaSettings,
    /// Each held mission's fencing token.
    held: std::sync::Mutex<BTreeMap<MissionId, u64>>,
    /// One claim at a time: two requests for a mission nobody holds must
    /// not claim it twice (the second claim would fence the first).
    claiming: tokio::sync::Mutex<()>,
    /// When the leases were last renewed.
    renewed: std::sync::Mutex<Instant>,
    /// The most missions this replica should hold, from its last
    /// announcement (no limit before the first).
    fair: AtomicU64,
    /// The missions nobody held at the last rounds, and since when.
    unclaimed_since: std::sync::Mutex<HashMap<MissionId, Instant>>,
}

impl Ownership {
    pub(super) fn new(settings: ReplicaSettings) -> Self {
        Self {
            settings,
            held: std::sync::Mutex::default(),
            claiming: tokio::sync::Mutex::default(),
            renewed: std::sync::Mutex::new(Instant::now()),
            fair: AtomicU64::new(u64::MAX),
            unclaimed_since: std::sync::Mutex::default(),
        }
    }

    /// Whether this replica should claim `id`, which nobody holds: it holds
    /// fewer missions than its share, or `id` has waited a whole lease
    /// period for a holder.
    fn should_claim(&self, id: MissionId) -> bool {
        let held = self.held().len() as u64;
        let waited = self.unclaimed_since.lock().unwrap_or_else(|e| e.into_inner()).get(&id).map(Instant::elapsed);
        held < self.fair.load(Ordering::Relaxed) || waited.is_some_and(|w| w >= self.settings.lease)
    }

    /// Remembers since when each of `unclaimed` has had no holder.
    fn note_unclaimed(&self, unclaimed: &[MissionId]) {
        let mut since = self.unclaimed_since.lock().unwrap_or_else(|e| e.into_inner());
        since.retain(|id, _| unclaimed.contains(id));
        for &id in unclaimed {
            since.entry(id).or_insert_with(Instant::now);
        }
    }

    /// The right to claim: held from a claim (or the creation of a mission)
    /// until its mission is in the executive's map, and while the lease
    /// keeper hands missions on. So the keeper never claims a mission this
    /// executive is claiming itself (a second claim would fence the first),
    /// and never hands on one not yet in the map (it would be put there
    /// after, and acted for without a lease).
    pub(super) async fn claiming(&self) -> tokio::sync::MutexGuard<'_, ()> {
        self.claiming.lock().await
    }

    /// Holds a mission this executive just created with its `lease` (see
    /// [`crate::store::Store::create_claimed_mission`]); the caller holds
    /// [`Self::claiming`] until the mission is in the executive's map.
    pub(super) fn hold_new(&self, mission: &mut Mission, lease: &Lease) {
        let id = mission.record().id;
        mission.set_fence(Fence { mission_id: id, token: lease.token });
        self.held().insert(id, lease.token);
    }

    fn held(&self) -> std::sync::MutexGuard<'_, BTreeMap<MissionId, u64>> {
        self.held.lock().unwrap_or_else(|e| e.into_inner())
    }

    fn fences(&self) -> Vec<Fence> {
        self.held().iter().map(|(&mission_id, &token)| Fence { mission_id, token }).collect()
    }
}

impl Executive {
    /// The mission `id`, which this executive does not hold: claimed and
    /// loaded if nobody holds it, otherwise where to ask.
    pub(super) async fn claim_or_point(&self, ownership: &Ownership, id: MissionId) -> Result<Arc<MissionCell>, Error> {
        let _one_at_a_time = ownership.claiming().await;
        if let Some(cell) = self.held_mission(id) {
            return Ok(cell);
        }
        let Some(record) = self.store.mission(id).await? else {
            return Err(Error::NotFound(format!("mission {id} does not exist; ListMissions shows the missions")));
        };
        let ReplicaSettings { claimant, lease, grace } = &ownership.settings;
        if !ownership.should_claim(id) {
            // Over its share: left to a replica under its own, unless this
            // replica held it before it restarted (it claims that back at once).
            let lease = self.store.lease(id).await?;
            let mine = |l: &Lease| l.owner == claimant.id && l.expires_at > Timestamp::now();
            if !lease.as_ref().is_some_and(mine) {
                return Err(Self::pointer_to(id, lease));
            }
        }
        match self.store.claim(id, claimant, Timestamp::now(), *lease, *grace).await? {
            Some(lease) => self.adopt(ownership, record, lease).await,
            None => Err(self.pointer(id).await),
        }
    }

    /// Where to ask for a mission another replica holds.
    async fn pointer(&self, id: MissionId) -> Error {
        Self::pointer_to(id, self.store.lease(id).await.ok().flatten())
    }

    /// Where to ask for mission `id`, whose lease is `lease`: its holder
    /// while the lease lasts; nobody (ask again, or another replica) once
    /// it ran out or was released.
    fn pointer_to(id: MissionId, lease: Option<Lease>) -> Error {
        match lease {
            Some(lease) if lease.expires_at > Timestamp::now() => Error::Elsewhere {
                message: format!("mission {id} is held by the replica {} at {}: ask there", lease.owner, lease.address),
                owner: Some(lease.address),
            },
            _ => Error::Elsewhere {
                message: format!("mission {id} is changing hands: retry shortly, or ask another replica"),
                owner: None,
            },
        }
    }

    /// Loads a mission just claimed with `lease` and starts acting for it.
    async fn adopt(
        &self,
        ownership: &Ownership,
        record: MissionRecord,
        lease: Lease,
    ) -> Result<Arc<MissionCell>, Error> {
        let id = record.id;
        let fence = Fence { mission_id: id, token: lease.token };
        let cells = record.spec.frame.len() as u64;
        let loaded = match self.usage.reserve(cells, &self.settings) {
            Ok(()) => self.writer.load(record).await.inspect_err(|_| self.usage.release(cells)),
            Err(e) => Err(e),
        };
        let mut mission = match loaded {
            Ok(mission) => mission,
            Err(e) => {
                // Another replica may take it at once.
                if let Err(release) = self.store.release(fence).await {
                    tracing::warn!(mission = id, error = %release, "a claim that could not be used stays until it runs out");
                }
                return Err(e);
            }
        };
        mission.set_fence(fence);
        self.refresh_tokens().await?;
        let cell = Arc::new(MissionCell::new(mission));
        ownership.held().insert(id, lease.token);
        self.start_holding(Arc::clone(&cell)).await;
        tracing::info!(mission = id, token = lease.token, "mission claimed and loaded");
        Ok(cell)
    }

    /// Lets a mission go: another replica holds it now. Its planner stops
    /// and, once the requests under way end, its robots' streams close, so
    /// that they reconnect and are pointed to the new holder.
    fn give_up(&self, ownership: &Ownership, id: MissionId) {
        self.stop_holding(ownership, id);
        tracing::warn!(mission = id, "mission given up: another replica holds it now");
    }

    /// Stops acting for a mission (see [`Self::give_up`]).
    pub(super) fn stop_holding(&self, ownership: &Ownership, id: MissionId) {
        ownership.held().remove(&id);
        self.forget_mission(id);
    }

    /// Releases the leases of the missions held beyond `fair`, the newest
    /// first, for the replicas under their share to claim.
    async fn hand_on_excess(&self, ownership: &Ownership, fair: u64) {
        let fences = ownership.fences();
        let excess = (fences.len() as u64).saturating_sub(fair) as usize;
        for fence in fences.into_iter().rev().take(excess) {
            self.stop_holding(ownership, fence.mission_id);
            match self.store.release(fence).await {
                Ok(()) => {
                    tracing::info!(mission = fence.mission_id, "mission handed on: more than this replica's share")
                }
                Err(e) => {
                    tracing::warn!(mission = fence.mission_id, error = %e, "a lease handed on is left to run out")
                }
            }
        }
    }

    /// One round of the lease keeper: renews the held leases, lets go of
    /// those another replica took, announces this replica, hands on the
    /// missions beyond its share and claims, up to it, those nobody holds.
    pub async fn keep_leases(&self) -> Result<(), Error> {
        let Some(ownership) = &self.ownership else { return Ok(()) };
        let held = ownership.fences();
        let period = ownership.settings.lease;
        let renewed = match self.store.renew(&held, Timestamp::now(), period).await {
            Ok(renewed) => renewed,
            Err(e) => {
                // Unrenewed past the period, the leases are others' to take:
                // stop acting for them before anyone does.
                let since = ownership.renewed.lock().unwrap_or_else(|e| e.into_inner()).elapsed();
                if since > period {
                    for fence in &held {
                        self.give_up(ownership, fence.mission_id);
                    }
                }
                return Err(e.into());
            }
        };
        *ownership.renewed.lock().unwrap_or_else(|e| e.into_inner()) = Instant::now();
        for fence in held.iter().filter(|f| !renewed.contains(&f.mission_id)) {
            self.give_up(ownership, fence.mission_id);
        }
        {
            // No mission is created or claimed here between the count of the
            // share and the handing on: one would be handed on as excess.
            let _no_claims_meanwhile = ownership.claiming().await;
            let share = self.store.announce(&ownership.settings.claimant, Timestamp::now(), period).await?;
            ownership.fair.store(share.fair(), Ordering::Relaxed);
            self.hand_on_excess(ownership, share.fair()).await;
        }
        let unclaimed = self.store.unclaimed(Timestamp::now(), ownership.settings.grace).await?;
        ownership.note_unclaimed(&unclaimed);
        for id in unclaimed {
            if self.held_mission(id).is_none()
                && ownership.should_claim(id)
                && let Err(e) = self.claim_or_point(ownership, id).await
            {
                tracing::debug!(mission = id, error = %e, "an unclaimed mission was not taken");
            }
        }
        self.refresh_tokens().await
    }

    /// Hands every held mission on at once (a graceful stop), and
    /// withdraws this replica from the others' shares.
    pub async fn release_leases(&self) {
        let Some(ownership) = &self.ownership else { return };
        if let Err(e) = self.store.announce(&ownership.settings.claimant, Timestamp::now(), Duration::ZERO).await {
            tracing::warn!(error = %e, "this replica's announcement is left to run out");
        }
        for fence in ownership.fences() {
            if let Err(e) = self.store.release(fence).await {
                tracing::warn!(mission = fence.mission_id, error = %e, "a lease was left to run out");
            }
        }
    }

    /// Rereads every robot's token hash: robots registered with other
    /// replicas reach this one when their mission changes hands.
    async fn refresh_tokens(&self) -> Result<(), Error> {
        let tokens = self.store.robot_tokens().await?.into_iter().collect();
        *self.tokens.write().unwrap_or_else(|e| e.into_inner()) = tokens;
        Ok(())
    }
}

/// Runs the lease keeper every third of the lease period until `stop`.
pub async fn keep_leases_until(executive: Arc<Executive>, stop: CancellationToken) {
    let Some(period) = executive.ownership.as_ref().map(|o| o.settings.lease / 3) else { return };
    let mut tick = tokio::time::interval(period.max(Duration::from_millis(10)));
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    loop {
        tokio::select! {
            () = stop.cancelled() => return,
            _ = tick.tick() => {}
        }
        if let Err(e) = executive.keep_leases().await {
            tracing::warn!(error = %e, "the leases could not be kept this round");
        }
    }
}
