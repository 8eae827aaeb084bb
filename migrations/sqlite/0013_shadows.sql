-- Spoofwatch schema, version 13: shadow evaluation of a candidate model.
--
-- One row per shadow: the candidate, which vehicles it scores (`scope_json`: all, a share by a
-- stable hash of the vehicle id, or a list) and who started and stopped it. At most one is running
-- (`stopped_at` NULL) per database; the server checks it inside its write transaction. Every
-- replica reads the running one, so it survives restarts and is seen by all.
CREATE TABLE shadows (
    id          INTEGER PRIMARY KEY AUTOINCREMENT NOT NULL,
    model_id    TEXT    NOT NULL,
    scope_json  TEXT    NOT NULL,
    started_at  INTEGER  NOT NULL,
    started_by  TEXT    NOT NULL,
    stopped_at  INTEGER,
    stopped_by  TEXT
);

-- Each server process's cumulative counts for a shadow (`process` is the instance id and the
-- process's start time), rewritten whole every few seconds: the summary is their sum.
CREATE TABLE shadow_tallies (
    shadow_id   INTEGER  NOT NULL REFERENCES shadows (id) ON DELETE CASCADE,
    process     TEXT    NOT NULL,
    updated_at  INTEGER  NOT NULL,
    tally_json  TEXT    NOT NULL,
    PRIMARY KEY (shadow_id, process)
);

-- The vehicles a shadow scored and how often each one's shadow state started (afresh after the
-- first: a restart, hand-off, shed samples, idleness or a live reset).
CREATE TABLE shadow_vehicles (
    shadow_id   INTEGER  NOT NULL REFERENCES shadows (id) ON DELETE CASCADE,
    vehicle_id  TEXT    NOT NULL,
    starts      INTEGER  NOT NULL,
    PRIMARY KEY (shadow_id, vehicle_id)
);

-- The candidate's would-be alarms: apart from `alarm_events`, so that nothing reads them as real
-- (never in WatchAlarms, never paged, never in the real alarm metrics). An episode is keyed by its
-- vehicle and onset sample time within its shadow.
CREATE TABLE shadow_alarms (
    id                     INTEGER PRIMARY KEY AUTOINCREMENT NOT NULL,
    shadow_id              INTEGER  NOT NULL REFERENCES shadows (id) ON DELETE CASCADE,
    vehicle_id             TEXT    NOT NULL,
    model_id               TEXT    NOT NULL,
    onset_timestamp_s      REAL    NOT NULL,
    onset_at               INTEGER  NOT NULL,
    severity               TEXT    NOT NULL CHECK (severity IN ('warning', 'critical')),
    escalated_timestamp_s  REAL,
    peak_probability       REAL    NOT NULL,
    end_timestamp_s        REAL,
    ended_at               INTEGER,
    end_reason             TEXT CHECK (end_reason IN ('cleared', 'restarted', 'shed', 'idle', 'reset', 'stopped')),
    live_alarmed           INTEGER NOT NULL,
    UNIQUE (shadow_id, vehicle_id, onset_timestamp_s)
);
CREATE INDEX shadow_alarms_open ON shadow_alarms (shadow_id, vehicle_id, ended_at);
