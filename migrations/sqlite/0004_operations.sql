-- Operating a fleet: task kinds and who created them, robot liveness, home
-- poses and tokens, blacklisted targets, forbidden regions, pausing and the
-- report of what was left at completion.

-- What a task asks: 'explore' (a policy's frontier), 'goto', 'hold', 'home'
-- or 'pin' (operator overrides, and 'home' at mission end too).
ALTER TABLE tasks ADD COLUMN kind TEXT NOT NULL DEFAULT 'explore'
    CHECK (kind IN ('explore', 'goto', 'hold', 'home', 'pin'));
-- 'policy', 'executive' or the operator's name; and the reason given.
ALTER TABLE tasks ADD COLUMN created_by TEXT NOT NULL DEFAULT 'policy';
ALTER TABLE tasks ADD COLUMN note TEXT NOT NULL DEFAULT '';

-- The operator's name on operator transitions.
ALTER TABLE task_transitions ADD COLUMN by_name TEXT NOT NULL DEFAULT '';

-- Set when the robot's lease ran out; cleared when it reports again.
ALTER TABLE robots ADD COLUMN lost INTEGER NOT NULL DEFAULT 0;
-- Where it registered: where it returns at the end.
ALTER TABLE robots ADD COLUMN home_x REAL NOT NULL DEFAULT 0;
ALTER TABLE robots ADD COLUMN home_y REAL NOT NULL DEFAULT 0;
-- SHA-256 of its bearer token, hex; NULL before one was issued.
ALTER TABLE robots ADD COLUMN token_sha256 TEXT;
UPDATE robots SET home_x = pose_x, home_y = pose_y;

ALTER TABLE missions ADD COLUMN lease_s REAL NOT NULL DEFAULT 15;
ALTER TABLE missions ADD COLUMN stall_s REAL NOT NULL DEFAULT 30;
ALTER TABLE missions ADD COLUMN rendezvous_x REAL;
ALTER TABLE missions ADD COLUMN rendezvous_y REAL;
ALTER TABLE missions ADD COLUMN paused INTEGER NOT NULL DEFAULT 0;
-- JSON array of {reason, cells, x, y}: the frontier left at completion.
ALTER TABLE missions ADD COLUMN leftovers TEXT NOT NULL DEFAULT '[]';

-- Targets a robot must not be sent to again until the map around them
-- changes (reported unreachable, or stalled on).
CREATE TABLE blacklist (
    robot_id            INTEGER NOT NULL REFERENCES robots (id),
    cell_x              INTEGER NOT NULL,
    cell_y              INTEGER NOT NULL,
    cause               TEXT    NOT NULL,
    created_at          INTEGER NOT NULL,
    PRIMARY KEY (robot_id, cell_x, cell_y)
);

-- Regions where no target is assigned, while `allowed_at` is NULL.
CREATE TABLE forbidden_regions (
    id                  INTEGER PRIMARY KEY AUTOINCREMENT,
    mission_id          INTEGER NOT NULL REFERENCES missions (id),
    min_x               REAL    NOT NULL,
    min_y               REAL    NOT NULL,
    max_x               REAL    NOT NULL,
    max_y               REAL    NOT NULL,
    actor               TEXT    NOT NULL,
    reason              TEXT    NOT NULL,
    created_at          INTEGER NOT NULL,
    allowed_at          INTEGER
);

CREATE INDEX forbidden_regions_by_mission ON forbidden_regions (mission_id, id);
