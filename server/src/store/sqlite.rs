//! The SQLite backend's setup and robustness: connection options, the file-identity check, the
//! size limit, the connection hygiene hooks and the connection that holds the file for the life of
//! the store. Queries live with their tables, written once for both backends.
//!
//! No code here opens the database file outside SQLite's own connections: a POSIX `close` of any
//! descriptor on the file releases every lock this process holds on it, and another process that
//! then opens and closes the file (a `sqlite3` shell, a backup) would take it for the last user and
//! delete the write-ahead log under the running server. Files are checked with `stat` and
//! `access` only.

use std::path::{Path, PathBuf};
use std::str::FromStr;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;

use sqlx::sqlite::{
    SqliteConnectOptions, SqliteJournalMode, SqlitePool, SqlitePoolOptions, SqliteSynchronous,
};
use sqlx::{Connection, SqliteConnection};
use tokio::sync::Mutex;

use super::error::{migration_error, outlived_no_fault};
use super::{FaultKind, StoreError, StoreFault, StoreOptions};

/// How long a connection waits for another writer's lock before failing with SQLITE_BUSY.
const BUSY_TIMEOUT: Duration = Duration::from_secs(5);

/// SQLite's default page size, which this store never changes.
const PAGE_SIZE: u64 = 4096;

/// A SQLite database: its pool and, for databases on disk, the file opened.
#[derive(Debug, Clone)]
pub(super) struct SqliteBackend {
    pub(super) pool: SqlitePool,
    /// The file opened, for databases on disk: checked so that a deleted or replaced file is
    /// noticed instead of writing into an unlinked inode.
    file: Option<Arc<DatabaseFile>>,
    /// For databases on disk, a connection that runs no query and stays open until the store
    /// closes: while the pool retires and replaces its connections, this process still holds
    /// its shared lock on the write-ahead log, so no other process ever checkpoints and deletes
    /// the log under it.
    holder: Option<Arc<Mutex<Option<SqliteConnection>>>>,
}

/// Opens (creating if missing) and migrates the SQLite database at `url_or_path`.
pub(super) async fn open(
    url_or_path: &str,
    options: StoreOptions,
) -> Result<SqliteBackend, StoreError> {
    let mut connect = connect_options(url_or_path)?;
    if let Some(max_bytes) = options.max_bytes {
        connect = connect.pragma("max_page_count", (max_bytes / PAGE_SIZE).max(1).to_string());
    }
    let in_memory = is_in_memory(url_or_path);
    let path = (!in_memory).then(|| connect.get_filename().to_path_buf());
    let mut holder = None;
    if path.is_some() {
        // The first connection creates the file, once (the pool's connections never create one,
        // so a file deleted while the server runs is not silently replaced by an empty one), and
        // then holds it until the store closes.
        holder = Some(SqliteConnection::connect_with(&connect).await?);
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
    let migrator = sqlx::migrate!("../migrations/sqlite");
    migrator
        .run(&pool)
        .await
        .map_err(|error| migration_error(&migrator, error))?;
    let file = match path {
        Some(path) => Some(Arc::new(DatabaseFile::opened(path)?)),
        None => None,
    };
    Ok(SqliteBackend {
        pool,
        file,
        holder: holder.map(|connection| Arc::new(Mutex::new(Some(connection)))),
    })
}

impl SqliteBackend {
    /// [`FaultKind::Lost`] once the file was found deleted or replaced.
    pub(super) fn usable(&self) -> Result<(), StoreError> {
        match &self.file {
            Some(file) if file.is_lost() => Err(StoreError::Unavailable(StoreFault::seen(
                FaultKind::Lost,
                format!("{} is not the file opened", file.path.display()),
            ))),
            _ => Ok(()),
        }
    }

    /// Closes the pool, then the connection holding the file: the last to close checkpoints the
    /// write-ahead log into the database and removes it.
    pub(super) async fn close(&self) {
        self.pool.close().await;
        if let Some(holder) = &self.holder
            && let Some(connection) = holder.lock().await.take()
            && let Err(error) = connection.close().await
        {
            tracing::warn!(%error, "closing the database file's holding connection failed");
        }
    }

    /// See [`super::Store::check_file`].
    pub(super) fn check_file(&self) -> Result<(), StoreFault> {
        match &self.file {
            Some(file) => file.check(),
            None => Ok(()),
        }
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
/// released while the file is not writable (`access(2)`, which opens nothing: see the module
/// docs): SQLite opens such a file read-only and the connection would stay read-only after the
/// file is writable again.
async fn still_usable(connection: &mut SqliteConnection, path: &Path) -> Result<bool, sqlx::Error> {
    if rustix::fs::access(path, rustix::fs::Access::WRITE_OK).is_err() {
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
