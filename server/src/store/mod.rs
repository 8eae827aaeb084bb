//! Persistence for the service: SQLite through sqlx (runtime queries, `FromRow` rows).
//!
//! One [`Store`] wraps a connection pool. Tables: models (+ artifact blobs in their own table so list
//! queries never read blobs), datasets (+ content blobs), jobs (+ per-epoch history) and alarm events.
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

#[cfg(test)]
mod tests;

use std::str::FromStr;
use std::time::{Duration, SystemTime, UNIX_EPOCH};

use sqlx::sqlite::SqliteRow;
use sqlx::sqlite::{
    SqliteConnectOptions, SqliteJournalMode, SqlitePool, SqlitePoolOptions, SqliteSynchronous,
};
use sqlx::{FromRow, Sqlite, Transaction};

pub use alarms::{AlarmEventRow, AlarmWrite};
pub use datasets::{DatasetRow, NewDataset};
pub use error::StoreError;
pub use jobs::{EpochRow, JobFilter, JobKind, JobOutcome, JobRow, JobState, NewJob};
pub use models::{ModelRow, ModelSource, NewModel};
pub use paging::{DEFAULT_PAGE_SIZE, MAX_PAGE_SIZE, Page, PageRequest};

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
}

impl Store {
    /// Opens (creating if missing) and migrates the database at `url_or_path`.
    ///
    /// Accepts `sqlite://path`, `sqlite:path`, `sqlite::memory:` (tests only: the database lives as long
    /// as the store) or a bare filesystem path. Connections use WAL, `synchronous=NORMAL`,
    /// `foreign_keys=ON` and a 5 s busy timeout.
    pub async fn open(url_or_path: &str) -> Result<Store, StoreError> {
        let options = connect_options(url_or_path)?;
        let in_memory = is_in_memory(url_or_path);
        let pool_options = if in_memory {
            // An in-memory database vanishes with its last connection: keep exactly one, forever.
            SqlitePoolOptions::new()
                .max_connections(1)
                .min_connections(1)
                .idle_timeout(None)
                .max_lifetime(None)
        } else {
            SqlitePoolOptions::new()
        };
        let pool = pool_options.connect_with(options).await?;
        sqlx::migrate!("../migrations").run(&pool).await?;
        Ok(Store { pool })
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
            .fetch_optional(&self.pool)
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
            .fetch_optional(&self.pool)
            .await?)
    }

    /// Starts a write transaction that takes SQLite's write lock up front (see the module docs).
    /// Runs one raw statement: fault injection in tests of the store's callers.
    #[cfg(test)]
    pub(crate) async fn execute_for_test(&self, sql: &'static str) {
        sqlx::query(sql)
            .execute(&self.pool)
            .await
            .unwrap_or_else(|error| panic!("{sql}: {error}"));
    }

    async fn begin_write(&self) -> Result<Transaction<'static, Sqlite>, StoreError> {
        Ok(self.pool.begin_with("BEGIN IMMEDIATE").await?)
    }
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
