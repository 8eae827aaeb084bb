//! A PostgreSQL outage, for real: the test runs its own throw-away cluster
//! (`scripts/postgres-ephemeral.sh`) and stops it while a vehicle streams into its attack. While the
//! database is down, detection goes on from memory with every output unchanged, `spoofwatch.storage`
//! health is NOT_SERVING and DetectionService stays SERVING (so a balancer keeps the replica). When
//! the same cluster is back, without a restart of the server, storage health is SERVING again, the
//! alarm events and session snapshots held in the meantime are stored, and another server on the
//! database resumes the vehicle from the snapshot. A vehicle that moves to a replica holding no
//! session for it while the database is down is refused with UNAVAILABLE, to retry, rather than
//! started afresh behind its stored snapshot, and resumes from that snapshot once the database is
//! back.
//!
//! Runs where PostgreSQL is available to the tests (`SPOOFWATCH_TEST_POSTGRES_URL` set; the test
//! only needs the binaries); skipped otherwise, failed under `SPOOFWATCH_REQUIRE_POSTGRES=1`.

use std::net::TcpListener;
use std::path::{Path, PathBuf};
use std::process::Command;

use spoofwatch_core::scenario::AttackKind;
use spoofwatch_proto::v1;
use spoofwatch_server::Config;
use spoofwatch_server::store::test_database::{REQUIRE_VARIABLE, URL_VARIABLE};
use spoofwatch_tests::{
    Clients, ServingStatus, TestServer, alarms_of, attacked_drive, code_of, fingerprint, health_of,
    normal_drive, open_stream, start_request, start_stream, test_config, track_samples,
    wait_for_health,
};
use tonic::Code;
use tonic_types::StatusExt;

const STORAGE: &str = "spoofwatch.storage";
const BATCH: usize = 10;

/// Whether this test may run here (see the module docs).
fn postgres_available() -> bool {
    if std::env::var(URL_VARIABLE).is_ok_and(|url| !url.is_empty()) {
        return true;
    }
    assert!(
        std::env::var(REQUIRE_VARIABLE).as_deref() != Ok("1"),
        "{REQUIRE_VARIABLE}=1 but {URL_VARIABLE} is not set"
    );
    eprintln!("skipping the PostgreSQL outage test: {URL_VARIABLE} is not set");
    false
}

fn script(args: &[&str]) -> Command {
    let mut command = Command::new("bash");
    command
        .arg(Path::new(env!("CARGO_MANIFEST_DIR")).join("../scripts/postgres-ephemeral.sh"))
        .args(args);
    command
}

/// `scripts/postgres-ephemeral.sh <args>`; returns its stdout, panics when it fails.
fn cluster(args: &[&str]) -> String {
    let output = script(args)
        .output()
        .expect("run scripts/postgres-ephemeral.sh");
    assert!(
        output.status.success(),
        "postgres-ephemeral.sh {args:?} failed: {}",
        String::from_utf8_lossy(&output.stderr)
    );
    String::from_utf8(output.stdout)
        .expect("UTF-8")
        .trim()
        .to_string()
}

/// A cluster of our own in a temporary directory, stopped when dropped (also when the test fails).
struct Cluster {
    dir: PathBuf,
    port: String,
    _temp: tempfile::TempDir,
}

impl Cluster {
    fn start() -> (Cluster, String) {
        let temp = tempfile::tempdir().expect("temp dir");
        let port = TcpListener::bind("127.0.0.1:0")
            .and_then(|l| l.local_addr())
            .expect("a free port")
            .port()
            .to_string();
        let dir = temp.path().join("pg");
        let url = cluster(&["start", dir.to_str().expect("UTF-8 path"), &port]);
        let cluster = Cluster {
            dir,
            port,
            _temp: temp,
        };
        (cluster, url)
    }

    fn stop(&self) {
        cluster(&["stop", self.dir.to_str().expect("UTF-8 path")]);
    }

    fn restart(&self) {
        cluster(&["start", self.dir.to_str().expect("UTF-8 path"), &self.port]);
    }
}

impl Drop for Cluster {
    fn drop(&mut self) {
        let _ = script(&["stop", self.dir.to_str().unwrap_or_default()]).output();
    }
}

fn replica(url: &str) -> Config {
    let mut config = Config::with_database(url);
    config.shutdown_grace_secs = 2;
    config
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn detection_continues_through_a_database_outage_and_storage_catches_up() {
    if !postgres_available() {
        return;
    }
    let vehicle = "outage-1";
    // The fix freezes at 150 s: the alarm's onset falls inside the outage.
    let track = attacked_drive(vehicle, 400.0, 41, AttackKind::FrozenPosition, 150.0, 120.0);
    let batches: Vec<Vec<v1::Sample>> = track_samples(&track)
        .chunks(BATCH)
        .map(<[v1::Sample]>::to_vec)
        .collect();
    let (outage_from, outage_to) = (10, 30); // batches: 100 s to 300 s

    // The uninterrupted run, on SQLite.
    let reference_dir = tempfile::tempdir().expect("temp dir");
    let reference = TestServer::start(test_config(reference_dir.path())).await;
    let mut reference_clients = Clients::of(&reference).await;
    let (mut stream, _) = start_stream(&reference_clients, vehicle, "").await;
    let mut uninterrupted = Vec::new();
    for (seq, batch) in (1..).zip(&batches) {
        uninterrupted.extend(stream.detect(seq, batch.clone()).await.expect("detections"));
    }
    stream.finish().await.expect("the stream ends cleanly");
    let expected_alarms = alarms_of(&mut reference_clients, vehicle).await;
    assert!(!expected_alarms.is_empty(), "the drive alarms");
    drop(reference_clients);
    reference.stop().await;

    let (postgres, url) = Cluster::start();
    let server = TestServer::start(replica(&url)).await;
    let clients = Clients::of(&server).await;
    let (mut stream, _) = start_stream(&clients, vehicle, "").await;
    let mut detections = Vec::new();
    for (seq, batch) in (1..).zip(&batches) {
        if seq == outage_from {
            postgres.stop();
        }
        if seq == outage_to {
            // The onset could not be stored: storage reports it, detection does not stop.
            wait_for_health(&server, STORAGE, ServingStatus::NotServing).await;
            assert_eq!(
                health_of(&server, "spoofwatch.v1.DetectionService").await,
                ServingStatus::Serving
            );
            postgres.restart();
            wait_for_health(&server, STORAGE, ServingStatus::Serving).await;
        }
        detections.extend(stream.detect(seq, batch.clone()).await.expect("detections"));
    }
    assert_eq!(
        fingerprint(&detections),
        fingerprint(&uninterrupted),
        "detection from memory is the uninterrupted run's"
    );
    stream
        .finish()
        .await
        .expect("the stream ends cleanly (its snapshot is stored)");
    drop(clients);
    server.stop().await;

    // Another server on the database: every alarm event is there once, and the session resumes.
    let next = TestServer::start(replica(&url)).await;
    let mut clients = Clients::of(&next).await;
    assert_eq!(alarms_of(&mut clients, vehicle).await, expected_alarms);
    let (_stream, accepted) = start_stream(&clients, vehicle, "").await;
    assert!(accepted.resumed && accepted.from_snapshot, "{accepted:?}");
    assert_eq!(accepted.last_seq, batches.len() as u64);
    drop(clients);
    next.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_vehicle_moving_while_the_database_is_down_waits_for_its_snapshot() {
    if !postgres_available() {
        return;
    }
    let vehicle = "outage-moves";
    let batches: Vec<Vec<v1::Sample>> = track_samples(&normal_drive(vehicle, 60.0, 7))
        .chunks(BATCH)
        .map(<[v1::Sample]>::to_vec)
        .collect();
    let (postgres, url) = Cluster::start();
    let first = TestServer::start(replica(&url)).await;
    let second = TestServer::start(replica(&url)).await;
    let first_clients = Clients::of(&first).await;
    let (mut stream, _) = start_stream(&first_clients, vehicle, "").await;
    for (seq, batch) in (1..).zip(&batches) {
        stream.detect(seq, batch.clone()).await.expect("detections");
    }
    stream
        .finish()
        .await
        .expect("the stream ends (its snapshot is stored)");

    postgres.stop();
    let second_clients = Clients::of(&second).await;
    let refused = match open_stream(&second_clients, start_request(vehicle, "", false)).await {
        Ok(mut stream) => stream
            .accepted()
            .await
            .expect_err("no session while unreadable"),
        Err(error) => error,
    };
    assert_eq!(code_of(&refused), Code::Unavailable, "{refused}");
    let status = refused.status().expect("a status");
    assert!(
        status
            .message()
            .contains("stored session could not be read"),
        "{}",
        status.message()
    );
    assert!(
        status.get_details_retry_info().is_some(),
        "UNAVAILABLE says when to retry"
    );

    postgres.restart();
    wait_for_health(&second, STORAGE, ServingStatus::Serving).await;
    let (_stream, accepted) = start_stream(&second_clients, vehicle, "").await;
    assert!(
        accepted.resumed && accepted.from_snapshot,
        "the refused start left nothing behind to shadow the snapshot: {accepted:?}"
    );
    assert_eq!(accepted.last_seq, batches.len() as u64);
    drop((first_clients, second_clients));
    first.stop().await;
    second.stop().await;
}
