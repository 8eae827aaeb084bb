-- Spoofwatch schema, version 10 (PostgreSQL): alarm severities, as
-- migrations/sqlite/0010_alarm_severity.sql.
--
-- An alarm is one episode whose severity only rises: it opens as a warning (or, on decisive
-- evidence, as critical) and a warning can escalate to critical while it is open. `severity` is the
-- highest it reached, `escalated_timestamp_s` (sample time) and `escalated_at` (server wall-clock,
-- unix ms) when it turned critical, NULL while it is a warning. Alarms stored before this version
-- were warnings: the default says so.
ALTER TABLE alarm_events ADD COLUMN severity TEXT NOT NULL DEFAULT 'warning'
    CHECK (severity IN ('warning', 'critical'));
ALTER TABLE alarm_events ADD COLUMN escalated_timestamp_s DOUBLE PRECISION;
ALTER TABLE alarm_events ADD COLUMN escalated_at BIGINT;

-- The event log gains the escalation as an event kind, and each event keeps the severity the alarm
-- had as the event left it (WatchAlarms filters on it).
ALTER TABLE alarm_event_log DROP CONSTRAINT alarm_event_log_kind_check;
ALTER TABLE alarm_event_log ADD CONSTRAINT alarm_event_log_kind_check
    CHECK (kind IN ('onset', 'escalated', 'end'));
ALTER TABLE alarm_event_log ADD COLUMN severity TEXT NOT NULL DEFAULT 'warning'
    CHECK (severity IN ('warning', 'critical'));
ALTER TABLE alarm_event_log ADD COLUMN escalated_timestamp_s DOUBLE PRECISION;
ALTER TABLE alarm_event_log ADD COLUMN escalated_at BIGINT;
