-- Spoofwatch schema, version 3: job ownership, so that replicas can share one database.
-- A queued or running job belongs to the server process (instance) that admitted it and runs it;
-- that process refreshes heartbeat_at every few seconds. A job whose owner stopped refreshing it
-- (its lease expired) is failed by any other server; a job left by an earlier run of the same
-- instance is failed at its next start. Rows from before this version have no owner: the first
-- start fails them if they are unfinished, as every start used to.
ALTER TABLE jobs ADD COLUMN owner TEXT;
ALTER TABLE jobs ADD COLUMN heartbeat_at BIGINT;
