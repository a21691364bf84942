//! Which executive replica acts for a mission.
//!
//! Replicas sharing one database divide the missions between them through
//! leases in the database (`mission_leases`), not through a cluster of
//! their own. A replica creates a mission with its lease, in one
//! transaction, and claims one whose lease ran out more than a grace
//! period ago; while it acts for the
//! mission it renews the lease; a replica that stops renewing (it died, it
//! was paused, it lost the database) loses its missions to whoever claims
//! them next, who loads them from the database and carries on.
//!
//! Time alone cannot keep two replicas from acting for one mission: a
//! replica paused past its lease wakes up believing it still holds it. So
//! each claim gives the lease a new *fencing token* (one more than the
//! last), and every write of an owner checks, inside its transaction, that
//! the lease still carries the token it was claimed with ([`Fence`]). A
//! stale owner's write is refused ([`super::StoreError::Fenced`]) and the
//! replica gives the mission up. Row-level fencing was chosen over
//! PostgreSQL's advisory locks because an advisory lock belongs to a
//! connection: the pool's connections come and go, a lock held by a
//! connection that outlived its replica's pause would let the stale replica
//! write, and a lock cannot be checked inside another connection's
//! transaction. (Kleppmann, "How to do distributed locking", 2016, on
//! fencing tokens; Gray and Cheriton, "Leases", SOSP 1989.)

use crate::domain::{MissionId, Timestamp};

/// A mission's lease, as stored.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Lease {
    /// The mission.
    pub mission_id: MissionId,
    /// The replica that holds it (`--replica-id`).
    pub owner: String,
    /// Where clients reach that replica (`--advertise`).
    pub address: String,
    /// The fencing token of the holder's claim.
    pub token: u64,
    /// When it runs out unless renewed (the holder's clock).
    pub expires_at: Timestamp,
}

/// What a write of a mission's owner carries: the token it claimed the
/// mission with. The write is made only if the lease still carries it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Fence {
    /// The mission.
    pub mission_id: MissionId,
    /// The token of the writer's claim.
    pub token: u64,
}

/// How many replicas are alive and how many missions they share, as a
/// replica's announcement finds them.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Share {
    /// Replicas whose announcement has not run out, the announcer among them.
    pub replicas: u64,
    /// Every mission in the database.
    pub missions: u64,
}

impl Share {
    /// The most missions one replica should hold: the missions divided
    /// evenly, rounded up.
    pub fn fair(&self) -> u64 {
        self.missions.div_ceil(self.replicas.max(1))
    }
}

/// A replica, as its leases name it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Claimant {
    /// Its name (`--replica-id`).
    pub id: String,
    /// Where clients reach it (`--advertise`).
    pub address: String,
}
