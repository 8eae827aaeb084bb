//! PostgreSQL-only: a server that goes away makes calls fail as a fault (never a panic), and the
//! pool reconnects once it is back. Runs its own throw-away cluster (scripts/postgres-ephemeral.sh),
//! so stopping it disturbs no other test; runs when PostgreSQL tests do (see `store::test_database`).

use std::process::Command;

use super::new_model;
use crate::store::test_database::{REQUIRE_VARIABLE, URL_VARIABLE};
use crate::store::{FaultKind, Store, StoreError};

const SCRIPT: &str = concat!(
    env!("CARGO_MANIFEST_DIR"),
    "/../scripts/postgres-ephemeral.sh"
);

/// A cluster of the ephemeral script, stopped when dropped (also when the test panics).
struct Cluster {
    dir: tempfile::TempDir,
    port: u16,
}

impl Cluster {
    fn start(&self) -> String {
        let dir = self.dir.path().to_string_lossy();
        let out = Command::new(SCRIPT)
            .args(["start", &dir, &self.port.to_string()])
            .output()
            .expect("run the ephemeral PostgreSQL script");
        assert!(
            out.status.success(),
            "{}",
            String::from_utf8_lossy(&out.stderr)
        );
        String::from_utf8_lossy(&out.stdout).trim().to_string()
    }

    fn stop(&self) {
        let dir = self.dir.path().to_string_lossy();
        let status = Command::new(SCRIPT).args(["stop", &dir]).status();
        assert!(status.is_ok_and(|s| s.success()), "the cluster stops");
    }
}

impl Drop for Cluster {
    fn drop(&mut self) {
        let dir = self.dir.path().to_string_lossy().into_owned();
        let _ = Command::new(SCRIPT).args(["stop", &dir]).status();
    }
}

#[tokio::test]
async fn a_postgres_server_that_goes_away_is_unavailable_then_served_again() {
    if std::env::var(URL_VARIABLE).is_err() {
        assert!(
            std::env::var(REQUIRE_VARIABLE).as_deref() != Ok("1"),
            "{REQUIRE_VARIABLE}=1 but {URL_VARIABLE} is not set"
        );
        eprintln!("skipping: {URL_VARIABLE} is not set (no PostgreSQL for tests)");
        return;
    }
    let port = std::net::TcpListener::bind("127.0.0.1:0")
        .and_then(|listener| listener.local_addr())
        .expect("a free port")
        .port();
    let cluster = Cluster {
        dir: tempfile::tempdir().expect("temp dir"),
        port,
    };
    let url = cluster.start();
    let store = Store::open(&url).await.expect("open");
    store.insert_model(new_model("before")).await.unwrap();

    cluster.stop();
    let fault = match store.model_count().await {
        Err(StoreError::Unavailable(fault)) => fault,
        other => panic!("expected the database to be unavailable, got {other:?}"),
    };
    assert!(
        matches!(fault.kind, FaultKind::Unreachable | FaultKind::Busy),
        "{fault:?}"
    );

    cluster.start();
    assert_eq!(store.model_count().await.unwrap(), 1, "the pool reconnects");
    store.insert_model(new_model("after")).await.unwrap();
    store.close().await;
}
