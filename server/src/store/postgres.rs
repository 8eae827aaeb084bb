//! The PostgreSQL backend's setup: pool limits and timeouts, migrations, and the write lock that
//! gives write transactions SQLite's `BEGIN IMMEDIATE` semantics. Queries live with their tables,
//! written once for both backends.
//!
//! A server that goes away is survived without a restart: pooled connections are pinged before use
//! (sqlx's default) and replaced, so calls fail as [`super::FaultKind::Unreachable`] or
//! [`super::FaultKind::Busy`] (no connection in time) while it is down and succeed again once it is
//! back.

use std::str::FromStr;
use std::time::Duration;

use sqlx::postgres::{PgConnectOptions, PgPoolOptions};
use sqlx::{PgPool, Postgres, Transaction};

use super::StoreError;
use super::error::migration_error;

/// Connections one server keeps to PostgreSQL at most: enough for the alarm writer, jobs and
/// concurrent API calls; two replicas stay well under PostgreSQL's default of 100.
pub const POOL_MAX_CONNECTIONS: u32 = 16;

/// How long a call waits for a pooled connection (also while the server is unreachable) before
/// failing as busy/unavailable.
pub const POOL_ACQUIRE_TIMEOUT: Duration = Duration::from_secs(5);

/// Statements running longer than this are cancelled by the server (a lock or an overload that would
/// otherwise hold a connection forever). Generous: dataset uploads write blobs of many MiB.
pub const STATEMENT_TIMEOUT: Duration = Duration::from_secs(60);

/// The key of the advisory lock every write transaction takes (any constant unique to Spoofwatch
/// within the database: "SPOOFWAT" in ASCII).
const WRITE_LOCK_KEY: i64 = 0x53_50_4f_4f_46_57_41_54;

/// Connects a pool to the database at `url` and applies the migrations.
pub(super) async fn open(url: &str) -> Result<PgPool, StoreError> {
    let statement_timeout = format!("{}ms", STATEMENT_TIMEOUT.as_millis());
    let connect = PgConnectOptions::from_str(url)?
        .application_name("spoofwatch")
        .options([("statement_timeout", statement_timeout.as_str())]);
    let pool = PgPoolOptions::new()
        .max_connections(POOL_MAX_CONNECTIONS)
        .acquire_timeout(POOL_ACQUIRE_TIMEOUT)
        .connect_with(connect)
        .await?;
    warn_if_new(&pool).await?;
    // sqlx serialises concurrent migrators (replicas starting together) with an advisory lock.
    let migrator = sqlx::migrate!("../migrations/postgres");
    migrator
        .run(&pool)
        .await
        .map_err(|error| migration_error(&migrator, error))?;
    Ok(pool)
}

/// Takes the write lock inside `tx`; PostgreSQL releases it at commit or rollback. Writers queue for
/// it (bounded by the statement timeout) the way SQLite writers queue for `BEGIN IMMEDIATE`.
pub(super) async fn take_write_lock(
    tx: &mut Transaction<'static, Postgres>,
) -> Result<(), StoreError> {
    sqlx::query("SELECT pg_advisory_xact_lock($1)")
        .bind(WRITE_LOCK_KEY)
        .execute(&mut **tx)
        .await?;
    Ok(())
}

/// Logs a warning when the database holds no Spoofwatch tables yet: right on a first start, a
/// sign of a lost database on any later one.
async fn warn_if_new(pool: &PgPool) -> Result<(), StoreError> {
    let migrated: bool = sqlx::query_scalar("SELECT to_regclass('_sqlx_migrations') IS NOT NULL")
        .fetch_one(pool)
        .await?;
    if !migrated {
        tracing::warn!(
            "initialising a new, empty PostgreSQL database (no Spoofwatch tables found): expected \
             on a first start only"
        );
    }
    Ok(())
}
