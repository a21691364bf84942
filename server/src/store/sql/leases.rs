//! Mission leases and identity blocks in SQL (see [`crate::store::lease`]).

use std::time::Duration;

use super::SqlStore;
use super::rows;
use super::statement::{Backend, Statement, Transaction};
use crate::domain::{MissionId, Timestamp};
use crate::store::{Claimant, Fence, Lease, Share, StoreError};

/// How long a replica that stopped announcing itself stays in `replicas`.
const FORGET_AFTER_MS: i64 = 24 * 3600 * 1000;

/// `now + period`, in the milliseconds leases are kept in.
fn until(now: Timestamp, period: Duration) -> i64 {
    now.millis().saturating_add(i64::try_from(period.as_millis()).unwrap_or(i64::MAX))
}

/// `now - grace`: a lease that ran out before this may be claimed.
fn claimable_before(now: Timestamp, grace: Duration) -> i64 {
    now.millis().saturating_sub(i64::try_from(grace.as_millis()).unwrap_or(i64::MAX))
}

/// The first lease of a mission just created, for `claimant` until
/// `now + period`, with fencing token 1; returns the lease's row.
pub(super) fn first_lease(mission_id: MissionId, claimant: &Claimant, now: Timestamp, period: Duration) -> Statement {
    Statement::new(
        "INSERT INTO mission_leases (mission_id, owner, address, token, expires_at) VALUES ($1, $2, $3, 1, $4)
         RETURNING *",
    )
    .int(mission_id as i64)
    .text(&claimant.id)
    .text(&claimant.address)
    .int(until(now, period))
}

impl<B: Backend> SqlStore<B> {
    pub(super) async fn read_lease(&self, mission_id: MissionId) -> Result<Option<Lease>, StoreError> {
        let select = Statement::new("SELECT * FROM mission_leases WHERE mission_id = $1");
        let row = self.backend.fetch_optional(select.int(mission_id as i64)).await?;
        row.as_ref().map(rows::lease_from_row).transpose()
    }

    pub(super) async fn claim_lease(
        &self,
        mission_id: MissionId,
        claimant: &Claimant,
        now: Timestamp,
        period: Duration,
        grace: Duration,
    ) -> Result<Option<Lease>, StoreError> {
        let claim = Statement::new(
            "INSERT INTO mission_leases (mission_id, owner, address, token, expires_at)
             SELECT $1, $2, $3, 1, $4 FROM missions WHERE id = $1 AND deleted_at IS NULL
             ON CONFLICT (mission_id) DO UPDATE SET owner = excluded.owner, address = excluded.address,
                 token = mission_leases.token + 1, expires_at = excluded.expires_at
             WHERE mission_leases.expires_at < $5 OR mission_leases.owner = $2
             RETURNING *",
        )
        .int(mission_id as i64)
        .text(&claimant.id)
        .text(&claimant.address)
        .int(until(now, period))
        .int(claimable_before(now, grace));
        let mut tx = self.backend.begin_write().await?;
        let rows = tx.fetch_all(claim).await?;
        tx.commit().await?;
        rows.first().map(rows::lease_from_row).transpose()
    }

    pub(super) async fn renew_leases(
        &self,
        held: &[Fence],
        now: Timestamp,
        period: Duration,
    ) -> Result<Vec<MissionId>, StoreError> {
        let mut renewed = Vec::with_capacity(held.len());
        let mut tx = self.backend.begin_write().await?;
        for fence in held {
            let renew =
                Statement::new("UPDATE mission_leases SET expires_at = $1 WHERE mission_id = $2 AND token = $3")
                    .int(until(now, period))
                    .int(fence.mission_id as i64)
                    .int(fence.token as i64);
            if tx.execute(renew).await? == 1 {
                renewed.push(fence.mission_id);
            }
        }
        tx.commit().await?;
        Ok(renewed)
    }

    pub(super) async fn release_lease(&self, fence: Fence) -> Result<(), StoreError> {
        let release = Statement::new("UPDATE mission_leases SET expires_at = 0 WHERE mission_id = $1 AND token = $2")
            .int(fence.mission_id as i64)
            .int(fence.token as i64);
        let mut tx = self.backend.begin_write().await?;
        tx.execute(release).await?;
        tx.commit().await
    }

    pub(super) async fn unclaimed_missions(
        &self,
        now: Timestamp,
        grace: Duration,
    ) -> Result<Vec<MissionId>, StoreError> {
        let select = Statement::new(
            "SELECT m.id AS n FROM missions m LEFT JOIN mission_leases l ON l.mission_id = m.id
             WHERE m.deleted_at IS NULL AND (l.mission_id IS NULL OR l.expires_at < $1) ORDER BY m.id",
        );
        let rows = self.backend.fetch_all(select.int(claimable_before(now, grace))).await?;
        rows.iter().map(|row| rows::identity(row, "missions", "n")).collect()
    }

    pub(super) async fn announce_replica(
        &self,
        claimant: &Claimant,
        now: Timestamp,
        period: Duration,
    ) -> Result<Share, StoreError> {
        let announce = Statement::new(
            "INSERT INTO replicas (id, address, expires_at) VALUES ($1, $2, $3)
             ON CONFLICT (id) DO UPDATE SET address = excluded.address, expires_at = excluded.expires_at",
        )
        .text(&claimant.id)
        .text(&claimant.address)
        .int(until(now, period));
        let count = Statement::new(
            "SELECT (SELECT COUNT(*) FROM replicas WHERE expires_at > $1) AS replicas,
                    (SELECT COUNT(*) FROM missions WHERE deleted_at IS NULL) AS missions",
        )
        .int(now.millis());
        // Replicas gone for a day are forgotten (on Kubernetes every pod
        // has a new name).
        let forget = Statement::new("DELETE FROM replicas WHERE expires_at < $1")
            .int(now.millis().saturating_sub(FORGET_AFTER_MS));
        let mut tx = self.backend.begin_write().await?;
        tx.execute(forget).await?;
        tx.execute(announce).await?;
        let row = tx.fetch_one(count).await?;
        tx.commit().await?;
        rows::share_from_row(&row)
    }

    pub(super) async fn new_id_block(&self, owner: &str, now: Timestamp) -> Result<u64, StoreError> {
        let insert = Statement::new("INSERT INTO id_blocks (owner, taken_at) VALUES ($1, $2) RETURNING id AS n")
            .text(owner)
            .int(now.millis());
        let mut tx = self.backend.begin_write().await?;
        let row = tx.fetch_one(insert).await?;
        tx.commit().await?;
        rows::identity(&row, "id_blocks", "n")
    }
}
