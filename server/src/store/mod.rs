//! Persistence for the service through sqlx (runtime queries, `FromRow` rows), on one of two
//! backends chosen by the database URL: SQLite (`sqlite://…`, `sqlite:…` or a bare path; the
//! embedded default, one server) or PostgreSQL (`postgres://…`, `postgresql://…`; replicas sharing
//! one database).
//!
//! One [`Store`] wraps a connection pool. Tables: models (+ artifact blobs in their own table so list
//! queries never read blobs), datasets (+ content blobs), jobs (+ per-epoch history), alarm events
//! (+ the event log behind WatchAlarms), session snapshots (the hand-off of detection state) and
//! shadows (a candidate model's configuration, counts and would-be alarms, apart from the real ones).
//! The schema lives in `migrations/sqlite/` and `migrations/postgres/` at the workspace root (the same
//! versions, each in its dialect) and is applied by [`Store::open`].
//!
//! Every query is written once: [`on_pool!`] and [`in_write_tx!`] compile a query body once per
//! backend, so the two cannot drift apart. The SQL therefore sticks to what both understand: `$N`
//! placeholders (sqlx's SQLite driver binds `$N` by number), `ON CONFLICT … DO NOTHING`, `RETURNING`,
//! `TRUE`/`FALSE`, row-value comparisons. Enums are stored as TEXT ([`text_enum!`]); JSON columns are
//! TEXT on SQLite and JSONB on PostgreSQL (sqlx's `Json` reads and writes both). What stays
//! backend-specific is connection setup and robustness: `sqlite` (file identity, page limit,
//! connection hygiene) and `postgres` (pool limits, timeouts).
//!
//! Conventions:
//! - Ids are TEXT chosen by the caller (alarm events excepted: they get an integer id).
//! - Every wall-clock time is unix epoch milliseconds (UTC) in an integer column named `*_at`; Rust
//!   fields carry an `_ms` suffix. [`now_unix_ms`] is the clock the store uses.
//! - JSON columns (`*_json`) hold opaque `serde_json::Value`s the caller fills.
//! - Every multi-statement write runs in a write transaction that takes the database's write lock up
//!   front: `BEGIN IMMEDIATE` on SQLite (a deferred transaction that reads first and writes later
//!   fails at once with SQLITE_BUSY under a concurrent writer, whereas an immediate one waits through
//!   `busy_timeout`), a transaction-scoped advisory lock on PostgreSQL (so a read-then-write sees no
//!   concurrent change, exactly as on SQLite, without row-lock bookkeeping in every query).

/// Evaluates `$body` with `$pool` bound to the store's pool (`&SqlitePool` or `&PgPool`): the body
/// is written once and compiled once per backend. `?` in the body converts into [`StoreError`] and
/// returns from the enclosing function. Fails first when the store is unusable (see `Store::backend`).
macro_rules! on_pool {
    ($store:expr, |$pool:ident| $body:expr) => {
        match $store.backend()? {
            $crate::store::Backend::Sqlite(sqlite) => {
                let $pool = &sqlite.pool;
                $body
            }
            $crate::store::Backend::Postgres($pool) => $body,
        }
    };
}

/// Evaluates `$body` with `$tx` a write transaction (see the module docs) on the store's backend,
/// compiled once per backend like [`on_pool!`]. The body commits; returning early rolls back.
macro_rules! in_write_tx {
    ($store:expr, |$tx:ident| $body:expr) => {
        match $store.backend()? {
            $crate::store::Backend::Sqlite(sqlite) => {
                #[allow(unused_mut)]
                let mut $tx = sqlite.pool.begin_with("BEGIN IMMEDIATE").await?;
                $body
            }
            $crate::store::Backend::Postgres(postgres) => {
                #[allow(unused_mut)]
                let mut $tx = postgres.begin().await?;
                $crate::store::postgres::take_write_lock(&mut $tx).await?;
                $body
            }
        }
    };
}

/// Implements sqlx's `Type`, `Encode` and `Decode` for a fieldless enum stored as its lowercase
/// name in a TEXT column, for every backend (a derived `sqlx::Type` enum would be a custom type on
/// PostgreSQL). Needs `as_str` and `from_str_opt` on the enum.
macro_rules! text_enum {
    ($name:ident) => {
        impl<DB: sqlx::Database> sqlx::Type<DB> for $name
        where
            str: sqlx::Type<DB>,
        {
            fn type_info() -> DB::TypeInfo {
                <str as sqlx::Type<DB>>::type_info()
            }

            fn compatible(ty: &DB::TypeInfo) -> bool {
                <str as sqlx::Type<DB>>::compatible(ty)
            }
        }

        impl<'q, DB: sqlx::Database> sqlx::Encode<'q, DB> for $name
        where
            &'q str: sqlx::Encode<'q, DB>,
        {
            fn encode_by_ref(
                &self,
                buf: &mut <DB as sqlx::Database>::ArgumentBuffer,
            ) -> Result<sqlx::encode::IsNull, sqlx::error::BoxDynError> {
                <&'q str as sqlx::Encode<'q, DB>>::encode(self.as_str(), buf)
            }
        }

        impl<'r, DB: sqlx::Database> sqlx::Decode<'r, DB> for $name
        where
            &'r str: sqlx::Decode<'r, DB>,
        {
            fn decode(
                value: <DB as sqlx::Database>::ValueRef<'r>,
            ) -> Result<Self, sqlx::error::BoxDynError> {
                let text = <&'r str as sqlx::Decode<'r, DB>>::decode(value)?;
                $name::from_str_opt(text)
                    .ok_or_else(|| format!("unknown {} '{text}'", stringify!($name)).into())
            }
        }
    };
}

mod alarms;
mod datasets;
mod error;
mod incidents;
mod jobs;
mod models;
mod outbox;
mod paging;
mod postgres;
mod shadows;
mod snapshots;
mod sqlite;
pub mod test_database;

#[cfg(test)]
mod tests;

use std::time::{SystemTime, UNIX_EPOCH};

use sqlx::PgPool;

pub use alarms::{
    AlarmEvent, AlarmEventKind, AlarmEventRow, AlarmFilter, AlarmState, LoggedAlarmEvent,
    StoredCredential, StoredPlace, StoredSeverity, StoredWhy, first_seq_of_run,
};
pub use datasets::{DatasetRow, NewDataset};
pub use error::{FaultKind, MigrationError, StoreError, StoreFault};
pub use incidents::{
    CloseOutcome, Closure, ClosureKind, CorrelationStep, CorrelatorPlace, IncidentEventKind,
    IncidentRow, IncidentState, IncidentWrite, LoggedIncidentEvent, StoredClosure,
};
pub use jobs::{EpochRow, JobEndError, JobFilter, JobKind, JobOutcome, JobRow, JobState, NewJob};
pub use models::{ModelRow, ModelSource, NewModel};
pub use paging::{DEFAULT_PAGE_SIZE, MAX_PAGE_SIZE, Page, PageRequest};
pub use postgres::{POOL_ACQUIRE_TIMEOUT, POOL_MAX_CONNECTIONS, STATEMENT_TIMEOUT};
pub use shadows::{ShadowAlarmEnd, ShadowAlarmRow, ShadowRow, ShadowStart};
pub use snapshots::{ExpiredSnapshots, SnapshotRow};

/// The service's database: a cheap-to-clone handle over a connection pool.
#[derive(Debug, Clone)]
pub struct Store {
    backend: Backend,
}

/// The database behind a [`Store`].
#[derive(Debug, Clone)]
enum Backend {
    Sqlite(sqlite::SqliteBackend),
    Postgres(PgPool),
}

/// Options of [`Store::open_with`].
#[derive(Clone, Copy, Debug, Default)]
pub struct StoreOptions {
    /// Refuse to grow the database beyond this many bytes (writes then fail as [`FaultKind::Full`]);
    /// `None` = only the disk limits it. SQLite only: PostgreSQL's size is the operator's business.
    pub max_bytes: Option<u64>,
}

/// Which backend a database URL names.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum BackendKind {
    /// `sqlite://…`, `sqlite:…` or a bare filesystem path.
    Sqlite,
    /// `postgres://…` or `postgresql://…`.
    Postgres,
}

impl BackendKind {
    /// The backend `url_or_path` names: PostgreSQL for its URL schemes, SQLite for anything else.
    pub fn of(url_or_path: &str) -> BackendKind {
        if url_or_path.starts_with("postgres://") || url_or_path.starts_with("postgresql://") {
            BackendKind::Postgres
        } else {
            BackendKind::Sqlite
        }
    }
}

impl Store {
    /// Opens (creating if missing) and migrates the database at `url_or_path` without a size limit.
    pub async fn open(url_or_path: &str) -> Result<Store, StoreError> {
        Self::open_with(url_or_path, StoreOptions::default()).await
    }

    /// Opens and migrates the database `url_or_path` names (see [`BackendKind::of`]).
    ///
    /// SQLite: accepts `sqlite://path`, `sqlite:path`, `sqlite::memory:` (tests only: the database
    /// lives as long as the store) or a bare filesystem path, created if missing. Connections use
    /// WAL, `synchronous=NORMAL`, `foreign_keys=ON`, a 5 s busy timeout and `max_page_count` from
    /// `options.max_bytes`.
    ///
    /// PostgreSQL: the database must exist; a pool of at most [`POOL_MAX_CONNECTIONS`] connections,
    /// waiting at most [`POOL_ACQUIRE_TIMEOUT`] for one, each statement cut off after
    /// [`STATEMENT_TIMEOUT`]. `options.max_bytes` is refused ([`StoreError::InvalidValue`]).
    pub async fn open_with(url_or_path: &str, options: StoreOptions) -> Result<Store, StoreError> {
        let backend = match BackendKind::of(url_or_path) {
            BackendKind::Sqlite => Backend::Sqlite(sqlite::open(url_or_path, options).await?),
            BackendKind::Postgres => {
                if options.max_bytes.is_some() {
                    return Err(StoreError::InvalidValue {
                        field: "database_max_mib",
                        reason: "applies to SQLite databases only".to_string(),
                    });
                }
                Backend::Postgres(postgres::open(url_or_path).await?)
            }
        };
        Ok(Store { backend })
    }

    /// Which backend this store uses.
    pub fn kind(&self) -> BackendKind {
        match &self.backend {
            Backend::Sqlite(_) => BackendKind::Sqlite,
            Backend::Postgres(_) => BackendKind::Postgres,
        }
    }

    /// The backend, unless the SQLite database file was found deleted or replaced: then every call
    /// fails with [`FaultKind::Lost`] rather than write into a file nobody will read again.
    fn backend(&self) -> Result<&Backend, StoreError> {
        if let Backend::Sqlite(sqlite) = &self.backend {
            sqlite.usable()?;
        }
        Ok(&self.backend)
    }

    /// Checks that the database file is still the one opened (same device and inode); once it is
    /// not, the store stays unavailable until a restart. Always `Ok` for in-memory SQLite databases
    /// and for PostgreSQL (a server, not a file).
    pub fn check_file(&self) -> Result<(), StoreFault> {
        match &self.backend {
            Backend::Sqlite(sqlite) => sqlite.check_file(),
            Backend::Postgres(_) => Ok(()),
        }
    }

    /// Closes every connection, waiting for in-flight queries; later calls fail with `PoolClosed`.
    pub async fn close(&self) {
        match &self.backend {
            Backend::Sqlite(sqlite) => sqlite.close().await,
            Backend::Postgres(pool) => pool.close().await,
        }
    }

    /// The SQLite pool (tests of SQLite-only behaviour).
    #[cfg(test)]
    pub(crate) fn sqlite_pool(&self) -> &sqlx::SqlitePool {
        match &self.backend {
            Backend::Sqlite(sqlite) => &sqlite.pool,
            Backend::Postgres(_) => panic!("not a SQLite store"),
        }
    }

    /// Runs one raw statement: fault injection in tests of the store's callers.
    #[cfg(test)]
    pub(crate) async fn execute_for_test(&self, sql: &'static str) {
        self.try_execute_for_test(sql)
            .await
            .unwrap_or_else(|error| panic!("{sql}: {error}"));
    }

    /// Runs one raw statement and returns the driver's error (tests of what the schema refuses).
    #[cfg(test)]
    pub(crate) async fn try_execute_for_test(&self, sql: &'static str) -> Result<(), sqlx::Error> {
        match &self.backend {
            Backend::Sqlite(sqlite) => sqlx::query(sql).execute(&sqlite.pool).await.map(drop),
            Backend::Postgres(pool) => sqlx::query(sql).execute(pool).await.map(drop),
        }
    }

    /// The texts `sql` selects, one per row (tests).
    #[cfg(test)]
    pub(crate) async fn strings_for_test(&self, sql: &'static str) -> Vec<String> {
        let rows = match &self.backend {
            Backend::Sqlite(sqlite) => sqlx::query_scalar(sql).fetch_all(&sqlite.pool).await,
            Backend::Postgres(pool) => sqlx::query_scalar(sql).fetch_all(pool).await,
        };
        rows.unwrap_or_else(|error| panic!("{sql}: {error}"))
    }

    /// The one integer `sql` selects (tests).
    #[cfg(test)]
    pub(crate) async fn scalar_for_test(&self, sql: &'static str) -> i64 {
        let value: Result<i64, StoreError> = async {
            Ok(on_pool!(self, |pool| sqlx::query_scalar(sql)
                .fetch_one(pool)
                .await?))
        }
        .await;
        value.unwrap_or_else(|error| panic!("{sql}: {error}"))
    }
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
