//! Storage faults, injected for real and without root: a full database (the `--database-max-mib`
//! limit, which SQLite enforces as SQLITE_FULL), a database file made immutable (`chattr +i`: an
//! I/O error or a read-only refusal on every write, where the file system and privileges allow it)
//! and a deleted database file. While the fault lasts, writes are refused with RESOURCE_EXHAUSTED/UNAVAILABLE and a retry
//! hint, detection goes on from memory and `spoofwatch.storage` health is NOT_SERVING; once it
//! clears, without a restart, every alarm a client was shown is stored exactly once with its own
//! end, and writes work again. A deleted file is detected and turns the server NOT_SERVING.

use std::collections::HashSet;
use std::path::Path;
use std::process::Command;

use spoofwatch_proto::v1;
use spoofwatch_server::store::Store;
use spoofwatch_tests::{
    Clients, Episode, ServingStatus, TestServer, database_path, health_of, normal_drive,
    start_server, stored_episodes, stream_frozen_fix_drive, try_upload_tracks, upload_tracks,
    wait_for_health,
};
use tonic::Code;
use tonic_types::StatusExt;

const STORAGE: &str = "spoofwatch.storage";

/// Streams frozen-fix drives for new vehicles until the alarm writer reports the database refusing
/// (small alarm rows still fit into partly used pages for a while), then two more; returns every
/// vehicle's episodes as the client saw them.
async fn stream_until_alarms_are_refused(
    server: &TestServer,
    clients: &Clients,
) -> Vec<(String, Vec<Episode>)> {
    let mut shown = Vec::new();
    let mut after_refusal = 0;
    while after_refusal < 2 {
        let vehicle = format!("car-{}", shown.len());
        let episodes = stream_frozen_fix_drive(clients, &vehicle).await;
        assert!(!episodes.is_empty(), "{vehicle}: a frozen fix alarms");
        shown.push((vehicle, episodes));
        if health_of(server, STORAGE).await == ServingStatus::NotServing {
            after_refusal += 1;
        }
        assert!(shown.len() < 300, "the alarm writer never saw the fault");
    }
    shown
}

/// After the server stopped: every vehicle's stored alarm events are exactly the episodes it was
/// shown, and no alarm id is used twice.
async fn assert_every_shown_alarm_is_stored_once(dir: &Path, shown: &[(String, Vec<Episode>)]) {
    let store = Store::open(&database_path(dir).display().to_string())
        .await
        .expect("the database opens");
    let mut ids = HashSet::new();
    for (vehicle, episodes) in shown {
        let events = store
            .list_alarm_events(Some(vehicle), 100)
            .await
            .expect("alarm events");
        for event in &events {
            assert!(ids.insert(event.id), "alarm id {} used twice", event.id);
        }
        assert_eq!(
            &stored_episodes(&events),
            episodes,
            "{vehicle}: one stored event per alarm it was shown, each closed by its own end"
        );
    }
    store.close().await;
}

/// Uploads a small drive; `Err` with the refusal.
async fn upload_small(clients: &mut Clients, name: &str) -> Result<v1::Dataset, tonic::Status> {
    try_upload_tracks(clients, name, &[normal_drive("probe", 30.0, 3)]).await
}

/// A refusal for a storage fault: `code`, a message naming one of the `causes`, and a retry hint.
fn assert_storage_refusal(status: &tonic::Status, code: Code, causes: &[&str]) {
    assert_eq!(status.code(), code, "{status:?}");
    assert!(
        causes.iter().any(|cause| status.message().contains(cause)),
        "{status:?}"
    );
    assert!(
        status.get_details_retry_info().is_some(),
        "a retry hint: {status:?}"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_full_database_loses_no_alarm_and_takes_writes_again_once_space_is_freed() {
    let (dir, server, mut clients) = start_server(|config| config.database_max_mib = Some(2)).await;
    // Fill with ever smaller datasets, so that little room is left even for small rows.
    let mut ballast = Vec::new();
    let mut refusals = Vec::new();
    for duration_s in [600.0, 60.0, 5.0] {
        let refused = loop {
            let name = format!("ballast {}", ballast.len());
            let drive = normal_drive("ballast", duration_s, ballast.len() as u64);
            match try_upload_tracks(&mut clients, &name, &[drive]).await {
                Ok(dataset) => ballast.push(dataset.name),
                Err(status) => break status,
            }
            assert!(
                ballast.len() < 1_000,
                "the database size limit never applied"
            );
        };
        refusals.push(refused);
    }
    for refused in &refusals {
        assert_storage_refusal(refused, Code::ResourceExhausted, &["the database is full"]);
    }

    let shown = stream_until_alarms_are_refused(&server, &clients).await;
    assert_eq!(health_of(&server, "").await, ServingStatus::Serving);

    for name in ballast {
        clients
            .datasets
            .delete_dataset(v1::DeleteDatasetRequest { name })
            .await
            .expect("deleting works while the database is full");
    }
    wait_for_health(&server, STORAGE, ServingStatus::Serving).await;
    upload_tracks(
        &mut clients,
        "after the fault",
        &[normal_drive("v", 30.0, 1)],
    )
    .await;
    drop(clients);
    server.stop().await;
    assert_every_shown_alarm_is_stored_once(dir.path(), &shown).await;
}

/// Sets or clears the immutable attribute; `false` when the file system or privileges refuse.
fn set_immutable(files: &[&Path], on: bool) -> bool {
    Command::new("chattr")
        .arg(if on { "+i" } else { "-i" })
        .args(files)
        .output()
        .is_ok_and(|output| output.status.success())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_unwritable_database_file_loses_no_alarm_and_recovers_without_restart() {
    let (dir, server, mut clients) = start_server(|_| {}).await;
    let database = database_path(dir.path());
    let wal = database.with_extension("db-wal");
    let files = [database.as_path(), wal.as_path()];
    if !set_immutable(&files, true) {
        eprintln!(
            "SKIPPED: `chattr +i` is refused here (needs CAP_LINUX_IMMUTABLE on ext4/xfs), so the \
             database file cannot be made unwritable"
        );
        return;
    }
    let refused = upload_small(&mut clients, "while unwritable").await;
    let shown = stream_until_alarms_are_refused(&server, &clients).await;
    assert!(set_immutable(&files, false), "chattr -i");
    let refused = refused.expect_err("an upload is refused while the file is unwritable");
    // A connection opened before the fault fails its write with an I/O error; one the pool opened
    // during it (the alarm feed reads every 200 ms) got the file read-only.
    assert_storage_refusal(
        &refused,
        Code::Unavailable,
        &["I/O error", "the database is read-only"],
    );

    wait_for_health(&server, STORAGE, ServingStatus::Serving).await;
    upload_small(&mut clients, "after the fault")
        .await
        .expect("uploads work again without a restart");
    drop(clients);
    server.stop().await;
    assert_every_shown_alarm_is_stored_once(dir.path(), &shown).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_deleted_database_file_turns_the_server_not_serving_and_detection_goes_on() {
    let (dir, server, mut clients) = start_server(|_| {}).await;
    let database = database_path(dir.path());
    for suffix in ["db", "db-wal", "db-shm"] {
        let _ = std::fs::remove_file(database.with_extension(suffix));
    }
    wait_for_health(&server, "", ServingStatus::NotServing).await;
    assert_eq!(health_of(&server, STORAGE).await, ServingStatus::NotServing);
    assert_eq!(
        health_of(&server, "spoofwatch.v1.DatasetService").await,
        ServingStatus::NotServing
    );
    assert_eq!(
        health_of(&server, "spoofwatch.v1.DetectionService").await,
        ServingStatus::Serving,
        "detection runs from memory"
    );
    let refused = upload_small(&mut clients, "into the void")
        .await
        .expect_err("no write lands in a deleted file");
    assert_storage_refusal(&refused, Code::Unavailable, &["deleted or replaced"]);
    let episodes = stream_frozen_fix_drive(&clients, "still-watched").await;
    assert!(!episodes.is_empty(), "detection still alarms");
    drop(clients);
    server.stop().await;
    assert!(
        !database.exists(),
        "no empty database silently takes the deleted one's place"
    );
}
