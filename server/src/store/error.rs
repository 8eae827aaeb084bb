//! The store's error type.

/// Everything a store operation can fail with.
///
/// `Database` and `Migration` wrap sqlx errors whose text may reveal internals: callers map them to
/// INTERNAL and log them rather than showing them to clients. Every other variant is safe to show.
#[derive(Debug, thiserror::Error)]
pub enum StoreError {
    /// No row of `kind` (e.g. "model") has this id.
    #[error("{kind} '{id}' not found")]
    NotFound {
        /// What was looked up: "model", "dataset", "job" or "alarm event".
        kind: &'static str,
        /// The id that matched nothing.
        id: String,
    },
    /// A row of `kind` with this id already exists.
    #[error("{kind} '{id}' already exists")]
    AlreadyExists {
        /// What was inserted: "model", "dataset", "job" or "epoch".
        kind: &'static str,
        /// The conflicting id (for an epoch: "job/epoch").
        id: String,
    },
    /// The model is the active one and cannot be deleted.
    #[error("model '{id}' is the active model; activate another model before deleting it")]
    ModelActive {
        /// The active model's id.
        id: String,
    },
    /// The job is still queued or running and cannot be deleted.
    #[error("job '{id}' is {state} and cannot be deleted until it finishes; cancel it first")]
    JobNotFinished {
        /// The job's id.
        id: String,
        /// Its current state ("queued" or "running").
        state: &'static str,
    },
    /// The requested transition is not allowed from the row's current state.
    #[error("cannot {action} {kind} '{id}': it is {state}")]
    InvalidState {
        /// What kind of row: "job" or "alarm event".
        kind: &'static str,
        /// The row's id.
        id: String,
        /// What was attempted, e.g. "finish" or "mark running".
        action: &'static str,
        /// The state that forbids it, e.g. "succeeded".
        state: &'static str,
    },
    /// A page token that this store did not issue for this listing.
    #[error("invalid page token")]
    InvalidPageToken,
    /// A value the schema cannot hold (e.g. a non-finite loss or probability).
    #[error("invalid {field}: {reason}")]
    InvalidValue {
        /// The offending field.
        field: &'static str,
        /// Why it was rejected.
        reason: String,
    },
    /// The database failed (I/O, corruption, lock timeout, closed pool...).
    #[error("database error")]
    Database(#[source] sqlx::Error),
    /// Applying the embedded migrations failed.
    #[error("database migration failed")]
    Migration(#[source] sqlx::migrate::MigrateError),
}

impl From<sqlx::Error> for StoreError {
    fn from(error: sqlx::Error) -> Self {
        StoreError::Database(error)
    }
}

impl From<sqlx::migrate::MigrateError> for StoreError {
    fn from(error: sqlx::migrate::MigrateError) -> Self {
        StoreError::Migration(error)
    }
}

/// An INSERT's failure: a UNIQUE or PRIMARY KEY clash is `AlreadyExists` for `kind`/`id`, anything
/// else a database error.
pub(crate) fn insert_error(error: sqlx::Error, kind: &'static str, id: &str) -> StoreError {
    if error
        .as_database_error()
        .is_some_and(|db_error| db_error.is_unique_violation())
    {
        StoreError::AlreadyExists {
            kind,
            id: id.to_string(),
        }
    } else {
        error.into()
    }
}

/// The length of a blob as the INTEGER its `size_bytes` column holds.
pub(crate) fn byte_length(field: &'static str, bytes: &[u8]) -> Result<i64, StoreError> {
    i64::try_from(bytes.len()).map_err(|_| StoreError::InvalidValue {
        field,
        reason: "larger than i64::MAX bytes".to_owned(),
    })
}

/// Rejects NaN and infinities, which SQLite would silently store as NULL (or reject as NOT NULL).
pub(crate) fn require_finite(field: &'static str, value: f64) -> Result<f64, StoreError> {
    if value.is_finite() {
        Ok(value)
    } else {
        Err(StoreError::InvalidValue {
            field,
            reason: format!("must be a finite number, got {value}"),
        })
    }
}

/// Rejects a probability outside [0, 1] (or NaN).
pub(crate) fn require_probability(field: &'static str, value: f64) -> Result<f64, StoreError> {
    if (0.0..=1.0).contains(&value) {
        Ok(value)
    } else {
        Err(StoreError::InvalidValue {
            field,
            reason: format!("must be a probability in [0, 1], got {value}"),
        })
    }
}
