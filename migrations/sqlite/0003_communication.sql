-- Coordination scoped by communication (Burgard et al. 2005, §II-D): robots
-- report whom they can reach; each connected sub-team is planned apart.
ALTER TABLE missions ADD COLUMN scoped_by_communication INTEGER NOT NULL DEFAULT 0;
