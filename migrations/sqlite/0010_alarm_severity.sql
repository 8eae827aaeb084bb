-- Spoofwatch schema, version 10: alarm severities (docs/detector.md §7.4).
--
-- An alarm is one episode whose severity only rises: it opens as a warning (or, on decisive
-- evidence, as critical) and a warning can escalate to critical while it is open. `severity` is the
-- highest it reached, `escalated_timestamp_s` (sample time) and `escalated_at` (server wall-clock,
-- unix ms) when it turned critical, NULL while it is a warning. Alarms stored before this version
-- were warnings: the default says so.
ALTER TABLE alarm_events ADD COLUMN severity TEXT NOT NULL DEFAULT 'warning'
    CHECK (severity IN ('warning', 'critical'));
ALTER TABLE alarm_events ADD COLUMN escalated_timestamp_s REAL;
ALTER TABLE alarm_events ADD COLUMN escalated_at INTEGER;

-- The event log gains the escalation as an event kind, and each event keeps the severity the alarm
-- had as the event left it (WatchAlarms filters on it). SQLite cannot change a CHECK constraint in
-- place, so the log is copied into a table of the new shape.
CREATE TABLE alarm_event_log_v10 (
    seq                   INTEGER PRIMARY KEY NOT NULL,
    alarm_id              INTEGER NOT NULL REFERENCES alarm_events (id),
    kind                  TEXT    NOT NULL CHECK (kind IN ('onset', 'escalated', 'end')),
    end_timestamp_s       REAL,
    ended_at              INTEGER,
    peak_probability      REAL    NOT NULL,
    samples               INTEGER NOT NULL CHECK (samples >= 0),
    position              INTEGER,
    severity              TEXT    NOT NULL DEFAULT 'warning'
        CHECK (severity IN ('warning', 'critical')),
    escalated_timestamp_s REAL,
    escalated_at          INTEGER
);
INSERT INTO alarm_event_log_v10 (seq, alarm_id, kind, end_timestamp_s, ended_at, peak_probability,
    samples, position)
SELECT seq, alarm_id, kind, end_timestamp_s, ended_at, peak_probability, samples, position
FROM alarm_event_log;
DROP TABLE alarm_event_log;
ALTER TABLE alarm_event_log_v10 RENAME TO alarm_event_log;
CREATE UNIQUE INDEX alarm_event_log_by_position ON alarm_event_log (position);
