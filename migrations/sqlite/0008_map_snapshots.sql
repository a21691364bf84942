-- A mission's oldest map patches, folded into the fused map they make (see
-- server/src/store/compact.rs). Replaces those patches in map_patches: on
-- start-up a mission's map is its snapshot, then the patches logged after
-- `through_patch_id`.
CREATE TABLE map_snapshots (
    mission_id          INTEGER PRIMARY KEY REFERENCES missions (id),
    -- map_patches.id of the last patch folded in.
    through_patch_id    INTEGER NOT NULL,
    -- Patches folded in, in all.
    folded              INTEGER NOT NULL,
    -- The fused map, one LZ4 block (server/src/store/snapshot.rs).
    state               BLOB    NOT NULL,
    -- Its size decompressed.
    raw_bytes           INTEGER NOT NULL,
    taken_at            INTEGER NOT NULL
);
