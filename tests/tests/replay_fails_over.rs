//! A replay survives its server going away: the server is stopped mid-stream and restarted on the
//! same port (its in-memory sessions lost), the replay reconnects within its failover deadline,
//! finds no session to resume and resends the whole recording on a fresh one; its final rows
//! (`ReplayLog`) equal an uninterrupted replay's bit for bit, one detection per recorded row.

use spoofwatch_client::replay::{ReplayEvent, ReplayOptions, ReplaySummary, replay_tracks};
use spoofwatch_client::replay_log::ReplayLog;
use spoofwatch_core::sample::Track;
use spoofwatch_core::scenario::AttackKind;
use spoofwatch_tests::{Connection, TestServer, attacked_drive, test_config};
use tokio::sync::{mpsc, oneshot};

/// Replays `track` over `connection`; calls `on_row` with each detection's record index as it
/// arrives. Returns the final rows and the summary.
async fn replay(
    connection: &Connection,
    track: &Track,
    options: &ReplayOptions,
    mut on_row: impl FnMut(usize),
) -> (ReplayLog, ReplaySummary) {
    let (events_tx, mut events) = mpsc::channel(64);
    let task = tokio::spawn({
        let (connection, track, options) = (connection.clone(), track.clone(), options.clone());
        async move { replay_tracks(&connection, vec![track], &options, events_tx).await }
    });
    let mut log = ReplayLog::default();
    while let Some(event) = events.recv().await {
        if let ReplayEvent::Detection(d) = &event {
            on_row(d.index);
        }
        log.record(event);
    }
    let summary = task
        .await
        .expect("the replay task")
        .remove(0)
        .expect("the replay succeeds");
    (log, summary)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_replay_through_a_server_restart_matches_an_uninterrupted_one() {
    let dir = tempfile::tempdir().expect("temp dir");
    let server = TestServer::start(test_config(dir.path())).await;
    let port = server.addr.port();
    let connection = Connection::connect(server.url(), None)
        .await
        .expect("connect");
    // 400 s at 1 Hz with a ramp attack, so alarms (and their state) are part of what must match.
    let ramp = AttackKind::RampDrift { velocity_mps: 2.0 };
    let track = attacked_drive("car-9", 400.0, 31, ramp, 150.0, 120.0);
    let fast = ReplayOptions {
        batch_size: 5,
        ..ReplayOptions::default()
    };
    let (uninterrupted, _) = replay(&connection, &track, &fast, |_| {}).await;

    // Paced at 100 samples/s so the stop lands mid-stream; the stop and restart run beside the
    // replay, which must not wait for them.
    let paced = ReplayOptions {
        rate_hz: 100.0,
        ..fast
    };
    let (stop_now, stop_requested) = oneshot::channel::<()>();
    let restarter = tokio::spawn(async move {
        if stop_requested.await.is_ok() {
            server.stop().await;
            let config = test_config(dir.path());
            let restarted = TestServer::start_on_port(config, port).await;
            Some((restarted, dir))
        } else {
            None
        }
    });
    let mut stop_now = Some(stop_now);
    let (failed_over, summary) = replay(&connection, &track, &paced, |index| {
        if index >= 50
            && let Some(stop) = stop_now.take()
        {
            let _ = stop.send(());
        }
    })
    .await;
    let (restarted, _dir) = restarter
        .await
        .expect("the restart task")
        .expect("the server was stopped mid-stream");

    assert!(summary.failovers >= 1, "{summary:?}");
    let failovers: Vec<(bool, usize)> = failed_over
        .vehicles()
        .flat_map(|(_, events)| events.iter())
        .filter_map(|e| match e {
            ReplayEvent::Failover {
                accepted,
                resend_from,
                ..
            } => Some((accepted.resumed, *resend_from)),
            _ => None,
        })
        .collect();
    assert!(!failovers.is_empty(), "a Failover event was sent");
    // The restarted server kept no session in memory: the replay started over.
    if let Some(&(resumed, resend_from)) = failovers.last()
        && !resumed
    {
        assert_eq!(resend_from, 0);
    }
    assert_eq!(summary.detections, track.records.len() as u64);

    let expected: Vec<_> = uninterrupted.detections("car-9").collect();
    let got: Vec<_> = failed_over.detections("car-9").collect();
    assert_eq!(got.len(), track.records.len(), "one detection per row");
    assert!(
        expected.iter().any(|d| d.detection.alarm_onset),
        "the attack raises an alarm"
    );
    for (row, (g, e)) in got.iter().zip(&expected).enumerate() {
        assert_eq!(g.index, row, "in order");
        assert_eq!(
            g.detection.probability.to_bits(),
            e.detection.probability.to_bits(),
            "row {row}"
        );
        assert_eq!(
            (
                g.detection.alarm,
                g.detection.alarm_onset,
                g.detection.alarm_end
            ),
            (
                e.detection.alarm,
                e.detection.alarm_onset,
                e.detection.alarm_end
            ),
            "row {row}"
        );
    }
    drop(connection);
    restarted.stop().await;
}
