//! Opening, pragmas, persistence across reopen, and concurrent writers.

use serde_json::json;

use super::{count_rows, db_path, new_dataset, new_job, new_model, temp_store};
use crate::alarms::event::{Onset, opened};
use crate::store::{
    AlarmEvent, AlarmEventKind, EpochRow, FaultKind, JobKind, JobOutcome, JobState, PageRequest,
    Store, StoreError, StoreOptions,
};
use sqlx::Connection;

#[tokio::test]
async fn open_creates_the_file_and_applies_the_pragmas() {
    let (dir, store) = temp_store().await;
    assert!(dir.path().join("spoofwatch.db").is_file());
    let journal_mode = sqlx::query_scalar::<_, String>("PRAGMA journal_mode")
        .fetch_one(store.sqlite_pool())
        .await
        .unwrap();
    assert_eq!(journal_mode, "wal");
    let foreign_keys = sqlx::query_scalar::<_, i64>("PRAGMA foreign_keys")
        .fetch_one(store.sqlite_pool())
        .await
        .unwrap();
    assert_eq!(foreign_keys, 1);
    // 1 = NORMAL (0 OFF, 2 FULL, 3 EXTRA).
    let synchronous = sqlx::query_scalar::<_, i64>("PRAGMA synchronous")
        .fetch_one(store.sqlite_pool())
        .await
        .unwrap();
    assert_eq!(synchronous, 1);
    let busy_timeout_ms = sqlx::query_scalar::<_, i64>("PRAGMA busy_timeout")
        .fetch_one(store.sqlite_pool())
        .await
        .unwrap();
    assert_eq!(busy_timeout_ms, 5_000);
    assert_eq!(store.model_count().await.unwrap(), 0);
}

#[tokio::test]
async fn open_accepts_urls_bare_paths_and_memory() {
    let dir = tempfile::tempdir().unwrap();
    let bare = dir.path().join("bare.db").to_string_lossy().into_owned();
    let url = format!("sqlite://{}", dir.path().join("url.db").to_string_lossy());
    let short_url = format!("sqlite:{}", dir.path().join("short.db").to_string_lossy());
    for target in [
        bare.as_str(),
        url.as_str(),
        short_url.as_str(),
        "sqlite::memory:",
    ] {
        let store = Store::open(target).await.unwrap();
        store.insert_model(new_model("m1")).await.unwrap();
        assert_eq!(store.model_count().await.unwrap(), 1, "{target}");
        store.close().await;
    }
    for file in ["bare.db", "url.db", "short.db"] {
        assert!(dir.path().join(file).is_file(), "{file} created");
    }
}

#[tokio::test]
async fn memory_databases_are_private_to_their_store() {
    let first = Store::open("sqlite::memory:").await.unwrap();
    let second = Store::open("sqlite::memory:").await.unwrap();
    first.insert_model(new_model("m1")).await.unwrap();
    assert_eq!(second.model_count().await.unwrap(), 0);
}

/// The fault kind of a store error, panicking on anything that is not a fault.
fn fault_kind(error: StoreError) -> FaultKind {
    match error {
        StoreError::Unavailable(fault) => fault.kind,
        other => panic!("expected a database fault, got {other:?}"),
    }
}

#[tokio::test]
async fn opening_an_unusable_path_is_a_cant_open_fault() {
    let dir = tempfile::tempdir().unwrap();
    let inside_missing_dir = dir.path().join("no-such-dir").join("db.sqlite");
    let error = Store::open(&inside_missing_dir.to_string_lossy())
        .await
        .unwrap_err();
    assert_eq!(fault_kind(error), FaultKind::CantOpen);
}

async fn a_closed_store_fails_with_a_closed_fault(store: Store) {
    store.close().await;
    let error = store.model_count().await.unwrap_err();
    assert_eq!(
        error.to_string(),
        "the database is closed (the server is shutting down)"
    );
    assert_eq!(fault_kind(error), FaultKind::Closed);
}

#[tokio::test]
async fn a_full_database_refuses_writes_and_takes_them_again_once_space_is_freed() {
    let dir = tempfile::tempdir().unwrap();
    let options = StoreOptions {
        max_bytes: Some(512 * 1024),
    };
    let store = Store::open_with(&db_path(&dir), options).await.unwrap();
    let mut blob = new_dataset("ballast-0");
    blob.content = vec![vec![7; 40 * 1024]];
    let mut stored = Vec::new();
    let full = loop {
        let mut dataset = blob.clone();
        dataset.id = format!("ballast-{}", stored.len());
        match store.insert_dataset(dataset.clone()).await {
            Ok(_) => stored.push(dataset.id),
            Err(error) => break error,
        }
        assert!(stored.len() < 100, "the size limit never applied");
    };
    assert_eq!(fault_kind(full), FaultKind::Full);
    // Small rows fill the last partly used pages, then fail too.
    let mut id = 1;
    let refused = loop {
        if let Err(error) = store.write_alarms(&[alarm_onset(id)]).await {
            break error;
        }
        id += 1;
        assert!(id < 100_000, "alarm rows never filled the database");
    };
    assert_eq!(fault_kind(refused), FaultKind::Full);
    // Reads keep working while full.
    assert_eq!(store.max_alarm_id().await.unwrap(), id - 1);

    for dataset in &stored[..2] {
        store.delete_dataset(dataset).await.unwrap();
    }
    store.write_alarms(&[alarm_onset(id)]).await.unwrap();
    store.insert_model(new_model("after-full")).await.unwrap();
    assert_eq!(store.max_alarm_id().await.unwrap(), id);
}

#[tokio::test]
async fn a_deleted_database_file_is_detected_and_refuses_everything_after() {
    let (dir, store) = temp_store().await;
    store.insert_model(new_model("m1")).await.unwrap();
    store.check_file().unwrap();
    std::fs::remove_file(db_path(&dir)).unwrap();
    let fault = store.check_file().unwrap_err();
    assert_eq!(fault.kind, FaultKind::Lost);
    assert!(fault.cause.contains("No such file"), "{}", fault.cause);
    let error = store.insert_model(new_model("m2")).await.unwrap_err();
    assert_eq!(fault_kind(error), FaultKind::Lost);
    assert_eq!(
        fault_kind(store.model_count().await.unwrap_err()),
        FaultKind::Lost
    );
}

#[tokio::test]
async fn a_replaced_database_file_is_detected() {
    let (dir, store) = temp_store().await;
    let path = db_path(&dir);
    let replacement = dir.path().join("other.db");
    std::fs::copy(&path, &replacement).unwrap();
    std::fs::rename(&replacement, &path).unwrap();
    let fault = store.check_file().unwrap_err();
    assert_eq!(fault.kind, FaultKind::Lost);
    assert!(fault.cause.contains("replaced"), "{}", fault.cause);
    // Once lost, always lost: the file the server opened is gone.
    assert!(store.check_file().is_err());
}

#[tokio::test]
async fn a_read_only_database_is_a_read_only_fault() {
    let (dir, store) = temp_store().await;
    store.close().await;
    let read_only = format!("sqlite://{}?mode=ro", db_path(&dir));
    // Migrations are already applied, so opening read-only succeeds and only writes fail.
    let store = Store::open(&read_only).await.unwrap();
    let error = store.insert_model(new_model("m1")).await.unwrap_err();
    assert_eq!(fault_kind(error), FaultKind::ReadOnly);
    assert_eq!(store.model_count().await.unwrap(), 0);
}

#[tokio::test]
async fn a_database_locked_by_another_process_is_a_busy_fault() {
    let (dir, store) = temp_store().await;
    // Another connection (as another process would) holds the write lock past the busy timeout.
    let mut other = sqlx::SqliteConnection::connect(&format!("sqlite://{}", db_path(&dir)))
        .await
        .unwrap();
    sqlx::query("BEGIN IMMEDIATE")
        .execute(&mut other)
        .await
        .unwrap();
    let error = store.insert_model(new_model("m1")).await.unwrap_err();
    assert_eq!(fault_kind(error), FaultKind::Busy);
    sqlx::query("ROLLBACK").execute(&mut other).await.unwrap();
    store.insert_model(new_model("m1")).await.unwrap();
}

/// An alarm onset with id `id`.
fn alarm_onset(id: i64) -> AlarmEvent {
    AlarmEvent {
        seq: id,
        kind: AlarmEventKind::Onset,
        alarm: opened(id, &Onset::warning("v1", "m1", 10.0, 1_000, 0.9)),
    }
}

#[tokio::test]
async fn reopening_the_same_file_keeps_everything() {
    let dir = tempfile::tempdir().unwrap();
    let path = db_path(&dir);
    let alarm_id;
    {
        let store = Store::open(&path).await.unwrap();
        store.insert_model(new_model("m1")).await.unwrap();
        store.insert_model(new_model("m2")).await.unwrap();
        store.set_active_model("m2").await.unwrap();
        store.insert_dataset(new_dataset("d1")).await.unwrap();
        store
            .insert_job(new_job("j1", JobKind::Training))
            .await
            .unwrap();
        store.mark_running("j1").await.unwrap();
        let epoch = EpochRow {
            epoch: 0,
            train_loss: 0.25,
            val_loss: 0.5,
            val_auroc: Some(0.75),
            learning_rate: 0.001,
            elapsed_s: 1.5,
        };
        store.append_epoch("j1", &epoch).await.unwrap();
        store
            .finish_job(
                "j1",
                JobOutcome::Succeeded {
                    result: json!({"model": "m2"}),
                },
            )
            .await
            .unwrap();
        alarm_id = 1;
        store
            .write_alarms(&[onset(alarm_id, "car", 9.5)])
            .await
            .unwrap();
        store.close().await;
    }

    // Migrations already applied must be recognised, not re-run or rejected.
    let store = Store::open(&path).await.unwrap();
    assert_eq!(store.model_count().await.unwrap(), 2);
    assert_eq!(
        store.active_model().await.unwrap().expect("active kept").id,
        "m2"
    );
    assert_eq!(
        store.model_artifact("m1").await.unwrap(),
        Some(vec![1, 2, 3])
    );
    let dataset = store
        .get_dataset("d1")
        .await
        .unwrap()
        .expect("dataset kept");
    assert_eq!(dataset.rows, 10);
    assert_eq!(
        store
            .dataset_content("d1")
            .await
            .unwrap()
            .map(|pieces| pieces.concat().len()),
        Some(30)
    );
    let job = store.get_job("j1").await.unwrap().expect("job kept");
    assert_eq!(job.state, JobState::Succeeded);
    assert_eq!(job.result, Some(json!({"model": "m2"})));
    assert_eq!(
        store.job_epochs("j1").await.unwrap()[0].val_auroc,
        Some(0.75)
    );
    let alarms = store.list_alarm_events(None, 10).await.unwrap();
    assert_eq!(alarms.len(), 1);
    assert_eq!(alarms[0].id, alarm_id);
    assert!(alarms[0].is_open());
    let listed = store.list_models(&PageRequest::default()).await.unwrap();
    assert_eq!(listed.items.len(), 2);

    // The alarm writer continues ids after the stored ones.
    assert_eq!(store.max_alarm_id().await.unwrap(), alarm_id);
}

fn onset(id: i64, vehicle_id: &str, onset_timestamp_s: f64) -> AlarmEvent {
    AlarmEvent {
        seq: id,
        kind: AlarmEventKind::Onset,
        alarm: opened(
            id,
            &Onset::warning(vehicle_id, "m2", onset_timestamp_s, 1, 0.9),
        ),
    }
}

/// Two stores (two pools, like two processes) hammer one file with read-then-write transactions;
/// `BEGIN IMMEDIATE` plus `busy_timeout` must make every one of them wait instead of failing BUSY.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn concurrent_writers_on_one_file_never_fail_busy() {
    const PER_WRITER: usize = 50;
    let (dir, first) = temp_store().await;
    let second = Store::open(&db_path(&dir)).await.unwrap();

    let mut tasks = Vec::new();
    for (writer, store) in [first.clone(), second.clone()].into_iter().enumerate() {
        for index in 0..PER_WRITER {
            let store = store.clone();
            tasks.push(tokio::spawn(async move {
                let id = format!("w{writer}-{index}");
                store.insert_model(new_model(&id)).await?;
                // Reads the row, then writes two updates: the deferred-transaction BUSY trap.
                store.set_active_model(&id).await?;
                let alarm = (writer * PER_WRITER + index + 1) as i64;
                store.write_alarms(&[onset(alarm, &id, 1.0)]).await?;
                Ok::<_, StoreError>(())
            }));
        }
    }
    for task in tasks {
        task.await
            .expect("task did not panic")
            .expect("write succeeded");
    }

    assert_eq!(first.model_count().await.unwrap(), 2 * PER_WRITER as u64);
    assert_eq!(count_rows(&second, "model_artifacts").await, 100);
    assert_eq!(count_rows(&second, "alarm_events").await, 100);
    let active: i64 = sqlx::query_scalar("SELECT COUNT(*) FROM models WHERE active = 1")
        .fetch_one(first.sqlite_pool())
        .await
        .unwrap();
    assert_eq!(active, 1);
}

on_both_backends!(a_closed_store_fails_with_a_closed_fault,);
