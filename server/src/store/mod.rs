//! Persistence for the service: SQLite through sqlx (runtime queries, `FromRow` rows).
//!
//! One [`Store`] wraps a connection pool. Tables: models (+ artifact blobs in their own table so list
//! queries never read blobs), datasets (+ content blobs), jobs (+ per-epoch history), alarm events
//! (+ the event log behind WatchAlarms) and session snapshots (the hand-off of detection state).
//! The schema lives in `migrations/` at the workspace root and is applied by [`Store::open`].
//!
//! Conventions:
//! - Ids are TEXT chosen by the caller (alarm events excepted: they get an integer id).
//! - Every wall-clock time is unix epoch milliseconds (UTC) in an INTEGER column named `*_at`; Rust
//!   fields carry an `_ms` suffix. [`now_unix_ms`] is the clock the store uses.
//! - JSON columns (`*_json`) hold opaque `serde_json::Value`s the caller fills.
//! - Every multi-statement write runs in a transaction begun with `BEGIN IMMEDIATE`: a deferred
//!   transaction that reads first and writes later fails at once with SQLITE_BUSY under a concurrent
//!   writer, whereas an immediate one waits for the lock through `busy_timeout`.

mod alarms;
mod datasets;
mod error;
mod jobs;
mod models;
mod paging;
mod snapshots;

#[cfg(test)]
mod tests;

use std::path::{Path, PathBuf};
use std::str::FromStr;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, SystemTime, UNIX_EPOCH};

use sqlx::sqlite::SqliteRow;
use sqlx::sqlite::{
    SqliteConnectOptions, SqliteJournalMode, SqlitePool, SqlitePoolOptions, SqliteSynchronous,
};
use sqlx::{Connection, FromRow, Sqlite, SqliteConnection, Transaction};

pub use alarms::{
    AlarmEvent, AlarmEventKind, AlarmEventRow, AlarmFilter, AlarmState, first_seq_of_run,
};
pub use datasets::{DatasetRow, NewDataset};
use error::outlived_no_fault;
pub use error::{FaultKind, StoreError, StoreFault};
pub use jobs::{EpochRow, JobFilter, JobKind, JobOutcome, JobRow, JobState, NewJob};
pub use models::{ModelRow, ModelSource, NewModel};
pub use paging::{DEFAULT_PAGE_SIZE, MAX_PAGE_SIZE, Page, PageRequest};
pub use snapshots::SnapshotRow;

/// How long a connection waits for another writer's lock before failing with SQLITE_BUSY.
const BUSY_TIMEOUT: Duration = Duration::from_secs(5);

/// gRPC status code ABORTED, recorded for jobs interrupted by a server restart.
pub const ABORTED_CODE: i32 = 10;

/// gRPC status code CANCELLED, recorded for jobs finished as [`JobOutcome::Cancelled`].
pub const CANCELLED_CODE: i32 = 1;

/// The service's SQLite database: a cheap-to-clone handle over a connection pool.
#[derive(Debug, Clone)]
pub struct Store {
    pool: SqlitePool,
    /// The file opened, for databases on disk: checked so that a deleted or replaced file is
    /// noticed instead of writing into an unlinked inode.
    file: Option<Arc<DatabaseFile>>,
}

/// Options of [`Store::open_with`].
#[derive(Clone, Copy, Debug, Default)]
pub struct StoreOptions {
    /// Refuse to grow the database beyond this many bytes (writes then fail as [`FaultKind::Full`]);
    /// `None` = only the disk limits it.
    pub max_bytes: Option<u64>,
}

impl Store {
    /// Opens (creating if missing) and migrates the database at `url_or_path` without a size limit.
    pub async fn open(url_or_path: &str) -> Result<Store, StoreError> {
        Self::open_with(url_or_path, StoreOptions::default()).await
    }

    /// Opens (creating if missing) and migrates the database at `url_or_path`.
    ///
    /// Accepts `sqlite://path`, `sqlite:path`, `sqlite::memory:` (tests only: the database lives as long
    /// as the store) or a bare filesystem path. Connections use WAL, `synchronous=NORMAL`,
    /// `foreign_keys=ON`, a 5 s busy timeout and `max_page_count` from `options.max_bytes`.
    pub async fn open_with(url_or_path: &str, options: StoreOptions) -> Result<Store, StoreError> {
        let mut connect = connect_options(url_or_path)?;
        if let Some(max_bytes) = options.max_bytes {
            connect = connect.pragma("max_page_count", (max_bytes / PAGE_SIZE).max(1).to_string());
        }
        let in_memory = is_in_memory(url_or_path);
        let path = (!in_memory).then(|| connect.get_filename().to_path_buf());
        if path.is_some() {
            // Create the file now, once; the pool's connections never create one, so a file
            // deleted while the server runs is not silently replaced by an empty one.
            SqliteConnection::connect_with(&connect)
                .await?
                .close()
                .await?;
            connect = connect.create_if_missing(false);
        }
        let pool_options = if let Some(path) = path.clone() {
            // Connections a fault may have spoiled are replaced.
            let path = Arc::new(path);
            SqlitePoolOptions::new()
                .before_acquire(|_, metadata| {
                    Box::pin(async move { Ok(outlived_no_fault(metadata.age)) })
                })
                .after_release(move |connection, _| {
                    let path = Arc::clone(&path);
                    Box::pin(async move { still_usable(connection, &path).await })
                })
        } else {
            // An in-memory database vanishes with its last connection: keep exactly one, forever.
            SqlitePoolOptions::new()
                .max_connections(1)
                .min_connections(1)
                .idle_timeout(None)
                .max_lifetime(None)
        };
        let pool = pool_options.connect_with(connect).await?;
        warn_if_new(&pool, path.as_deref()).await?;
        sqlx::migrate!("../migrations").run(&pool).await?;
        let file = match path {
            Some(path) => Some(Arc::new(DatabaseFile::opened(path)?)),
            None => None,
        };
        Ok(Store { pool, file })
    }

    /// The pool, unless the database file was found deleted or replaced: then every call fails
    /// with [`FaultKind::Lost`] rather than write into a file nobody will read again.
    fn pool(&self) -> Result<&SqlitePool, StoreError> {
        match &self.file {
            Some(file) if file.is_lost() => Err(StoreError::Unavailable(StoreFault::seen(
                FaultKind::Lost,
                format!("{} is not the file opened", file.path.display()),
            ))),
            _ => Ok(&self.pool),
        }
    }

    /// Checks that the database file is still the one opened (same device and inode); once it is
    /// not, the store stays unavailable until a restart. Always `Ok` for in-memory databases.
    pub fn check_file(&self) -> Result<(), StoreFault> {
        match &self.file {
            Some(file) => file.check(),
            None => Ok(()),
        }
    }

    /// Closes every connection, waiting for in-flight queries; later calls fail with `PoolClosed`.
    pub async fn close(&self) {
        self.pool.close().await;
    }

    /// The row `select` returns for `id` (its one parameter), or `None`.
    async fn fetch_by_id<R>(&self, select: &'static str, id: &str) -> Result<Option<R>, StoreError>
    where
        R: for<'r> FromRow<'r, SqliteRow> + Send + Unpin,
    {
        Ok(sqlx::query_as(select)
            .bind(id)
            .fetch_optional(self.pool()?)
            .await?)
    }

    /// The blob `select` returns for `id` (its one parameter), or `None`.
    async fn fetch_blob(
        &self,
        select: &'static str,
        id: &str,
    ) -> Result<Option<Vec<u8>>, StoreError> {
        Ok(sqlx::query_scalar(select)
            .bind(id)
            .fetch_optional(self.pool()?)
            .await?)
    }

    /// Runs one raw statement: fault injection in tests of the store's callers.
    #[cfg(test)]
    pub(crate) async fn execute_for_test(&self, sql: &'static str) {
        sqlx::query(sql)
            .execute(&self.pool)
            .await
            .unwrap_or_else(|error| panic!("{sql}: {error}"));
    }

    /// Starts a write transaction that takes SQLite's write lock up front (see the module docs).
    async fn begin_write(&self) -> Result<Transaction<'static, Sqlite>, StoreError> {
        Ok(self.pool()?.begin_with("BEGIN IMMEDIATE").await?)
    }
}

/// Logs a warning when the database holds no Spoofwatch tables yet: right on a first start, a
/// sign of a lost database on any later one.
async fn warn_if_new(pool: &SqlitePool, path: Option<&Path>) -> Result<(), StoreError> {
    let migrated: i64 = sqlx::query_scalar(
        "SELECT count(*) FROM sqlite_master WHERE type = 'table' AND name = '_sqlx_migrations'",
    )
    .fetch_one(pool)
    .await?;
    if migrated == 0
        && let Some(path) = path
    {
        tracing::warn!(
            path = %path.display(),
            "initialising a new, empty database (no Spoofwatch tables found): expected on a first \
             start only"
        );
    }
    Ok(())
}

/// Whether a connection handed back to the pool can serve again. After SQLITE_FULL or an I/O error
/// SQLite may roll a transaction back by itself; sqlx then still counts it as open, its own ROLLBACK
/// fails, and every later `BEGIN IMMEDIATE` on that connection would fail until a restart. Such a
/// connection is closed instead (the pool opens a fresh one when needed). So is any connection
/// released while the file cannot be opened for writing: SQLite opens such a file read-only and
/// the connection would stay read-only after the file is writable again.
async fn still_usable(connection: &mut SqliteConnection, path: &Path) -> Result<bool, sqlx::Error> {
    if std::fs::OpenOptions::new().write(true).open(path).is_err() {
        tracing::debug!("closing a database connection: the file is not writable");
        return Ok(false);
    }
    if connection.is_in_transaction() {
        // A dropped transaction's ROLLBACK may still be queued on the connection's worker: wait for
        // it with a round trip before judging.
        connection.ping().await?;
    }
    let usable = !connection.is_in_transaction();
    if !usable {
        tracing::warn!("closing a database connection left inside a failed transaction");
    }
    Ok(usable)
}

/// SQLite's default page size, which this store never changes.
const PAGE_SIZE: u64 = 4096;

/// The database file as opened: its identity (device, inode) and whether it was found changed.
#[derive(Debug)]
struct DatabaseFile {
    path: PathBuf,
    identity: (u64, u64),
    lost: AtomicBool,
}

impl DatabaseFile {
    fn opened(path: PathBuf) -> Result<Self, StoreError> {
        let identity = file_identity(&path).map_err(|error| {
            StoreError::Unavailable(StoreFault::seen(
                FaultKind::CantOpen,
                format!("{}: {error}", path.display()),
            ))
        })?;
        Ok(DatabaseFile {
            path,
            identity,
            lost: AtomicBool::new(false),
        })
    }

    fn is_lost(&self) -> bool {
        self.lost.load(Ordering::Relaxed)
    }

    fn check(&self) -> Result<(), StoreFault> {
        let lost = |cause: String| StoreFault::seen(FaultKind::Lost, cause);
        if self.is_lost() {
            return Err(lost(format!(
                "{} is not the file opened",
                self.path.display()
            )));
        }
        let cause = match file_identity(&self.path) {
            Ok(identity) if identity == self.identity => return Ok(()),
            Ok(_) => format!("{} was replaced by another file", self.path.display()),
            Err(error) => format!("{}: {error}", self.path.display()),
        };
        self.lost.store(true, Ordering::Relaxed);
        Err(lost(cause))
    }
}

/// (device, inode) of the file at `path`.
fn file_identity(path: &Path) -> std::io::Result<(u64, u64)> {
    use std::os::unix::fs::MetadataExt;
    let metadata = std::fs::metadata(path)?;
    Ok((metadata.dev(), metadata.ino()))
}

/// Builds the connection options for a `sqlite:` URL or a bare path.
fn connect_options(url_or_path: &str) -> Result<SqliteConnectOptions, StoreError> {
    let base = if url_or_path.starts_with("sqlite:") {
        SqliteConnectOptions::from_str(url_or_path)?
    } else {
        SqliteConnectOptions::new().filename(url_or_path)
    };
    Ok(base
        .create_if_missing(true)
        .journal_mode(SqliteJournalMode::Wal)
        .synchronous(SqliteSynchronous::Normal)
        .foreign_keys(true)
        .busy_timeout(BUSY_TIMEOUT))
}

/// Whether `url` names an in-memory database (`sqlite::memory:` or `?mode=memory`).
fn is_in_memory(url: &str) -> bool {
    url.starts_with("sqlite:") && (url.contains(":memory:") || url.contains("mode=memory"))
}

/// The current wall-clock time as unix epoch milliseconds (UTC), the unit of every `*_at` column.
pub fn now_unix_ms() -> i64 {
    // A clock before 1970 is a broken host; 0 keeps the store usable rather than panicking.
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |elapsed| {
            i64::try_from(elapsed.as_millis()).unwrap_or(i64::MAX)
        })
}
