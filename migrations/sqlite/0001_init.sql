-- Spoofwatch schema, version 1.
-- Conventions: ids are TEXT chosen by the service (alarm events excepted); every *_at column is unix epoch
-- milliseconds (UTC) as INTEGER; *_json columns hold JSON text; booleans are INTEGER 0/1.
-- Blobs live in their own tables so that listing queries never read them.
-- Never edit this file once released: sqlx records its checksum. Add 0002_*.sql instead.

CREATE TABLE models (
    id                 TEXT    PRIMARY KEY NOT NULL,
    display_name       TEXT    NOT NULL,
    source             TEXT    NOT NULL CHECK (source IN ('bundled', 'training', 'import')),
    training_operation TEXT,
    created_at         INTEGER NOT NULL,
    schema_version     INTEGER NOT NULL,
    sha256             TEXT    NOT NULL,
    size_bytes         INTEGER NOT NULL CHECK (size_bytes >= 0),
    metadata_json      TEXT    NOT NULL,
    active             INTEGER NOT NULL DEFAULT 0 CHECK (active IN (0, 1))
);

-- At most one active model: the index only holds rows with active = 1, and it is UNIQUE.
CREATE UNIQUE INDEX models_at_most_one_active ON models (active) WHERE active = 1;
CREATE INDEX models_newest_first ON models (created_at DESC, id DESC);

CREATE TABLE model_artifacts (
    model_id TEXT PRIMARY KEY NOT NULL REFERENCES models (id) ON DELETE CASCADE,
    artifact BLOB NOT NULL
);

CREATE TABLE datasets (
    id            TEXT    PRIMARY KEY NOT NULL,
    display_name  TEXT    NOT NULL,
    source        TEXT    NOT NULL,
    format        TEXT    NOT NULL,
    rows          INTEGER NOT NULL CHECK (rows >= 0),
    vehicles      INTEGER NOT NULL CHECK (vehicles >= 0),
    labelled_rows INTEGER NOT NULL CHECK (labelled_rows >= 0),
    spoofed_rows  INTEGER NOT NULL CHECK (spoofed_rows >= 0),
    size_bytes    INTEGER NOT NULL CHECK (size_bytes >= 0),
    sha256        TEXT    NOT NULL,
    created_at    INTEGER NOT NULL
);

CREATE INDEX datasets_newest_first ON datasets (created_at DESC, id DESC);

CREATE TABLE dataset_contents (
    dataset_id TEXT PRIMARY KEY NOT NULL REFERENCES datasets (id) ON DELETE CASCADE,
    content    BLOB NOT NULL
);

CREATE TABLE jobs (
    id               TEXT    PRIMARY KEY NOT NULL,
    kind             TEXT    NOT NULL CHECK (kind IN ('training', 'evaluation')),
    state            TEXT    NOT NULL
                             CHECK (state IN ('queued', 'running', 'succeeded', 'failed', 'cancelled')),
    request_json     TEXT    NOT NULL,
    metadata_json    TEXT    NOT NULL,
    result_json      TEXT,
    error_code       INTEGER,
    error_message    TEXT,
    created_at       INTEGER NOT NULL,
    started_at       INTEGER,
    finished_at      INTEGER,
    cancel_requested INTEGER NOT NULL DEFAULT 0 CHECK (cancel_requested IN (0, 1))
);

CREATE INDEX jobs_newest_first ON jobs (created_at DESC, id DESC);
CREATE INDEX jobs_by_state ON jobs (state);

CREATE TABLE job_epochs (
    job_id        TEXT    NOT NULL REFERENCES jobs (id) ON DELETE CASCADE,
    epoch         INTEGER NOT NULL CHECK (epoch >= 0),
    train_loss    REAL    NOT NULL,
    val_loss      REAL    NOT NULL,
    val_auroc     REAL,
    learning_rate REAL    NOT NULL,
    elapsed_s     REAL    NOT NULL,
    PRIMARY KEY (job_id, epoch)
);

CREATE TABLE alarm_events (
    id                INTEGER PRIMARY KEY AUTOINCREMENT,
    vehicle_id        TEXT    NOT NULL,
    model_id          TEXT    NOT NULL,
    onset_timestamp_s REAL    NOT NULL,
    -- NULL while open, and also when the session ended while still alarming (see ended_at).
    end_timestamp_s   REAL,
    onset_at          INTEGER NOT NULL,
    ended_at          INTEGER,
    peak_probability  REAL    NOT NULL,
    samples           INTEGER NOT NULL CHECK (samples >= 0)
);

CREATE INDEX alarm_events_by_vehicle ON alarm_events (vehicle_id, onset_timestamp_s);
