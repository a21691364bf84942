-- Rooms and corridors given with a mission (Wurm et al. 2008, §VI): a
-- label per cell of its map as (label, run length) pairs of little-endian
-- uint32, row-major. No row: the mission segments its explored map online.
CREATE TABLE given_segmentations (
    mission_id  INTEGER PRIMARY KEY REFERENCES missions (id),
    label_runs  BLOB    NOT NULL,
    set_at      INTEGER NOT NULL
);
