//! A replay survives its server going away: the server is stopped mid-stream and restarted on the
//! same port (its in-memory sessions lost), the replay reconnects within its failover deadline,
//! finds no session to resume and resends the whole recording on a fresh one; its final rows
//! (`ReplayLog`) equal an uninterrupted replay's bit for bit, one detection per recorded row. Through
//! a roll-out (a new model activated before the restart) the replay goes on under the new model with
//! the rows not yet answered instead of resending the drive. Without failover, a replay whose server
//! drains reports the status its stream ended with (UNAVAILABLE).

use spoofwatch_client::replay::{ReplayEvent, ReplayOptions, ReplaySummary, replay_tracks};
use spoofwatch_client::replay_log::ReplayLog;
use spoofwatch_core::sample::Track;
use spoofwatch_core::scenario::AttackKind;
use spoofwatch_proto::v1;
use spoofwatch_tests::{
    Clients, Connection, TestServer, attacked_drive, code_of, export_model, import_model,
    test_config,
};
use tokio::sync::{mpsc, oneshot};
use tonic::Code;

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

/// Samples per batch.
const BATCH: usize = 5;

/// 400 s at 1 Hz with a 2 m/s ramp from 150 s for 120 s, so that alarms (and their state) are part
/// of what must match.
fn ramp_drive(vehicle: &str, seed: u64) -> Track {
    let ramp = AttackKind::RampDrift { velocity_mps: 2.0 };
    attacked_drive(vehicle, 400.0, seed, ramp, 150.0, 120.0)
}

/// The final rows of `track` replayed as fast as the server answers, without interruption.
async fn replay_uninterrupted(connection: &Connection, track: &Track) -> ReplayLog {
    let fast = ReplayOptions {
        batch_size: BATCH,
        ..ReplayOptions::default()
    };
    replay(connection, track, &fast, |_| {}).await.0
}

/// Replays `track` paced at 100 samples/s; once row 50 is answered, `before_restart` runs, then the
/// server is stopped and restarted on its port and database. Returns the final rows, the summary
/// and the restarted server.
async fn replay_through_a_restart<F>(
    server: TestServer,
    dir: tempfile::TempDir,
    connection: &Connection,
    track: &Track,
    before_restart: F,
) -> (ReplayLog, ReplaySummary, TestServer, tempfile::TempDir)
where
    F: std::future::Future<Output = ()> + Send + 'static,
{
    let paced = ReplayOptions {
        rate_hz: 100.0,
        batch_size: BATCH,
        ..ReplayOptions::default()
    };
    let port = server.addr.port();
    // The stop and restart run beside the replay, which must not wait for them.
    let (stop_now, stop_requested) = oneshot::channel::<()>();
    let restarter = tokio::spawn(async move {
        if stop_requested.await.is_ok() {
            before_restart.await;
            server.stop().await;
            let restarted = TestServer::start_on_port(test_config(dir.path()), port).await;
            Some((restarted, dir))
        } else {
            None
        }
    });
    let mut stop_now = Some(stop_now);
    let (log, summary) = replay(connection, track, &paced, |index| {
        if index >= 50
            && let Some(stop) = stop_now.take()
        {
            let _ = stop.send(());
        }
    })
    .await;
    let (restarted, dir) = restarter
        .await
        .expect("the restart task")
        .expect("the server was stopped mid-stream");
    (log, summary, restarted, dir)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_replay_through_a_roll_out_goes_on_under_the_new_model_without_resending() {
    let dir = tempfile::tempdir().expect("temp dir");
    let server = TestServer::start(test_config(dir.path())).await;
    let connection = server.connection(None).await;
    let mut clients = Clients::new(connection.clone());
    let artifact = export_model(&mut clients.models, "models/default").await;
    let candidate = import_model(&mut clients, artifact, "candidate").await.name;
    let track = ramp_drive("car-7", 32);
    let uninterrupted = replay_uninterrupted(&connection, &track).await;

    // The new model is activated while the vehicle streams: its open stream keeps the old model
    // until the restart ends it; the session that comes back starts afresh under the new one.
    let activate = {
        let (mut models, candidate) = (clients.models.clone(), candidate.clone());
        async move {
            models
                .set_active_model(v1::SetActiveModelRequest { name: candidate })
                .await
                .expect("the candidate activates");
        }
    };
    let (rolled, summary, restarted, _dir) =
        replay_through_a_restart(server, dir, &connection, &track, activate).await;

    let failovers: Vec<(String, usize)> = rolled
        .vehicles()
        .flat_map(|(_, events)| events.iter())
        .filter_map(|e| match e {
            ReplayEvent::Failover {
                accepted,
                resend_from,
                ..
            } => Some((accepted.replaced_model.clone(), *resend_from)),
            _ => None,
        })
        .collect();
    let (replaced, resend_from) = failovers.last().cloned().expect("a failover");
    assert_eq!(replaced, "models/default", "{failovers:?}");
    assert!(
        resend_from >= 50,
        "went on, not from the start: {failovers:?}"
    );
    assert_eq!(summary.detections, track.records.len() as u64);

    let expected: Vec<_> = uninterrupted.detections("car-7").collect();
    let got: Vec<_> = rolled.detections("car-7").collect();
    assert_eq!(got.len(), track.records.len(), "one detection per row");
    let switch = got
        .iter()
        .position(|d| *d.model == *candidate)
        .expect("rows under the new model");
    assert!(
        switch >= 50 && switch <= resend_from,
        "switch at row {switch}"
    );
    assert!(got[switch..].iter().all(|d| *d.model == *candidate));
    // Before the switch: the old model's detections, bit for bit.
    for (row, (g, e)) in got[..switch].iter().zip(&expected).enumerate() {
        assert_eq!((g.index, &*g.model), (row, "models/default"));
        assert_eq!(
            g.detection.probability.to_bits(),
            e.detection.probability.to_bits(),
            "row {row}"
        );
    }
    drop(connection);
    restarted.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_replay_through_a_server_restart_matches_an_uninterrupted_one() {
    let dir = tempfile::tempdir().expect("temp dir");
    let server = TestServer::start(test_config(dir.path())).await;
    let connection = Connection::connect(server.url(), None)
        .await
        .expect("connect");
    let track = ramp_drive("car-9", 31);
    let uninterrupted = replay_uninterrupted(&connection, &track).await;
    let (failed_over, summary, restarted, _dir) =
        replay_through_a_restart(server, dir, &connection, &track, std::future::ready(())).await;

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

/// A paced replay without failover, its server draining between two batches: the stream, ended by
/// the drain while nothing was in flight, is found closed by the next batch; the replay reports the
/// status the server ended it with (UNAVAILABLE: retry elsewhere), not merely that it closed.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_replay_without_failover_reports_the_drains_unavailable() {
    let dir = tempfile::tempdir().expect("temp dir");
    let mut server = TestServer::start(test_config(dir.path())).await;
    let connection = Connection::connect(server.url(), None)
        .await
        .expect("connect");
    let track = ramp_drive("car-10", 32);
    // One sample a second, one per batch: between two batches nothing is in flight.
    let paced = ReplayOptions {
        rate_hz: 1.0,
        batch_size: 1,
        failover_s: 0.0,
        ..ReplayOptions::default()
    };
    let (events_tx, mut events) = mpsc::channel(64);
    let task = tokio::spawn({
        let (connection, track) = (connection.clone(), track.clone());
        async move { replay_tracks(&connection, vec![track], &paced, events_tx).await }
    });
    loop {
        match events.recv().await {
            Some(ReplayEvent::Detection(_)) => break,
            Some(_) => continue,
            None => panic!("the replay ended before its first detection"),
        }
    }
    server.trigger_shutdown();
    while events.recv().await.is_some() {}
    let error = task
        .await
        .expect("the replay task")
        .remove(0)
        .expect_err("the drain ends the replay");
    assert_eq!(code_of(&error), Code::Unavailable, "{error}");
    drop(connection);
    server.stop().await;
}
