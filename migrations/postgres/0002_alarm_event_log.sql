-- Spoofwatch schema, version 2 (PostgreSQL): the alarm event log behind WatchAlarms, as
-- migrations/sqlite/0002_alarm_event_log.sql.
-- Every alarm onset and end the server emits is one row here, in emission order, so a watcher that
-- reconnects with the cursor (seq) of the last event it saw is replayed exactly what it missed.
-- An end updates its alarm_events row in place; this log keeps each event as it was emitted.

-- One row per server start: its cursors are (run << 32) + n, so the cursors of a run are above every
-- cursor of earlier runs, including those a crash kept from being stored (they were only seen live).
CREATE TABLE alarm_runs (
    run        BIGINT GENERATED ALWAYS AS IDENTITY PRIMARY KEY,
    started_at BIGINT NOT NULL
);

CREATE TABLE alarm_event_log (
    -- The WatchAlarms cursor, assigned by the server in emission order (not by the database).
    seq              BIGINT           PRIMARY KEY NOT NULL,
    alarm_id         BIGINT           NOT NULL REFERENCES alarm_events (id),
    kind             TEXT             NOT NULL CHECK (kind IN ('onset', 'end')),
    -- The alarm as this event left it (vehicle, model and onset come from alarm_events, never
    -- changed after the onset): NULL end columns for an onset; end_timestamp_s is also NULL when
    -- the alarm was closed because its session or the server stopped.
    end_timestamp_s  DOUBLE PRECISION,
    ended_at         BIGINT,
    peak_probability DOUBLE PRECISION NOT NULL,
    samples          BIGINT           NOT NULL CHECK (samples >= 0)
);

-- ListAlarms filters.
CREATE INDEX alarm_events_by_model ON alarm_events (model_id);
CREATE INDEX alarm_events_by_onset_at ON alarm_events (onset_at);
