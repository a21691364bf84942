-- The replicas sharing this database, each announced until a time it
-- renews with its leases: how many are alive decides each one's fair share
-- of the missions (see server/src/executive/ownership.rs). Times are the
-- replicas' clocks, in milliseconds since the Unix epoch.
CREATE TABLE replicas (
    id          TEXT    PRIMARY KEY,
    address     TEXT    NOT NULL,
    expires_at  INTEGER NOT NULL
);
