-- Missions, robots, the map update log, tasks and their transitions.
-- Times are milliseconds since the Unix epoch (UTC).

CREATE TABLE missions (
    id                  INTEGER PRIMARY KEY AUTOINCREMENT,
    name                TEXT    NOT NULL,
    resolution          REAL    NOT NULL CHECK (resolution > 0),
    origin_x            REAL    NOT NULL,
    origin_y            REAL    NOT NULL,
    width               INTEGER NOT NULL CHECK (width > 0),
    height              INTEGER NOT NULL CHECK (height > 0),
    policy              TEXT    NOT NULL,
    -- JSON object of parameter name -> value, every parameter filled in.
    policy_params       TEXT    NOT NULL,
    replan_distance_m   REAL    NOT NULL,
    replan_interval_s   REAL    NOT NULL,
    replan_frontier_change REAL NOT NULL,
    state               TEXT    NOT NULL CHECK (state IN ('active', 'completed')),
    replans             INTEGER NOT NULL DEFAULT 0,
    map_updates         INTEGER NOT NULL DEFAULT 0,
    created_at          INTEGER NOT NULL,
    updated_at          INTEGER NOT NULL
);

CREATE TABLE robots (
    id                  INTEGER PRIMARY KEY AUTOINCREMENT,
    mission_id          INTEGER NOT NULL REFERENCES missions (id),
    name                TEXT    NOT NULL,
    sensor_range_m      REAL    NOT NULL,
    field_of_view_rad   REAL    NOT NULL,
    speed_mps           REAL    NOT NULL,
    footprint_radius_m  REAL    NOT NULL,
    state               TEXT    NOT NULL CHECK (state IN ('idle', 'moving', 'arrived', 'failed')),
    pose_x              REAL    NOT NULL,
    pose_y              REAL    NOT NULL,
    pose_theta          REAL    NOT NULL,
    -- Highest applied map sequence number (0 = none yet).
    last_map_seq        INTEGER NOT NULL DEFAULT 0,
    distance_m          REAL    NOT NULL DEFAULT 0,
    -- Replanning state: how far the robot had travelled at the latest
    -- replanning, and the version of its assignment.
    assignment_version  INTEGER NOT NULL DEFAULT 0,
    assigned_distance_m REAL    NOT NULL DEFAULT 0,
    current_task_id     INTEGER,
    last_seen           INTEGER NOT NULL,
    created_at          INTEGER NOT NULL,
    UNIQUE (mission_id, name)
);

CREATE INDEX robots_by_mission ON robots (mission_id);

-- Every acknowledged map update, in the order it was applied; replayed on
-- start-up to rebuild the fused map. Cells are little-endian f32 log-odds,
-- NaN for cells the robot marked unknown.
CREATE TABLE map_patches (
    id                  INTEGER PRIMARY KEY AUTOINCREMENT,
    mission_id          INTEGER NOT NULL REFERENCES missions (id),
    robot_id            INTEGER NOT NULL REFERENCES robots (id),
    seq                 INTEGER NOT NULL,
    x                   INTEGER NOT NULL,
    y                   INTEGER NOT NULL,
    width               INTEGER NOT NULL,
    height              INTEGER NOT NULL,
    cells               BLOB    NOT NULL,
    received_at         INTEGER NOT NULL
);

CREATE INDEX map_patches_by_mission ON map_patches (mission_id, id);

CREATE TABLE tasks (
    id                  INTEGER PRIMARY KEY AUTOINCREMENT,
    mission_id          INTEGER NOT NULL REFERENCES missions (id),
    robot_id            INTEGER NOT NULL REFERENCES robots (id),
    target_x            REAL    NOT NULL,
    target_y            REAL    NOT NULL,
    state               TEXT    NOT NULL CHECK (state IN
        ('assigned', 'active', 'reached', 'preempted', 'overridden', 'failed', 'released', 'cancelled')),
    policy              TEXT    NOT NULL,
    utility             REAL    NOT NULL,
    path_cost           REAL    NOT NULL,
    created_at          INTEGER NOT NULL,
    updated_at          INTEGER NOT NULL
);

CREATE INDEX tasks_by_mission ON tasks (mission_id, id);
CREATE INDEX tasks_by_robot ON tasks (robot_id, id);

-- Every state change of every task, with why and who.
CREATE TABLE task_transitions (
    id                  INTEGER PRIMARY KEY AUTOINCREMENT,
    task_id             INTEGER NOT NULL REFERENCES tasks (id),
    from_state          TEXT,
    to_state            TEXT    NOT NULL,
    cause               TEXT    NOT NULL,
    actor               TEXT    NOT NULL CHECK (actor IN ('policy', 'robot', 'operator', 'lease', 'executive')),
    at                  INTEGER NOT NULL
);

CREATE INDEX task_transitions_by_task ON task_transitions (task_id, id);

-- The latest bids of each robot (Simmons et al. 2000, §4.1).
CREATE TABLE bids (
    robot_id            INTEGER NOT NULL REFERENCES robots (id),
    ordinal             INTEGER NOT NULL,
    target_x            REAL    NOT NULL,
    target_y            REAL    NOT NULL,
    path_cost           REAL    NOT NULL,
    information_gain    REAL    NOT NULL,
    region_min_x        REAL    NOT NULL,
    region_min_y        REAL    NOT NULL,
    region_max_x        REAL    NOT NULL,
    region_max_y        REAL    NOT NULL,
    submitted_at        INTEGER NOT NULL,
    PRIMARY KEY (robot_id, ordinal)
);
