-- Spoofwatch schema, version 6 (PostgreSQL): every alarm keeps why it was raised, the explanation
-- of its onset sample, as migrations/sqlite/0006_alarm_why.sql.
--
-- `why_kind` is the dominant evidence's snake_case name (none, jump, held_offset, drift, frozen_fix,
-- energy); the vectors are east/north: the offset from the dead-reckoning anchor (m) and the drift
-- rate (m/s). The columns are written with the onset and never changed by its end. They are NULL on
-- alarms stored before this version (the API returns no explanation for them).
ALTER TABLE alarm_events ADD COLUMN why_kind TEXT;
ALTER TABLE alarm_events ADD COLUMN why_offset_east_m DOUBLE PRECISION;
ALTER TABLE alarm_events ADD COLUMN why_offset_north_m DOUBLE PRECISION;
ALTER TABLE alarm_events ADD COLUMN why_drift_east_mps DOUBLE PRECISION;
ALTER TABLE alarm_events ADD COLUMN why_drift_north_mps DOUBLE PRECISION;
