-- Spoofwatch schema, version 8: where each alarm started, and area incidents.
--
-- An alarm's onset fix (the reported position of its first alarming sample) places it; with the
-- offset of its explanation it gives the vehicle's true position, which area incidents correlate.
-- NULL on alarms stored before this version (they take no part in incidents).
ALTER TABLE alarm_events ADD COLUMN onset_latitude_deg DOUBLE PRECISION;
ALTER TABLE alarm_events ADD COLUMN onset_longitude_deg DOUBLE PRECISION;

-- One row per incident: the incident as its latest change left it (`spoofwatch_core::incident::
-- Incident` as JSON). Ids are the correlator's (1, 2, 3, ...).
CREATE TABLE incidents (
    id         BIGINT PRIMARY KEY NOT NULL,
    -- Wall-clock time the incident was stored as opened, and ended (NULL while open).
    opened_at  BIGINT  NOT NULL,
    ended_at   BIGINT,
    body_json  JSONB   NOT NULL
);
CREATE INDEX incidents_open ON incidents (ended_at);

-- The event log behind WatchIncidents: positions assigned in commit order inside the write
-- transaction, as for the alarm event log.
CREATE TABLE incident_event_log (
    position    BIGINT PRIMARY KEY NOT NULL,
    incident_id BIGINT  NOT NULL REFERENCES incidents (id),
    kind        TEXT    NOT NULL CHECK (kind IN ('opened', 'joined', 'ended')),
    stored_at   BIGINT  NOT NULL,
    -- The incident as this event left it.
    body_json   JSONB   NOT NULL
);

-- The one correlator of the database: who computes incidents (a lease, renewed by heartbeat_at),
-- how far into the alarm event log it has read, and its state (`spoofwatch_core::incident::
-- AreaState` as JSON). A replica takes the lease over once it expires, and continues from here.
CREATE TABLE incident_correlator (
    id             BIGINT PRIMARY KEY NOT NULL CHECK (id = 1),
    owner          TEXT,
    heartbeat_at   BIGINT,
    alarm_position BIGINT  NOT NULL,
    state_json     JSONB
);
INSERT INTO incident_correlator (id, owner, heartbeat_at, alarm_position, state_json)
VALUES (1, NULL, NULL, 0, NULL);
