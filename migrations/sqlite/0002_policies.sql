-- The information-gain region a task's target was expected to reveal
-- (Simmons et al. 2000), in cells of the mission grid; NULL when the policy
-- estimates none. Needed for hysteresis.
ALTER TABLE tasks ADD COLUMN gain_x INTEGER;
ALTER TABLE tasks ADD COLUMN gain_y INTEGER;
ALTER TABLE tasks ADD COLUMN gain_width INTEGER;
ALTER TABLE tasks ADD COLUMN gain_height INTEGER;

-- Things that happen to a mission as a whole: policy changes, ...
CREATE TABLE mission_events (
    id                  INTEGER PRIMARY KEY AUTOINCREMENT,
    mission_id          INTEGER NOT NULL REFERENCES missions (id),
    at                  INTEGER NOT NULL,
    kind                TEXT    NOT NULL,
    detail              TEXT    NOT NULL,
    actor               TEXT    NOT NULL
);

CREATE INDEX mission_events_by_mission ON mission_events (mission_id, id);

-- The latest segmentation of each mission's explored map (Wurm et al. 2008).
-- labels: run-length encoded, little-endian (label u32, run length u32)
-- pairs over the row-major cells; segments and critical_points: JSON.
CREATE TABLE segmentations (
    mission_id          INTEGER PRIMARY KEY REFERENCES missions (id),
    computed_at         INTEGER NOT NULL,
    labels              BLOB    NOT NULL,
    segments            TEXT    NOT NULL,
    critical_points     TEXT    NOT NULL
);
