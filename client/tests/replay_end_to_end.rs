//! End to end: an in-process server (real `spoofwatch_server::serve` on 127.0.0.1:0, temporary
//! database) and the `detect` replay logic over gRPC.

use spoofwatch_client::Connection;
use spoofwatch_client::replay::{
    ReplayEvent, ReplayOptions, ReplaySummary, replay_timestamps, replay_tracks,
};
use spoofwatch_core::sample::Track;
use spoofwatch_core::scenario::{DriveSpec, simulate_drive};
use spoofwatch_server::inprocess::InProcessServer;
use tokio::sync::mpsc;

/// A short simulated recording with a recorded trajectory break in the middle (the clock restarts).
fn recording(vehicle_id: &str, seed: u64) -> Track {
    let spec = DriveSpec {
        duration_s: 59.0,
        rate_hz: 1.0,
        seed,
        ..DriveSpec::default()
    };
    let mut track = simulate_drive(&spec, vehicle_id).expect("valid drive spec");
    // Second half: the source restarts its clock, as at an AV-GPS date change.
    for record in &mut track.records[30..] {
        record.sample.timestamp_s -= 30.0;
    }
    track.records[30].trajectory_break = true;
    track
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_sample_gets_one_detection_in_order_and_breaks_start_trajectories() {
    let server = InProcessServer::start(|_| {}).await.expect("server starts");
    let connection = Connection::connect(server.url(), None)
        .await
        .expect("connects");
    let tracks = vec![recording("car-1", 1), recording("sim/car#2", 2)];
    let options = ReplayOptions {
        rate_hz: 0.0,
        batch_size: 7, // 60 samples: 8 full batches and one of 4
        model: String::new(),
        ..ReplayOptions::default()
    };
    let (events_tx, mut events) = mpsc::channel(64);
    let replay = {
        let connection = connection.clone();
        let tracks = tracks.clone();
        tokio::spawn(async move { replay_tracks(&connection, tracks, &options, events_tx).await })
    };
    let mut detections: Vec<Vec<_>> = vec![Vec::new(), Vec::new()];
    let mut accepted = 0;
    while let Some(event) = events.recv().await {
        match event {
            ReplayEvent::Accepted { accepted: a, .. } => {
                assert!(a.model.starts_with("models/"), "{a:?}");
                assert!(!a.resumed, "reset: true starts afresh");
                accepted += 1;
            }
            ReplayEvent::Detection(d) => {
                let vehicle = match d.vehicle_id.as_str() {
                    "car-1" => 0,
                    // `/` and `#` are not allowed in vehicle ids: the replay replaces them.
                    "sim_car_2" => 1,
                    other => panic!("unexpected vehicle {other}"),
                };
                detections[vehicle].push(d);
            }
            ReplayEvent::ItemError { status, .. } => panic!("rejected batch: {status:?}"),
            ReplayEvent::Failover { .. } => panic!("no server went away"),
        }
    }
    let summaries = replay.await.expect("replay task");
    assert_eq!(accepted, 2);

    for (track, received) in tracks.iter().zip(&detections) {
        assert_eq!(
            received.len(),
            track.records.len(),
            "one detection per sample"
        );
        let expected_times = replay_timestamps(&track.records);
        for (i, d) in received.iter().enumerate() {
            assert_eq!(d.index, i, "in order");
            assert_eq!(d.line, track.records[i].line);
            assert_eq!(d.recorded_timestamp_s, track.records[i].sample.timestamp_s);
            assert_eq!(d.detection.timestamp_s, expected_times[i]);
            assert!((0.0..=1.0).contains(&d.detection.probability));
        }
        // The recorded break became a gap: the server started trajectory 1 exactly at row 30.
        let trajectories: Vec<u32> = received
            .iter()
            .map(|d| d.detection.evidence.as_ref().expect("evidence").trajectory)
            .collect();
        assert!(
            trajectories[..30].iter().all(|&t| t == 0),
            "{trajectories:?}"
        );
        assert!(
            trajectories[30..].iter().all(|&t| t == 1),
            "{trajectories:?}"
        );
        // δ inside the second trajectory is the recorded 1 s.
        let evidence = received[31].detection.evidence.as_ref().expect("evidence");
        assert_eq!(evidence.delta_t_s, 1.0);
    }

    for summary in summaries {
        let summary = summary.expect("stream succeeded");
        assert_eq!(summary.samples_sent, 60);
        assert_eq!(summary.detections, 60);
        assert_eq!(summary.rejected_batches, 0);
        assert_eq!(summary.batch_latencies.len(), 9);
    }
    server.shutdown().await.expect("clean shutdown");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_bad_sample_is_an_item_error_and_the_stream_goes_on() {
    let server = InProcessServer::start(|_| {}).await.expect("server starts");
    let connection = Connection::connect(server.url(), None)
        .await
        .expect("connects");
    let mut track = recording("car-3", 3);
    track.records[4].sample.latitude_deg = 91.0;
    let options = ReplayOptions {
        rate_hz: 0.0,
        batch_size: 5,
        model: String::new(),
        ..ReplayOptions::default()
    };
    let (events_tx, mut events) = mpsc::channel(64);
    let replay = tokio::spawn({
        let connection = connection.clone();
        async move { replay_tracks(&connection, vec![track], &options, events_tx).await }
    });
    let mut item_errors = Vec::new();
    let mut detected = 0;
    while let Some(event) = events.recv().await {
        match event {
            ReplayEvent::ItemError {
                seq, lines, status, ..
            } => item_errors.push((seq, lines, status)),
            ReplayEvent::Detection(_) => detected += 1,
            ReplayEvent::Accepted { .. } => {}
            ReplayEvent::Failover { .. } => panic!("no server went away"),
        }
    }
    let summary = replay.await.expect("task").remove(0).expect("stream ok");
    assert_eq!(detected, 55, "the rejected batch of 5 gets no detections");
    assert_eq!(summary.rejected_batches, 1);
    assert_eq!(item_errors.len(), 1);
    let (seq, lines, status) = &item_errors[0];
    assert_eq!(*seq, 1);
    assert_eq!(*lines, (1, 5));
    let text = spoofwatch_client::error::describe_rpc_status(status);
    assert!(
        text.starts_with("INVALID_ARGUMENT") && text.contains("batch.samples[4].latitude_deg"),
        "{text}"
    );
    server.shutdown().await.expect("clean shutdown");
}

/// Replays `track` with `options` and returns its events and summary.
async fn replay_one(
    connection: &Connection,
    track: &Track,
    options: ReplayOptions,
) -> (Vec<ReplayEvent>, ReplaySummary) {
    let (events_tx, mut events) = mpsc::channel(64);
    let replay = tokio::spawn({
        let connection = connection.clone();
        let track = track.clone();
        async move { replay_tracks(&connection, vec![track], &options, events_tx).await }
    });
    let mut received = Vec::new();
    while let Some(event) = events.recv().await {
        received.push(event);
    }
    let summary = replay
        .await
        .expect("replay task")
        .remove(0)
        .expect("every stream succeeded");
    (received, summary)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_reconnecting_vehicle_resumes_its_session_and_gets_the_same_detections() {
    let server = InProcessServer::start(|_| {}).await.expect("server starts");
    let connection = Connection::connect(server.url(), None)
        .await
        .expect("connects");
    let spec = DriveSpec {
        duration_s: 299.0,
        rate_hz: 1.0,
        seed: 5,
        ..DriveSpec::default()
    };
    let track = simulate_drive(&spec, "car-5").expect("valid drive spec");
    let batched = ReplayOptions {
        batch_size: 7,
        ..ReplayOptions::default()
    };
    let (steady, _) = replay_one(&connection, &track, batched.clone()).await;
    let reconnecting = ReplayOptions {
        reconnect_every_s: 30.0,
        reconnect_seed: 3,
        ..batched
    };
    let (events, summary) = replay_one(&connection, &track, reconnecting).await;

    // 300 s with 15–45 s between reconnects.
    assert!(summary.streams >= 7, "{summary:?}");
    assert_eq!(summary.resumed_reconnects, summary.streams - 1);
    assert_eq!((summary.detections, summary.rejected_batches), (300, 0));
    let mut streams_accepted = Vec::new();
    let mut firsts = Vec::new();
    let mut detections = Vec::new();
    for event in events {
        match event {
            ReplayEvent::Accepted {
                stream, accepted, ..
            } => {
                assert_eq!(
                    accepted.resumed,
                    stream > 0,
                    "stream {stream}: {accepted:?}"
                );
                assert_eq!(accepted.samples_seen as usize, detections.len());
                streams_accepted.push(stream);
            }
            ReplayEvent::Detection(d) => {
                assert_eq!(
                    d.stream + 1,
                    streams_accepted.len() as u32,
                    "line {}",
                    d.line
                );
                if d.first_on_stream {
                    firsts.push(d.index);
                }
                detections.push(d);
            }
            ReplayEvent::ItemError { status, .. } => panic!("rejected batch: {status:?}"),
            ReplayEvent::Failover { .. } => panic!("no server went away"),
        }
    }
    assert_eq!(streams_accepted, (0..summary.streams).collect::<Vec<u32>>());
    assert_eq!(firsts.len(), summary.streams as usize);
    assert_eq!(firsts[0], 0);
    // A resumed session is the same detector: no new trajectory, identical verdicts.
    let steady: Vec<_> = steady
        .into_iter()
        .filter_map(|e| match e {
            ReplayEvent::Detection(d) => Some(d.detection),
            _ => None,
        })
        .collect();
    assert_eq!(steady.len(), detections.len());
    for (d, expected) in detections.iter().zip(&steady) {
        assert_eq!(
            d.detection.probability.to_bits(),
            expected.probability.to_bits(),
            "line {}",
            d.line
        );
        assert_eq!(d.detection.alarm, expected.alarm, "line {}", d.line);
        let trajectory = d.detection.evidence.as_ref().expect("evidence").trajectory;
        assert_eq!(trajectory, 0, "line {}", d.line);
    }
    server.shutdown().await.expect("clean shutdown");
}

#[tokio::test]
async fn connecting_to_a_closed_port_fails_with_the_url() {
    // Bind then drop, so the port is very likely closed.
    let port = std::net::TcpListener::bind("127.0.0.1:0")
        .and_then(|l| l.local_addr())
        .expect("ephemeral port")
        .port();
    let url = format!("http://127.0.0.1:{port}");
    let error = Connection::connect(url.clone(), None)
        .await
        .expect_err("nothing listens there");
    assert!(error.to_string().contains(&url), "{error}");
}
