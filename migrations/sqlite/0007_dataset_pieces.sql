-- Spoofwatch schema, version 7: a dataset's bytes are stored as ordered pieces of at most 1 MiB, so
-- that storing or loading a large dataset never needs its bytes in one contiguous buffer (nor the
-- database driver's copy of one). A dataset stored before this version becomes its single piece 0.
CREATE TABLE dataset_pieces (
    dataset_id TEXT    NOT NULL REFERENCES datasets (id) ON DELETE CASCADE,
    piece      INTEGER NOT NULL CHECK (piece >= 0),
    content    BLOB    NOT NULL,
    PRIMARY KEY (dataset_id, piece)
);

INSERT INTO dataset_pieces (dataset_id, piece, content)
    SELECT dataset_id, 0, content FROM dataset_contents;

DROP TABLE dataset_contents;
