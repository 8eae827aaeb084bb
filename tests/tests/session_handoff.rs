//! Session hand-off between server processes sharing a database: a vehicle's stream continues on
//! another server (here: a second server started on the same database after the first stopped)
//! from the stored snapshot, `SessionAccepted` says so and reports `last_seq`, and once the client
//! resends the batches after it, every detection and the alarm history equal an uninterrupted run's,
//! bit for bit. A corrupt, foreign or other-model snapshot is refused with its reason; the session
//! starts afresh and nothing else is lost, and the alarm an other-model snapshot held open ends.

use spoofwatch_core::scenario::AttackKind;
use spoofwatch_proto::v1;
use spoofwatch_server::store::{AlarmEvent, SnapshotRow, Store};
use spoofwatch_tests::{
    Clients, TestServer, alarms_of, attacked_drive, export_model, fingerprint, import_model,
    normal_drive, start_stream, stream_batches, test_config, track_samples,
};

const BATCH: usize = 10;

/// An attacked drive, batched, with a hand-off point inside the alarm.
fn attacked_batches(vehicle: &str) -> Vec<Vec<v1::Sample>> {
    let track = attacked_drive(vehicle, 400.0, 31, AttackKind::FrozenPosition, 150.0, 120.0);
    track_samples(&track)
        .chunks(BATCH)
        .map(<[v1::Sample]>::to_vec)
        .collect()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_stream_continues_on_another_server_exactly_as_if_uninterrupted() {
    let vehicle = "handoff-1";
    let batches = attacked_batches(vehicle);

    // The uninterrupted run, on its own database.
    let reference_dir = tempfile::tempdir().expect("temp dir");
    let reference = TestServer::start(test_config(reference_dir.path())).await;
    let mut reference_clients = Clients::of(&reference).await;
    let (_, uninterrupted) = stream_batches(&reference_clients, (vehicle, ""), &batches, 1).await;
    let expected_alarms = alarms_of(&mut reference_clients, vehicle).await;
    assert!(
        uninterrupted.iter().any(|d| d.alarm_onset),
        "the drive alarms (else the test shows nothing)"
    );
    drop(reference_clients);
    reference.stop().await;

    // First server: the stream stops inside the alarm (the cut is a batch boundary in the attack).
    let dir = tempfile::tempdir().expect("temp dir");
    let cut = 20; // batches, 200 s: the frozen fix started at 150 s
    let first = TestServer::start(test_config(dir.path())).await;
    let clients = Clients::of(&first).await;
    let (_, before) = stream_batches(&clients, (vehicle, ""), &batches[..cut], 1).await;
    assert!(before.iter().any(|d| d.alarm), "the alarm is on at the cut");
    drop(clients);
    first.stop().await;

    // Second server, same database: the session continues from the snapshot.
    let second = TestServer::start(test_config(dir.path())).await;
    let mut clients = Clients::of(&second).await;
    let (accepted, after) =
        stream_batches(&clients, (vehicle, ""), &batches[cut..], cut as u64 + 1).await;
    assert!(accepted.resumed && accepted.from_snapshot, "{accepted:?}");
    assert_eq!(accepted.last_seq, cut as u64);
    assert_eq!(accepted.samples_seen, (cut * BATCH) as u64);
    assert_eq!(accepted.snapshot_refused, "");

    let handed_off: Vec<v1::Detection> = before.into_iter().chain(after).collect();
    assert_eq!(fingerprint(&handed_off), fingerprint(&uninterrupted));
    // The alarm that was open at the hand-off is one alarm, ended once, as in the uninterrupted run.
    assert_eq!(alarms_of(&mut clients, vehicle).await, expected_alarms);
    drop(clients);
    second.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn corrupt_foreign_and_other_model_snapshots_start_afresh_with_their_reason() {
    let dir = tempfile::tempdir().expect("temp dir");
    let first = TestServer::start(test_config(dir.path())).await;
    let clients = Clients::of(&first).await;
    let vehicles = ["corrupt", "foreign", "intact"];
    let mut last_seq = 0;
    for (seed, vehicle) in (1..).zip(vehicles) {
        let samples = track_samples(&normal_drive(vehicle, 60.0, seed));
        let batches: Vec<Vec<v1::Sample>> = samples.chunks(BATCH).map(<[_]>::to_vec).collect();
        stream_batches(&clients, (vehicle, ""), &batches, 1).await;
        last_seq = batches.len() as u64;
    }
    drop(clients);
    first.stop().await;

    // Damage two snapshots behind the server's back (through the store, as another writer would).
    let database = test_config(dir.path()).database;
    let store = Store::open(&database).await.expect("open the database");
    let stored = |vehicle: &'static str| {
        let store = store.clone();
        async move {
            store
                .load_snapshot(vehicle)
                .await
                .expect("readable")
                .expect("the stream's end stored a snapshot")
        }
    };
    let mut corrupt = stored("corrupt").await;
    let middle = corrupt.snapshot.len() / 2;
    corrupt.snapshot[middle] ^= 0x01;
    let written = stored("foreign").await;
    let server_version = written.schema_version;
    let foreign = SnapshotRow {
        schema_version: 99,
        ..written
    };
    store
        .write_alarms_and_snapshots::<AlarmEvent>(&[], &[corrupt, foreign])
        .await
        .expect("written");
    store.close().await;

    let second = TestServer::start(test_config(dir.path())).await;
    let clients = Clients::of(&second).await;
    let (_corrupt_stream, corrupt) = start_stream(&clients, "corrupt", "").await;
    assert!(!corrupt.resumed && !corrupt.from_snapshot);
    assert_eq!(corrupt.last_seq, 0);
    assert_eq!(
        corrupt.snapshot_refused,
        "the stored session snapshot is corrupt (checksum mismatch)"
    );
    let (_foreign_stream, foreign) = start_stream(&clients, "foreign", "").await;
    assert!(!foreign.resumed);
    assert_eq!(
        foreign.snapshot_refused,
        format!(
            "the stored session snapshot has schema version 99; this server reads version \
             {server_version}"
        )
    );
    let (_intact_stream, intact) = start_stream(&clients, "intact", "").await;
    assert!(
        intact.resumed && intact.from_snapshot,
        "the others are unaffected"
    );
    assert_eq!(intact.last_seq, last_seq);
    drop(clients);
    second.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_alarm_held_by_a_snapshot_of_the_replaced_model_ends_when_the_vehicle_starts_afresh() {
    let vehicle = "rollout-1";
    let batches = attacked_batches(vehicle);
    let dir = tempfile::tempdir().expect("temp dir");
    let first = TestServer::start(test_config(dir.path())).await;
    let mut clients = Clients::of(&first).await;
    let artifact = export_model(&mut clients.models, "models/default").await;
    let candidate = import_model(&mut clients, artifact, "candidate").await.name;
    // The stream stops inside the alarm; its snapshot holds the alarm open.
    let (_, before) = stream_batches(&clients, (vehicle, ""), &batches[..20], 1).await;
    let last_alarming = before
        .iter()
        .rev()
        .find(|d| d.alarm)
        .expect("the alarm is on at the cut")
        .timestamp_s;
    drop(clients);
    first.stop().await;

    // Another process, after a roll-out: the vehicle's snapshot is of the old model, so its
    // session starts afresh under the new one, and the alarm the old session held ends.
    let second = TestServer::start(test_config(dir.path())).await;
    let mut clients = Clients::of(&second).await;
    clients
        .models
        .set_active_model(v1::SetActiveModelRequest { name: candidate })
        .await
        .expect("the candidate activates");
    let (_stream, accepted) = start_stream(&clients, vehicle, "").await;
    assert!(!accepted.resumed, "{accepted:?}");
    assert_eq!(accepted.replaced_model, "models/default");
    let mut alarms = Vec::new();
    for _ in 0..500 {
        alarms = alarms_of(&mut clients, vehicle).await;
        if alarms.iter().all(|alarm| !alarm.4) {
            break;
        }
        tokio::time::sleep(std::time::Duration::from_millis(10)).await;
    }
    assert_eq!(alarms.len(), 1, "{alarms:?}");
    let (_, end, _, _, open) = alarms[0];
    assert!(!open, "the alarm ended: {alarms:?}");
    assert_eq!(
        end,
        Some(last_alarming),
        "at the last alarming sample the session saw"
    );
    drop(clients);
    second.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_stale_copy_left_on_a_server_does_not_overwrite_the_snapshot_of_the_one_that_went_on() {
    let vehicle = "moved-on";
    let batches: Vec<Vec<v1::Sample>> = track_samples(&normal_drive(vehicle, 300.0, 9))
        .chunks(BATCH)
        .map(<[v1::Sample]>::to_vec)
        .collect();
    let dir = tempfile::tempdir().expect("temp dir");
    // Two servers on one database: the vehicle streams on the first, then goes on on the second,
    // while the first still holds its (now stale) copy of the session.
    let first = TestServer::start(test_config(dir.path())).await;
    let second = TestServer::start(test_config(dir.path())).await;
    let (first_clients, second_clients) = (Clients::of(&first).await, Clients::of(&second).await);
    stream_batches(&first_clients, (vehicle, ""), &batches[..10], 1).await;
    let (accepted, _) = stream_batches(&second_clients, (vehicle, ""), &batches[10..], 11).await;
    assert!(
        accepted.from_snapshot && accepted.last_seq == 10,
        "{accepted:?}"
    );
    drop((first_clients, second_clients));
    second.stop().await;

    // The first server shuts down holding the stale copy: the snapshot stored is still the second's.
    first.stop().await;
    let store = Store::open(&test_config(dir.path()).database)
        .await
        .expect("open the database");
    let stored = store
        .load_snapshot(vehicle)
        .await
        .expect("readable")
        .expect("stored");
    assert_eq!(
        stored.last_seq,
        batches.len() as i64,
        "written by {}",
        stored.writer
    );
    store.close().await;
}
