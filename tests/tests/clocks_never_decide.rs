//! Servers' wall clocks never decide a vehicle's fate: a hand-off picks the copy of a session that
//! got further by the vehicle's own sample time and sequence numbers, whatever the replicas'
//! clocks wrote; a snapshot that looks a day old by the clock does not end the alarm of a vehicle
//! that is still streaming, while an abandoned vehicle's expired snapshot does end its alarm, at
//! its last alarming sample; and millisecond times sent as seconds are refused at a session's start.

use std::time::Duration;

use spoofwatch_core::scenario::AttackKind;
use spoofwatch_proto::v1;
use spoofwatch_server::store::{AlarmEvent, Store};
use spoofwatch_tests::{
    BatchOutcome, Clients, TestServer, alarms_of, attacked_drive, field_violations, normal_drive,
    open_stream, sessions_on, start_request, start_stream, test_config, track_samples,
};
use tonic::Code;

/// Moves the stored snapshot of `vehicle` to `updated_at_ms` by its writer's clock.
async fn restamp_snapshot(database: &str, vehicle: &str, updated_at_ms: impl Fn(i64) -> i64) {
    let store = Store::open(database).await.expect("open the database");
    let mut row = store
        .load_snapshot(vehicle)
        .await
        .expect("readable")
        .expect("a stored snapshot");
    row.updated_at_ms = updated_at_ms(row.updated_at_ms);
    store
        .write_alarms_and_snapshots::<AlarmEvent>(&[], &[row])
        .await
        .expect("written");
    store.close().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_hand_off_takes_the_copy_that_got_further_whatever_the_clocks_say() {
    let dir = tempfile::tempdir().expect("temp dir");
    let database = test_config(dir.path()).database;
    let a = TestServer::start(test_config(dir.path())).await;
    let b = TestServer::start(test_config(dir.path())).await;
    let (on_a, on_b) = (Clients::of(&a).await, Clients::of(&b).await);
    let samples = track_samples(&normal_drive("car", 100.0, 5));
    let batches: Vec<_> = samples.chunks(10).map(<[_]>::to_vec).collect();

    // A: batches 1-2; then B continues from A's snapshot with 3-5.
    let (mut stream, _) = start_stream(&on_a, "car", "").await;
    for seq in 1..=2 {
        stream
            .detect(seq, batches[seq as usize - 1].clone())
            .await
            .expect("scored");
    }
    stream.finish().await.expect("ended");
    let (mut stream, accepted) = start_stream(&on_b, "car", "").await;
    assert_eq!(accepted.last_seq, 2);
    for seq in 3..=5 {
        stream
            .detect(seq, batches[seq as usize - 1].clone())
            .await
            .expect("scored");
    }
    stream.finish().await.expect("ended");
    // B's clock runs an hour behind A's.
    restamp_snapshot(&database, "car", |t| t - 3_600_000).await;

    // Back on A, which still holds its own older copy in memory: B's copy got further.
    let (mut stream, accepted) = start_stream(&on_a, "car", "").await;
    assert_eq!(accepted.last_seq, 5, "{accepted:?}");
    assert!(accepted.from_snapshot, "{accepted:?}");
    stream.detect(6, batches[5].clone()).await.expect("scored");
    stream.finish().await.expect("ended");
    drop((on_a, on_b));
    a.stop().await;
    b.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_snapshot_that_looks_old_by_the_clock_does_not_end_a_streaming_vehicles_alarm() {
    let dir = tempfile::tempdir().expect("temp dir");
    let mut config = test_config(dir.path());
    // Expiry is looked for every second; a snapshot 10 s old by the clock is past the TTL.
    config.session_idle_secs = 4;
    config.snapshot_every_secs = 2;
    config.snapshot_ttl_secs = 10;
    let database = config.database.clone();
    let server = TestServer::start(config).await;
    let mut clients = Clients::of(&server).await;
    let track = attacked_drive("truck", 240.0, 21, AttackKind::FrozenPosition, 100.0, 60.0);
    let samples = track_samples(&track);
    let batches: Vec<_> = samples.chunks(20).map(<[_]>::to_vec).collect();
    let (mut stream, _) = start_stream(&clients, "truck", "").await;
    let mut seq = 0;
    let mut alarming = false;
    while !alarming {
        seq += 1;
        let detections = stream
            .detect(seq, batches[seq as usize - 1].clone())
            .await
            .expect("scored");
        alarming = detections.last().is_some_and(|d| d.alarm);
        assert!((seq as usize) < batches.len(), "the attack raised no alarm");
    }
    // As if this server's clock jumped 56 years ahead: its vehicle's snapshot looks ancient.
    restamp_snapshot(&database, "truck", |_| 0).await;
    tokio::time::sleep(Duration::from_secs(4)).await;
    let alarms = alarms_of(&mut clients, "truck").await;
    assert_eq!(alarms.len(), 1, "{alarms:?}");
    assert!(alarms[0].4, "the live alarm was ended: {alarms:?}");
    // The vehicle goes on; its alarm ends once, at a sample time of its own.
    for next in seq + 1..=batches.len() as u64 {
        stream
            .detect(next, batches[next as usize - 1].clone())
            .await
            .expect("scored");
    }
    stream.finish().await.expect("ended");
    let deadline = tokio::time::Instant::now() + Duration::from_secs(30);
    loop {
        let alarms = alarms_of(&mut clients, "truck").await;
        if !alarms[0].4 {
            assert_eq!(alarms.len(), 1, "{alarms:?}");
            assert!(alarms[0].1.is_some_and(|end| end <= 240.0), "{alarms:?}");
            break;
        }
        assert!(
            tokio::time::Instant::now() < deadline,
            "the alarm never ended: {alarms:?}"
        );
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
    drop(clients);
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_abandoned_vehicles_alarm_ends_at_its_last_alarming_sample_when_its_snapshot_expires() {
    let dir = tempfile::tempdir().expect("temp dir");
    let mut config = test_config(dir.path());
    config.session_idle_secs = 2;
    config.snapshot_every_secs = 1;
    config.snapshot_ttl_secs = 10;
    let database = config.database.clone();
    let server = TestServer::start(config).await;
    let mut clients = Clients::of(&server).await;
    let track = attacked_drive("lorry", 240.0, 23, AttackKind::FrozenPosition, 100.0, 60.0);
    let samples = track_samples(&track);
    let (mut stream, _) = start_stream(&clients, "lorry", "").await;
    let mut last_alarming = None;
    for (seq, batch) in samples.chunks(20).enumerate() {
        let detections = stream
            .detect(seq as u64 + 1, batch.to_vec())
            .await
            .expect("scored");
        if let Some(last) = detections.iter().rev().find(|d| d.alarm) {
            last_alarming = Some(last.timestamp_s);
        }
        // The vehicle goes away in the middle of its alarm.
        if detections.last().is_some_and(|d| d.alarm) {
            break;
        }
    }
    let last_alarming = last_alarming.expect("the frozen fix raised an alarm");
    stream.finish().await.expect("ended");
    // Evicted once idle, its session leaves its snapshot, which then looks old by the clock.
    let deadline = tokio::time::Instant::now() + Duration::from_secs(30);
    while !sessions_on(&clients).await.is_empty() {
        assert!(tokio::time::Instant::now() < deadline, "never evicted");
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    restamp_snapshot(&database, "lorry", |_| 0).await;
    loop {
        let alarms = alarms_of(&mut clients, "lorry").await;
        assert_eq!(alarms.len(), 1, "{alarms:?}");
        if !alarms[0].4 {
            assert_eq!(alarms[0].1, Some(last_alarming), "{alarms:?}");
            break;
        }
        assert!(
            tokio::time::Instant::now() < deadline,
            "the abandoned alarm never ended: {alarms:?}"
        );
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
    let store = Store::open(&database).await.expect("open the database");
    assert_eq!(store.load_snapshot("lorry").await.expect("readable"), None);
    store.close().await;
    drop(clients);
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn milliseconds_sent_as_seconds_are_refused_at_a_session_start() {
    let dir = tempfile::tempdir().expect("temp dir");
    let server = TestServer::start(test_config(dir.path())).await;
    let clients = Clients::of(&server).await;
    let samples = track_samples(&normal_drive("van", 30.0, 6));
    let in_milliseconds = |offset: f64| -> Vec<v1::Sample> {
        samples
            .iter()
            .map(|s| v1::Sample {
                timestamp_s: offset + s.timestamp_s * 1000.0,
                ..*s
            })
            .collect()
    };
    for (vehicle, batch) in [
        ("van-epoch", in_milliseconds(1.7e12)),
        ("van-relative", in_milliseconds(0.0)),
    ] {
        let mut stream = open_stream(&clients, start_request(vehicle, "", false))
            .await
            .expect("the call is accepted");
        stream.accepted().await.expect("accepted");
        stream
            .send_batch(1, batch[..10].to_vec())
            .await
            .expect("sent");
        let reply = stream.recv().await.expect("a reply");
        let BatchOutcome::Rejected(status) = reply.outcome else {
            panic!("{vehicle}: milliseconds were accepted");
        };
        assert_eq!(Code::from(status.code), Code::InvalidArgument);
        let violations = field_violations(&status);
        assert!(
            violations[0].1.contains("looks like milliseconds"),
            "{violations:?}"
        );
        // The same samples in seconds are accepted on the same session.
        let seconds = samples[..10].to_vec();
        stream.detect(2, seconds).await.expect("seconds are scored");
    }
    drop(clients);
    server.stop().await;
}
