-- Spoofwatch schema, version 5: the WatchAlarms cursor becomes a log position the database assigns.
--
-- `seq` stays the writer's idempotency key ((run << 32) + n, assigned before the write): with
-- several processes writing into one database, two runs' seqs interleave, and a row can commit
-- below a seq a reader has already passed. `position` is assigned inside the write transaction
-- (`COALESCE(MAX(position), 0) + 1`), which holds SQLite's single write lock (BEGIN IMMEDIATE) until
-- it commits, so positions increase in commit order: a reader that has seen position p never later
-- finds a newly committed row below p.
--
-- SQLite cannot add a NOT NULL column without a default to a table: every insert sets it, and the
-- unique index below keeps two rows from sharing one.
ALTER TABLE alarm_event_log ADD COLUMN position INTEGER;

-- Existing rows in cursor (seq) order: 1, 2, 3, ...
UPDATE alarm_event_log
SET position = numbered.position
FROM (SELECT seq, ROW_NUMBER() OVER (ORDER BY seq) AS position FROM alarm_event_log) AS numbered
WHERE alarm_event_log.seq = numbered.seq;

CREATE UNIQUE INDEX alarm_event_log_by_position ON alarm_event_log (position);
