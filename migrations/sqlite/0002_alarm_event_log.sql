-- Spoofwatch schema, version 2: the alarm event log behind WatchAlarms.
-- Every alarm onset and end the server emits is one row here, in emission order, so a watcher that
-- reconnects with the cursor (seq) of the last event it saw is replayed exactly what it missed.
-- An end updates its alarm_events row in place; this log keeps each event as it was emitted.

-- One row per server start: its cursors are (run << 32) + n, so the cursors of a run are above every
-- cursor of earlier runs, including those a crash kept from being stored (they were only seen live).
CREATE TABLE alarm_runs (
    run        INTEGER PRIMARY KEY AUTOINCREMENT,
    started_at INTEGER NOT NULL
);

CREATE TABLE alarm_event_log (
    -- The WatchAlarms cursor, assigned by the server in emission order (not by SQLite).
    seq              INTEGER PRIMARY KEY NOT NULL,
    alarm_id         INTEGER NOT NULL REFERENCES alarm_events (id),
    kind             TEXT    NOT NULL CHECK (kind IN ('onset', 'end')),
    -- The alarm as this event left it (vehicle, model and onset come from alarm_events, never
    -- changed after the onset): NULL end columns for an onset; end_timestamp_s is also NULL when
    -- the alarm was closed because its session or the server stopped.
    end_timestamp_s  REAL,
    ended_at         INTEGER,
    peak_probability REAL    NOT NULL,
    samples          INTEGER NOT NULL CHECK (samples >= 0)
);

-- ListAlarms filters.
CREATE INDEX alarm_events_by_model ON alarm_events (model_id);
CREATE INDEX alarm_events_by_onset_at ON alarm_events (onset_at);
