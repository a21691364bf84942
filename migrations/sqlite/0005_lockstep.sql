-- Missions planned inside the request that makes a replanning due
-- (simulations); the others are planned off the request path.
ALTER TABLE missions ADD COLUMN lockstep INTEGER NOT NULL DEFAULT 0;
