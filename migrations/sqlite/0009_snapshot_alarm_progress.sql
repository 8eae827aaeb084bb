-- Spoofwatch schema, version 9: how far a session snapshot's open alarm got.
--
-- Two copies of one session can reach the store in either order: the one a process holds, and the
-- one another process read when it replaced that session (a roll-out). The alarm the session held
-- ends at the latest alarming sample that any copy saw, so the store keeps each copy's progress on
-- that alarm where the end can be taken from it. NULL when the snapshot holds no alarm open, and
-- on snapshots stored before this version.
ALTER TABLE session_snapshots ADD COLUMN open_alarm_last_timestamp_s REAL;
ALTER TABLE session_snapshots ADD COLUMN open_alarm_peak_probability REAL;
ALTER TABLE session_snapshots ADD COLUMN open_alarm_samples INTEGER CHECK (open_alarm_samples >= 0);
CREATE INDEX session_snapshots_by_open_alarm ON session_snapshots (open_alarm_id);
