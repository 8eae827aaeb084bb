//! A database the server cannot migrate stops it at startup with an error naming the migration
//! (version and description) and the cause: a migration applied with other contents, and one
//! unknown to this build (a database written by a newer version).

use spoofwatch_tests::{TestServer, database_path, test_config};
use sqlx::{Connection, SqliteConnection};

/// A database migrated by a server that then stopped, in a new directory, edited by `sql`.
async fn migrated_then_edited(sql: &'static str) -> tempfile::TempDir {
    let dir = tempfile::tempdir().expect("temp dir");
    TestServer::start(test_config(dir.path()))
        .await
        .stop()
        .await;
    edit_database(dir.path(), sql).await;
    dir
}

/// Runs `sql` on the SQLite database of a stopped server in `dir`.
async fn edit_database(dir: &std::path::Path, sql: &'static str) {
    let url = format!("sqlite://{}", database_path(dir).display());
    let mut connection = SqliteConnection::connect(&url)
        .await
        .expect("open the stopped server's database");
    sqlx::query(sql)
        .execute(&mut connection)
        .await
        .unwrap_or_else(|error| panic!("{sql}: {error}"));
    connection.close().await.expect("close the database");
}

/// The error `serve` stops with on the database in `dir`.
async fn start_error(dir: &std::path::Path) -> String {
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0")
        .await
        .expect("bound");
    spoofwatch_server::serve(test_config(dir), listener, std::future::pending())
        .await
        .expect_err("a database that cannot be migrated stops the server")
        .to_string()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_migration_applied_with_other_contents_is_named_with_its_cause() {
    let dir =
        migrated_then_edited("UPDATE _sqlx_migrations SET checksum = X'00' WHERE version = 3")
            .await;
    let error = start_error(dir.path()).await;
    assert!(error.contains("migration 3 (job leases)"), "{error}");
    assert!(error.contains("checksum differs"), "{error}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_migration_from_a_newer_version_is_named_with_its_cause() {
    let dir = migrated_then_edited(
        "INSERT INTO _sqlx_migrations (version, description, success, checksum, execution_time) \
         VALUES (99999999, 'from the future', TRUE, X'00', 0)",
    )
    .await;
    let error = start_error(dir.path()).await;
    assert!(error.contains("migration 99999999"), "{error}");
    assert!(error.contains("newer Spoofwatch"), "{error}");
}
