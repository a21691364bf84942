-- Executive replicas sharing one database (PostgreSQL in practice; the
-- same tables here keep the store's SQL and its tests the same for both).
--
-- Which replica acts for each mission: a lease that its owner renews, and a
-- fencing token that grows by one at every change of owner. Every write of
-- the owner checks the token in its transaction, so a replica that lost a
-- mission (paused past its lease, cut off) can never write for it again.
-- Times are the replicas' clocks, in milliseconds since the Unix epoch.
CREATE TABLE mission_leases (
    mission_id  INTEGER PRIMARY KEY REFERENCES missions (id),
    owner       TEXT    NOT NULL,
    address     TEXT    NOT NULL,
    token       INTEGER NOT NULL,
    expires_at  INTEGER NOT NULL
);

-- Blocks of identities for tasks and forbidden regions: a replica gives
-- identities from blocks of its own (block N: N * 2^32 + 1 onwards), so
-- that replicas never give the same one.
CREATE TABLE id_blocks (
    id          INTEGER PRIMARY KEY AUTOINCREMENT,
    owner       TEXT    NOT NULL,
    taken_at    INTEGER NOT NULL
);
