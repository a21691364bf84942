-- The replicas sharing this database. See migrations/sqlite/0010_replicas.sql.
CREATE TABLE replicas (
    id          TEXT    PRIMARY KEY,
    address     TEXT    NOT NULL,
    expires_at  BIGINT  NOT NULL
);
