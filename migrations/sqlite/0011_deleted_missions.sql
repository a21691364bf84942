-- Missions an operator deleted (DeleteMission). A deleted mission is hidden
-- at once; its robots, tasks, map log and history are then removed a few
-- rows at a time, and `purged` is set once none is left. The mission's own
-- row stays, so that its identity is never given to another mission, and
-- keeps the largest task and region identities it had, so that theirs are
-- not either.
ALTER TABLE missions ADD COLUMN deleted_at INTEGER;
ALTER TABLE missions ADD COLUMN purged INTEGER NOT NULL DEFAULT 0 CHECK (purged IN (0, 1));
ALTER TABLE missions ADD COLUMN last_task_id INTEGER;
ALTER TABLE missions ADD COLUMN last_region_id INTEGER;
