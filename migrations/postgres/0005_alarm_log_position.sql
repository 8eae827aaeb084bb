-- Spoofwatch schema, version 5 (PostgreSQL): the WatchAlarms cursor becomes a log position the
-- database assigns, as migrations/sqlite/0005_alarm_log_position.sql.
--
-- `seq` stays the writer's idempotency key ((run << 32) + n, assigned before the write): with
-- replicas writing into one database, two runs' seqs interleave, and a row can commit below a seq
-- a reader has already passed. `position` is assigned inside the write transaction after it has
-- taken the write lock (`COALESCE(MAX(position), 0) + 1`), and the lock is released only once the
-- transaction has committed, so positions increase in commit order: a reader that has seen position
-- p never later finds a newly committed row below p. That is what makes a cursor resumable on any
-- replica.
ALTER TABLE alarm_event_log ADD COLUMN position BIGINT;

-- Existing rows in cursor (seq) order: 1, 2, 3, ...
UPDATE alarm_event_log
SET position = numbered.position
FROM (SELECT seq, ROW_NUMBER() OVER (ORDER BY seq) AS position FROM alarm_event_log) AS numbered
WHERE alarm_event_log.seq = numbered.seq;

ALTER TABLE alarm_event_log ALTER COLUMN position SET NOT NULL;
CREATE UNIQUE INDEX alarm_event_log_by_position ON alarm_event_log (position);
