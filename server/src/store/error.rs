//! The store's error type, and the classification of database faults.

use std::sync::OnceLock;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, Instant};

/// Everything a store operation can fail with.
///
/// `Database` and `Migration` wrap sqlx errors whose text may reveal internals: callers map them to
/// INTERNAL and log them rather than showing them to clients (a migration fails only at startup,
/// where its message is for the operator). Every other variant is safe to show.
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
    /// The database is unusable for a reason outside this request: full, read-only, failing I/O,
    /// locked, missing, corrupt or closed. Safe to show (the kind), and worth retrying later.
    #[error("{0}")]
    Unavailable(StoreFault),
    /// Any other database failure (a query or decoding bug): logged, answered INTERNAL.
    #[error("database error")]
    Database(#[source] sqlx::Error),
    /// Applying the embedded migrations failed: the message names the migration and the cause.
    #[error("database migration failed: {0}")]
    Migration(MigrationError),
}

/// Why the schema could not be brought to this build's version, for the operator reading the
/// start error: which migration (version and description) and what went wrong.
#[derive(Debug, thiserror::Error)]
#[error("{message}")]
pub struct MigrationError {
    message: String,
    #[source]
    source: sqlx::migrate::MigrateError,
}

/// `error` from running `migrator`, described with the migrations this build knows.
pub(crate) fn migration_error(
    migrator: &sqlx::migrate::Migrator,
    error: sqlx::migrate::MigrateError,
) -> StoreError {
    use sqlx::migrate::MigrateError;
    let named = |version: i64| match migrator.iter().find(|m| m.version == version) {
        Some(migration) => format!("migration {version} ({})", migration.description),
        None => format!("migration {version}"),
    };
    let latest = migrator.iter().map(|m| m.version).max().unwrap_or(0);
    let message = match &error {
        MigrateError::VersionMismatch(version) => format!(
            "{} was applied to this database with other contents than this build's (its checksum \
             differs): the database was migrated by another Spoofwatch build; run that build or \
             restore a backup",
            named(*version)
        ),
        MigrateError::VersionMissing(version) | MigrateError::VersionNotPresent(version) => {
            format!(
                "migration {version} is applied to this database but unknown to this build (it \
                 knows migrations up to {latest}): the database was written by a newer Spoofwatch; \
                 run that version or restore a backup"
            )
        }
        MigrateError::ExecuteMigration(cause, version) => {
            format!("{} failed: {cause}", named(*version))
        }
        MigrateError::Dirty(version) => format!(
            "{} is partially applied; fix the schema and remove its row from _sqlx_migrations",
            named(*version)
        ),
        other => other.to_string(),
    };
    StoreError::Migration(MigrationError {
        message,
        source: error,
    })
}

impl From<sqlx::Error> for StoreError {
    fn from(error: sqlx::Error) -> Self {
        match FaultKind::of(&error) {
            Some(kind) => {
                if kind.may_spoil_connections() {
                    note_connection_fault();
                }
                StoreError::Unavailable(StoreFault::seen(kind, error.to_string()))
            }
            None => StoreError::Database(error),
        }
    }
}

/// Why the database cannot serve right now. Each kind clears without a restart once its cause does
/// (space freed, file system writable again, lock released), except `Lost`, which needs an
/// operator: the file the server opened is gone or replaced.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum FaultKind {
    /// SQLITE_FULL: the disk (or the configured database size limit) is full.
    Full,
    /// SQLITE_READONLY: the database file or its file system became read-only.
    ReadOnly,
    /// SQLITE_IOERR: the file system failed a read or write.
    Io,
    /// SQLITE_BUSY/LOCKED, a PostgreSQL lock or statement timeout, or no pooled connection in time
    /// (also while a PostgreSQL server cannot be reached: the pool keeps trying until its timeout).
    Busy,
    /// SQLITE_CANTOPEN: the database file or its directory cannot be opened.
    CantOpen,
    /// SQLITE_CORRUPT/NOTADB: the file is damaged or not a database.
    Corrupt,
    /// The database file was deleted, moved or replaced while the server ran.
    Lost,
    /// The store was closed (the server is shutting down).
    Closed,
    /// The database server (PostgreSQL) refused or dropped the connection, or is shutting down.
    Unreachable,
}

impl FaultKind {
    /// Every kind (the label values of the store-fault metric).
    pub const ALL: [FaultKind; 9] = [
        FaultKind::Full,
        FaultKind::ReadOnly,
        FaultKind::Io,
        FaultKind::Busy,
        FaultKind::CantOpen,
        FaultKind::Corrupt,
        FaultKind::Lost,
        FaultKind::Closed,
        FaultKind::Unreachable,
    ];

    /// The kind of a sqlx error that is a fault of the database rather than of the query: from the
    /// SQLite primary result code (the low byte of the extended code) or the PostgreSQL SQLSTATE.
    pub fn of(error: &sqlx::Error) -> Option<FaultKind> {
        match error {
            sqlx::Error::PoolTimedOut => Some(FaultKind::Busy),
            sqlx::Error::PoolClosed | sqlx::Error::WorkerCrashed => Some(FaultKind::Closed),
            sqlx::Error::Io(io) => Some(Self::of_io(io)),
            sqlx::Error::Database(db_error) => {
                if let Some(pg) = db_error.try_downcast_ref::<sqlx::postgres::PgDatabaseError>() {
                    return Self::of_sqlstate(pg.code());
                }
                let code: i32 = db_error.code()?.parse().ok()?;
                match code {
                    // SQLITE_READONLY_DBMOVED: the file was unlinked or renamed under us.
                    1032 => Some(FaultKind::Lost),
                    _ => match code & 0xff {
                        13 => Some(FaultKind::Full),
                        8 => Some(FaultKind::ReadOnly),
                        10 => Some(FaultKind::Io),
                        5 | 6 => Some(FaultKind::Busy),
                        14 => Some(FaultKind::CantOpen),
                        11 | 26 => Some(FaultKind::Corrupt),
                        _ => None,
                    },
                }
            }
            _ => None,
        }
    }

    /// An I/O error talking to the database: a lost or refused connection to a database server is
    /// [`FaultKind::Unreachable`]; anything else (SQLite's own file I/O) is [`FaultKind::Io`].
    fn of_io(error: &std::io::Error) -> FaultKind {
        use std::io::ErrorKind;
        match error.kind() {
            ErrorKind::ConnectionRefused
            | ErrorKind::ConnectionReset
            | ErrorKind::ConnectionAborted
            | ErrorKind::NotConnected
            | ErrorKind::BrokenPipe
            | ErrorKind::UnexpectedEof
            | ErrorKind::TimedOut
            | ErrorKind::HostUnreachable
            | ErrorKind::NetworkUnreachable
            | ErrorKind::AddrNotAvailable => FaultKind::Unreachable,
            _ => FaultKind::Io,
        }
    }

    /// The kind of a PostgreSQL error from its SQLSTATE (None: the query's own fault, e.g. a
    /// constraint violation or a bug).
    fn of_sqlstate(code: &str) -> Option<FaultKind> {
        match code {
            // disk_full
            "53100" => Some(FaultKind::Full),
            // insufficient_resources, out_of_memory, too_many_connections, query_canceled (the
            // statement timeout), serialization_failure, deadlock_detected, lock_not_available
            "53000" | "53200" | "53300" | "57014" | "40001" | "40P01" | "55P03" => {
                Some(FaultKind::Busy)
            }
            // admin_shutdown, crash_shutdown, cannot_connect_now (starting or stopping), database
            // dropped; class 08: connection exceptions
            "57P01" | "57P02" | "57P03" | "57P04" => Some(FaultKind::Unreachable),
            _ if code.starts_with("08") => Some(FaultKind::Unreachable),
            // read_only_sql_transaction: a hot standby or a read-only default
            "25006" => Some(FaultKind::ReadOnly),
            // io_error (system_error class)
            "58030" => Some(FaultKind::Io),
            // data_corrupted, index_corrupted
            "XX001" | "XX002" => Some(FaultKind::Corrupt),
            _ => None,
        }
    }

    /// Whether connections opened before this fault may stay broken after it clears: SQLite opens a
    /// file it cannot write read-only and keeps it so, and a connection that saw an I/O error may
    /// hold stale state.
    fn may_spoil_connections(self) -> bool {
        matches!(
            self,
            FaultKind::ReadOnly | FaultKind::Io | FaultKind::CantOpen | FaultKind::Corrupt
        )
    }

    /// The value of the `kind` label of the store-fault metric.
    pub fn label(self) -> &'static str {
        match self {
            FaultKind::Full => "full",
            FaultKind::ReadOnly => "read_only",
            FaultKind::Io => "io",
            FaultKind::Busy => "busy",
            FaultKind::CantOpen => "cant_open",
            FaultKind::Corrupt => "corrupt",
            FaultKind::Lost => "lost",
            FaultKind::Closed => "closed",
            FaultKind::Unreachable => "unreachable",
        }
    }

    /// What an operator reads in logs and clients read in the status message.
    pub fn describe(self) -> &'static str {
        match self {
            FaultKind::Full => "the database is full (disk or --database-max-mib limit)",
            FaultKind::ReadOnly => "the database is read-only",
            FaultKind::Io => "the database file system is failing (I/O error)",
            FaultKind::Busy => {
                "the database is busy (locked by another writer, or no connection free in time)"
            }
            FaultKind::CantOpen => "the database file cannot be opened",
            FaultKind::Corrupt => "the database file is corrupt",
            FaultKind::Lost => {
                "the database file was deleted or replaced while the server ran; restore it and restart"
            }
            FaultKind::Closed => "the database is closed (the server is shutting down)",
            FaultKind::Unreachable => "the database server cannot be reached",
        }
    }
}

/// A database fault: its kind, and the driver's text for the log (never shown to clients).
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
#[error("{}", kind.describe())]
pub struct StoreFault {
    pub kind: FaultKind,
    pub cause: String,
}

impl StoreFault {
    /// A fault just classified; every one is counted in the metrics, so this is the only way
    /// faults are made.
    pub(crate) fn seen(kind: FaultKind, cause: String) -> Self {
        crate::telemetry::store_fault(kind.label());
        StoreFault { kind, cause }
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

/// Whether `error` lies in a row's values (a column missing, or a value of another type than the
/// field it decodes into) rather than in the database or the connection: retrying cannot help,
/// but the other rows are unaffected.
pub(crate) fn is_row_error(error: &sqlx::Error) -> bool {
    matches!(
        error,
        sqlx::Error::ColumnDecode { .. }
            | sqlx::Error::Decode(_)
            | sqlx::Error::ColumnNotFound(_)
            | sqlx::Error::ColumnIndexOutOfBounds { .. }
    )
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

/// Milliseconds after [`clock_start`] of the last fault that may spoil connections (0 = none yet).
/// Process-wide because faults are seen where sqlx errors are converted, which knows no store;
/// several stores in one process (tests) only cost each other a few reconnects.
static LAST_CONNECTION_FAULT_MS: AtomicU64 = AtomicU64::new(0);

fn clock_start() -> Instant {
    static START: OnceLock<Instant> = OnceLock::new();
    *START.get_or_init(Instant::now)
}

fn note_connection_fault() {
    let since_start = clock_start().elapsed().as_millis() as u64 + 1;
    LAST_CONNECTION_FAULT_MS.fetch_max(since_start, Ordering::Relaxed);
}

/// Whether a pooled connection of this `age` was opened after the last fault that may spoil
/// connections; older ones are closed before use so that the pool opens fresh ones.
pub(crate) fn outlived_no_fault(age: Duration) -> bool {
    let fault_ms = LAST_CONNECTION_FAULT_MS.load(Ordering::Relaxed);
    if fault_ms == 0 {
        return true;
    }
    let fault_at = clock_start() + Duration::from_millis(fault_ms - 1);
    Instant::now()
        .checked_sub(age)
        .is_some_and(|opened| opened > fault_at)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn connections_opened_before_a_spoiling_fault_are_retired() {
        let hour = Duration::from_secs(3600);
        note_connection_fault();
        assert!(!outlived_no_fault(hour), "opened before the fault");
        std::thread::sleep(Duration::from_millis(5));
        assert!(outlived_no_fault(Duration::ZERO), "opened after it");
        assert!(FaultKind::ReadOnly.may_spoil_connections());
        assert!(!FaultKind::Full.may_spoil_connections());
    }

    #[test]
    fn postgres_states_and_lost_connections_are_classified() {
        assert_eq!(FaultKind::of_sqlstate("53100"), Some(FaultKind::Full));
        assert_eq!(
            FaultKind::of_sqlstate("57P01"),
            Some(FaultKind::Unreachable)
        );
        assert_eq!(
            FaultKind::of_sqlstate("08006"),
            Some(FaultKind::Unreachable)
        );
        assert_eq!(FaultKind::of_sqlstate("57014"), Some(FaultKind::Busy));
        assert_eq!(
            FaultKind::of_sqlstate("23505"),
            None,
            "unique violation: the query's"
        );
        let refused = std::io::Error::from(std::io::ErrorKind::ConnectionRefused);
        assert_eq!(
            FaultKind::of(&sqlx::Error::Io(refused)),
            Some(FaultKind::Unreachable)
        );
        let disk = std::io::Error::other("disk I/O");
        assert_eq!(FaultKind::of(&sqlx::Error::Io(disk)), Some(FaultKind::Io));
    }
}
