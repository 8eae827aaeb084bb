//! Store tests: every query against a real, tempfile-backed SQLite database and, when
//! `SPOOFWATCH_TEST_POSTGRES_URL` names a server, against a fresh PostgreSQL database too
//! ([`on_both_backends!`]); tests of SQLite's own faults and files run on SQLite only.

/// For each named `async fn(Store)`, a module of two tests: `sqlite` on a fresh database file and
/// `postgres` on a fresh PostgreSQL database (skipped, or failed under
/// `SPOOFWATCH_REQUIRE_POSTGRES=1`, without a server: see `store::test_database`).
macro_rules! on_both_backends {
    ($($test:ident),+ $(,)?) => {
        $(
            mod $test {
                #[tokio::test]
                async fn sqlite() {
                    let (_dir, store) = $crate::store::tests::temp_store().await;
                    super::$test(store).await;
                }

                #[tokio::test]
                async fn postgres() {
                    use $crate::store::test_database::TestDatabase;
                    let Some(database) = TestDatabase::create(stringify!($test)).await else {
                        return;
                    };
                    let store = $crate::store::Store::open(&database.url)
                        .await
                        .expect("open the PostgreSQL test database");
                    super::$test(store.clone()).await;
                    store.close().await;
                    database.drop_database().await;
                }
            }
        )+
    };
}

/// In a module with `async fn check(store: Store)`: its two tests, `sqlite` and `postgres` (skipped
/// as in [`on_both_backends!`]), each on a database migrated to schema version `$version` only,
/// given the rows the statements insert (what a server of that version stored), then opened by
/// this build (which migrates it on) and handed to `check`.
macro_rules! from_schema_version {
    ($version:expr, sqlite: $sqlite:expr, postgres: $postgres:expr $(,)?) => {
        #[tokio::test]
        async fn sqlite() {
            let (_dir, store) = $crate::store::tests::sqlite_from_version($version, &$sqlite).await;
            check(store).await;
        }

        #[tokio::test]
        async fn postgres() {
            let Some((database, store)) =
                $crate::store::tests::postgres_from_version(module_path!(), $version, &$postgres)
                    .await
            else {
                return;
            };
            check(store.clone()).await;
            store.close().await;
            database.drop_database().await;
        }
    };
}

mod alarms;
mod connection;
mod credentials;
mod datasets;
mod incidents;
mod jobs;
mod models;
mod postgres;
mod severities;
mod shadows;
mod snapshots;

use serde_json::json;
use tempfile::TempDir;

use super::test_database::TestDatabase;
use super::{JobKind, ModelSource, NewDataset, NewJob, NewModel, Store};

/// A fresh, migrated database file in its own temporary directory (kept alive by the returned guard).
pub(super) async fn temp_store() -> (TempDir, Store) {
    let dir = tempfile::tempdir().expect("create temp dir");
    let store = Store::open(&db_path(&dir)).await.expect("open store");
    (dir, store)
}

/// A SQLite store on a database migrated to schema `version`, given the rows `old` inserts, then
/// opened by this build (see `from_schema_version!`).
pub(super) async fn sqlite_from_version(version: i64, old: &[&str]) -> (TempDir, Store) {
    let dir = tempfile::tempdir().expect("temp dir");
    let path = db_path(&dir);
    let url = format!("sqlite://{path}?mode=rwc");
    let pool = sqlx::SqlitePool::connect(&url).await.expect("connect");
    sqlx::migrate!("../migrations/sqlite")
        .run_to(version, &pool)
        .await
        .unwrap_or_else(|error| panic!("schema version {version}: {error}"));
    for statement in old {
        sqlx::query(sqlx::AssertSqlSafe(*statement))
            .execute(&pool)
            .await
            .unwrap_or_else(|error| panic!("{statement}: {error}"));
    }
    pool.close().await;
    let store = Store::open(&path).await.expect("open");
    (dir, store)
}

/// [`sqlite_from_version`] on a fresh PostgreSQL database for the test `test`; `None` without a
/// server (see `TestDatabase::create`).
pub(super) async fn postgres_from_version(
    test: &str,
    version: i64,
    old: &[&str],
) -> Option<(TestDatabase, Store)> {
    let database = TestDatabase::create(test).await?;
    let pool = sqlx::PgPool::connect(&database.url).await.expect("connect");
    sqlx::migrate!("../migrations/postgres")
        .run_to(version, &pool)
        .await
        .unwrap_or_else(|error| panic!("schema version {version}: {error}"));
    for statement in old {
        sqlx::query(sqlx::AssertSqlSafe(*statement))
            .execute(&pool)
            .await
            .unwrap_or_else(|error| panic!("{statement}: {error}"));
    }
    pool.close().await;
    let store = Store::open(&database.url).await.expect("open");
    Some((database, store))
}

/// The database file path inside `dir`.
fn db_path(dir: &TempDir) -> String {
    dir.path()
        .join("spoofwatch.db")
        .to_string_lossy()
        .into_owned()
}

/// A model whose fields are derived from `id`, with a 3-byte artifact.
fn new_model(id: &str) -> NewModel {
    NewModel {
        id: id.to_owned(),
        display_name: format!("Model {id}"),
        source: ModelSource::Training,
        training_operation: Some(format!("operations/train-{id}")),
        schema_version: 1,
        sha256: format!("sha-{id}"),
        metadata: json!({"threshold": 0.5, "auroc": 0.93, "id": id}),
        artifact: vec![1, 2, 3],
    }
}

/// A dataset whose fields are derived from `id`, with a small CSV content in two pieces.
fn new_dataset(id: &str) -> NewDataset {
    NewDataset {
        id: id.to_owned(),
        display_name: format!("Dataset {id}"),
        source: "upload".to_owned(),
        format: "telemetry-csv".to_owned(),
        rows: 10,
        vehicles: 2,
        labelled_rows: 8,
        spoofed_rows: 3,
        sha256: format!("sha-{id}"),
        content: vec![b"vehicle_id,timestamp_s\n".to_vec(), b"v1,0.0\n".to_vec()],
    }
}

/// A queued job request of `kind`.
fn new_job(id: &str, kind: JobKind) -> NewJob {
    NewJob {
        id: id.to_owned(),
        kind,
        request: json!({"dataset": "d1", "epochs": 5}),
        metadata: json!({"epoch": 0}),
        owner: "this-server".to_owned(),
    }
}

/// Rows in `table` (a fixed, test-chosen table name).
async fn count_rows(store: &Store, table: &'static str) -> i64 {
    let sql = match table {
        "models" => "SELECT COUNT(*) FROM models",
        "model_artifacts" => "SELECT COUNT(*) FROM model_artifacts",
        "datasets" => "SELECT COUNT(*) FROM datasets",
        "dataset_pieces" => "SELECT COUNT(*) FROM dataset_pieces",
        "jobs" => "SELECT COUNT(*) FROM jobs",
        "job_epochs" => "SELECT COUNT(*) FROM job_epochs",
        "alarm_events" => "SELECT COUNT(*) FROM alarm_events",
        other => panic!("unknown table {other}"),
    };
    store.scalar_for_test(sql).await
}
