-- Spoofwatch schema, version 4: session snapshots, the hand-off of a vehicle's detection state between
-- server processes (replicas, restarts). One row per vehicle: the latest snapshot its session wrote.
-- The snapshot blob is the server's own versioned, checksummed encoding; the other columns are what
-- the store reads without decoding it.

CREATE TABLE session_snapshots (
    vehicle_id     TEXT    PRIMARY KEY NOT NULL,
    model_id       TEXT    NOT NULL,
    schema_version INTEGER NOT NULL,
    -- Samples the session had processed, and the last batch sequence number it accepted.
    samples        INTEGER NOT NULL CHECK (samples >= 0),
    last_seq       INTEGER NOT NULL CHECK (last_seq >= 0),
    -- The alarm the session holds open: it stays open across a hand-off (never closed at a start).
    open_alarm_id  INTEGER REFERENCES alarm_events (id),
    -- The server process that wrote it (its alarm run).
    writer         TEXT    NOT NULL,
    updated_at     INTEGER NOT NULL,
    snapshot       BLOB    NOT NULL
);

CREATE INDEX session_snapshots_by_updated_at ON session_snapshots (updated_at);
CREATE INDEX session_snapshots_by_model ON session_snapshots (model_id);
