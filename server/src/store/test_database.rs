//! Fresh PostgreSQL databases for this workspace's tests (the store's unit tests and the black-box
//! tests in `tests/`), so every test runs on its own database, in parallel with the others.
//!
//! The server to create them on is `SPOOFWATCH_TEST_POSTGRES_URL` (e.g. the one
//! `scripts/postgres-ephemeral.sh start target/pg 55432` prints). Unset, PostgreSQL variants of tests
//! are skipped with a message, unless `SPOOFWATCH_REQUIRE_POSTGRES=1` (CI), which makes them fail.

use sqlx::{AssertSqlSafe, Connection, PgConnection};

/// The server on which test databases are created.
pub const URL_VARIABLE: &str = "SPOOFWATCH_TEST_POSTGRES_URL";

/// Set to `1`, a missing [`URL_VARIABLE`] fails tests instead of skipping them.
pub const REQUIRE_VARIABLE: &str = "SPOOFWATCH_REQUIRE_POSTGRES";

/// A database created for one test; [`TestDatabase::drop_database`] removes it. A test that panics
/// leaves its database behind, on a cluster meant to be thrown away.
#[derive(Debug)]
pub struct TestDatabase {
    /// The URL of the new, empty database.
    pub url: String,
    admin_url: String,
    name: String,
}

impl TestDatabase {
    /// A new empty database for the test `test`, or `None` (after saying so on stderr) when no
    /// server is configured. Panics when one is required but missing, or cannot be used.
    pub async fn create(test: &str) -> Option<TestDatabase> {
        let admin_url = match std::env::var(URL_VARIABLE) {
            Ok(url) if !url.is_empty() => url,
            _ => {
                assert!(
                    std::env::var(REQUIRE_VARIABLE).as_deref() != Ok("1"),
                    "{REQUIRE_VARIABLE}=1 but {URL_VARIABLE} is not set: {test} needs PostgreSQL"
                );
                eprintln!(
                    "skipping the PostgreSQL variant of {test}: {URL_VARIABLE} is not set (start \
                     one with scripts/postgres-ephemeral.sh start target/pg 55432)"
                );
                return None;
            }
        };
        let name = format!("t_{}", uuid::Uuid::new_v4().simple());
        let mut admin = PgConnection::connect(&admin_url)
            .await
            .unwrap_or_else(|error| panic!("connecting to {URL_VARIABLE}: {error}"));
        sqlx::query(AssertSqlSafe(format!("CREATE DATABASE {name}")))
            .execute(&mut admin)
            .await
            .unwrap_or_else(|error| panic!("creating the test database {name}: {error}"));
        // Closing politely is a courtesy; the database exists either way.
        let _ = admin.close().await;
        Some(TestDatabase {
            url: with_database(&admin_url, &name),
            admin_url,
            name,
        })
    }

    /// Drops the database, closing connections still open to it.
    pub async fn drop_database(self) {
        let mut admin = PgConnection::connect(&self.admin_url)
            .await
            .unwrap_or_else(|error| panic!("connecting to {URL_VARIABLE}: {error}"));
        let drop = format!("DROP DATABASE IF EXISTS {} WITH (FORCE)", self.name);
        sqlx::query(AssertSqlSafe(drop))
            .execute(&mut admin)
            .await
            .unwrap_or_else(|error| panic!("dropping the test database {}: {error}", self.name));
        let _ = admin.close().await;
    }
}

/// `url` (`postgres://user@host:port/db?params`) with its database replaced by `name`.
fn with_database(url: &str, name: &str) -> String {
    let (base, query) = match url.split_once('?') {
        Some((base, query)) => (base, Some(query)),
        None => (url, None),
    };
    let authority_start = base.find("://").map_or(0, |at| at + 3);
    let path_start = base[authority_start..]
        .find('/')
        .map_or(base.len(), |at| authority_start + at);
    let mut with = format!("{}/{name}", &base[..path_start]);
    if let Some(query) = query {
        with.push('?');
        with.push_str(query);
    }
    with
}

#[cfg(test)]
mod tests {
    use super::with_database;

    #[test]
    fn the_database_of_a_url_is_replaced() {
        assert_eq!(
            with_database("postgres://postgres@127.0.0.1:55432/postgres", "t_1"),
            "postgres://postgres@127.0.0.1:55432/t_1"
        );
        assert_eq!(
            with_database("postgresql://u:p@h/db?sslmode=disable", "t_2"),
            "postgresql://u:p@h/t_2?sslmode=disable"
        );
        assert_eq!(
            with_database("postgres://h:5432", "t_3"),
            "postgres://h:5432/t_3"
        );
    }
}
