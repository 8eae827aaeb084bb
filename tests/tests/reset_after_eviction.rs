//! ResetSession reaches a vehicle whose session is no longer in memory, black-box. A vehicle that
//! goes away in the middle of its alarm has its session evicted once idle; its snapshot, holding
//! the open alarm, stays stored until it expires. An admin's ResetSession then deletes the snapshot
//! and ends the alarm at its last alarming sample (as expiry would), answering OK, on the server
//! that evicted it and on one that never held it; the vehicle's next stream starts afresh. A
//! vehicle neither memory nor the store knows is NOT_FOUND, and so is one already reset.

use std::time::Duration;

use spoofwatch_core::scenario::AttackKind;
use spoofwatch_proto::v1;
use spoofwatch_tests::{
    Clients, TestServer, alarms_of, attacked_drive, sessions_on, start_stream, test_config,
    track_samples,
};
use tonic::Code;

/// Streams `vehicle`'s frozen-fix drive until it alarms, then goes away: the time of its last
/// alarming sample.
async fn alarm_and_leave(clients: &Clients, vehicle: &str, seed: u64) -> f64 {
    let track = attacked_drive(
        vehicle,
        240.0,
        seed,
        AttackKind::FrozenPosition,
        100.0,
        60.0,
    );
    let samples = track_samples(&track);
    let (mut stream, _) = start_stream(clients, vehicle, "").await;
    let mut last_alarming = None;
    for (seq, batch) in samples.chunks(20).enumerate() {
        let detections = stream
            .detect(seq as u64 + 1, batch.to_vec())
            .await
            .expect("scored");
        if let Some(last) = detections.iter().rev().find(|d| d.alarm) {
            last_alarming = Some(last.timestamp_s);
        }
        if detections.last().is_some_and(|d| d.alarm) {
            break;
        }
    }
    stream.finish().await.expect("ended");
    last_alarming.unwrap_or_else(|| panic!("{vehicle}: the frozen fix raised no alarm"))
}

async fn reset(clients: &Clients, vehicle: &str) -> Result<v1::Session, tonic::Status> {
    clients
        .detection
        .clone()
        .reset_session(v1::ResetSessionRequest {
            vehicle_id: vehicle.to_string(),
        })
        .await
        .map(tonic::Response::into_inner)
}

/// Asserts that `vehicle`'s one alarm ends at `last_alarming` (its end is stored by the server's
/// writer soon after the reset answers).
async fn ended_at(clients: &mut Clients, vehicle: &str, last_alarming: f64) {
    let deadline = tokio::time::Instant::now() + Duration::from_secs(30);
    loop {
        let alarms = alarms_of(clients, vehicle).await;
        assert_eq!(alarms.len(), 1, "{vehicle}: {alarms:?}");
        if !alarms[0].4 {
            assert_eq!(alarms[0].1, Some(last_alarming), "{vehicle}: {alarms:?}");
            return;
        }
        assert!(
            tokio::time::Instant::now() < deadline,
            "{vehicle}: the alarm is still open: {alarms:?}"
        );
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_evicted_vehicle_is_reset_from_its_stored_snapshot() {
    let dir = tempfile::tempdir().expect("temp dir");
    let mut config = test_config(dir.path());
    // Evicted after 2 s idle; snapshots expire only after an hour, so expiry ends nothing here.
    config.session_idle_secs = 2;
    config.snapshot_every_secs = 1;
    config.snapshot_ttl_secs = 3_600;
    let server = TestServer::start(config.clone()).await;
    let mut clients = Clients::of(&server).await;
    let lorry_last = alarm_and_leave(&clients, "lorry", 23).await;
    let van_last = alarm_and_leave(&clients, "van", 24).await;
    let deadline = tokio::time::Instant::now() + Duration::from_secs(30);
    while !sessions_on(&clients).await.is_empty() {
        assert!(tokio::time::Instant::now() < deadline, "never evicted");
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    for vehicle in ["lorry", "van"] {
        let alarms = alarms_of(&mut clients, vehicle).await;
        assert!(alarms.len() == 1 && alarms[0].4, "{vehicle}: {alarms:?}");
    }

    // On the server that evicted it.
    let session = reset(&clients, "lorry")
        .await
        .expect("the evicted vehicle is reset");
    assert_eq!(
        (
            session.vehicle_id.as_str(),
            session.samples,
            session.alarm_active,
            session.connected
        ),
        ("lorry", 0, false, false),
        "{session:?}"
    );
    assert_eq!(session.model, "models/default", "{session:?}");
    ended_at(&mut clients, "lorry", lorry_last).await;
    // Its snapshot is gone: a second reset finds nothing, and its next stream starts afresh.
    let again = reset(&clients, "lorry").await.expect_err("nothing left");
    assert_eq!(again.code(), Code::NotFound, "{again:?}");
    let (stream, accepted) = start_stream(&clients, "lorry", "").await;
    assert!(
        !accepted.resumed && !accepted.from_snapshot && accepted.samples_seen == 0,
        "{accepted:?}"
    );
    drop(stream);

    // On a server that never held it (another replica on the same database).
    let other = TestServer::start(config).await;
    let mut on_other = Clients::of(&other).await;
    reset(&on_other, "van")
        .await
        .expect("a vehicle only the store knows is reset");
    ended_at(&mut on_other, "van", van_last).await;

    let unknown = reset(&on_other, "never-seen").await.expect_err("unknown");
    assert_eq!(unknown.code(), Code::NotFound, "{unknown:?}");
    drop((clients, on_other));
    other.stop().await;
    server.stop().await;
}
