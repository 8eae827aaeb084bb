//! Nothing one client does starves the others of sessions or streams: each identity has a quota of
//! sessions; a full table makes room by evicting the session idle longest without a stream (it
//! resumes from its snapshot) before it refuses a new vehicle; a connection may hold only so many
//! streams at once; and a stream whose client stops reading its replies is ended.

use std::time::Duration;

use spoofwatch_proto::v1;
use spoofwatch_proto::v1::alarm_service_client::AlarmServiceClient;
use spoofwatch_proto::v1::detection_service_client::DetectionServiceClient;
use spoofwatch_tests::{
    Clients, ConnectOptions, Connection, TestServer, normal_drive, start_server, test_config,
    token_sha256, track_samples,
};
use tonic::Code;

async fn detect(connection: &Connection, vehicle: &str) -> Result<(), tonic::Status> {
    connection
        .detection()
        .detect(v1::DetectRequest {
            vehicle_id: vehicle.into(),
            samples: track_samples(&normal_drive(vehicle, 3.0, 1)),
            ..Default::default()
        })
        .await
        .map(drop)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn one_identity_cannot_take_more_than_its_quota_of_sessions() {
    let dir = tempfile::tempdir().expect("temp dir");
    let roles = dir.path().join("roles.toml");
    std::fs::write(
        &roles,
        format!(
            "[tokens]\n\"{}\" = {{ name = \"flood\", role = \"gateway\", all_vehicles = true }}\n\
             \"{}\" = {{ name = \"fleet\", role = \"gateway\", all_vehicles = true }}\n",
            token_sha256("flood-token"),
            token_sha256("fleet-token")
        ),
    )
    .expect("written");
    let mut config = test_config(dir.path());
    config.roles_file = Some(roles);
    config.auth_token = Some("admin".into());
    config.max_sessions_per_identity = 3;
    let server =
        TestServer::start_for(config, &ConnectOptions::with_token(Some("admin".into()))).await;
    let url = server.url();
    let connect = |token: &'static str| {
        let url = url.clone();
        async move {
            Connection::connect_with(&url, &ConnectOptions::with_token(Some(token.into())))
                .await
                .expect("connected")
        }
    };
    let flood = connect("flood-token").await;
    let fleet = connect("fleet-token").await;
    for i in 0..3 {
        detect(&flood, &format!("f-{i}"))
            .await
            .expect("within the quota");
    }
    let refused = detect(&flood, "f-3").await.expect_err("over the quota");
    assert_eq!(refused.code(), Code::ResourceExhausted);
    assert!(
        refused.message().contains("flood holds its quota of 3"),
        "{}",
        refused.message()
    );
    // A vehicle it already holds goes on; another identity is unaffected.
    detect(&flood, "f-0")
        .await
        .expect_err("its times went backwards, not a quota refusal");
    detect(&fleet, "v-1")
        .await
        .expect("another identity has its own quota");
    drop((flood, fleet));
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_full_table_evicts_the_session_idle_longest_before_refusing() {
    let (_dir, server, clients) = start_server(|config| config.max_sessions = 3).await;
    for vehicle in ["oldest", "middle", "newest"] {
        detect(&clients.connection, vehicle)
            .await
            .expect("admitted");
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    detect(&clients.connection, "arrival")
        .await
        .expect("room was made");
    let mut detection = clients.detection.clone();
    let gone = detection
        .get_session(v1::GetSessionRequest {
            vehicle_id: "oldest".into(),
        })
        .await
        .expect_err("the session idle longest left memory");
    assert_eq!(gone.code(), Code::NotFound);
    // It continues from its snapshot when it comes back.
    let (_stream, accepted) = spoofwatch_tests::start_stream(&clients, "oldest", "").await;
    assert!(accepted.from_snapshot, "{accepted:?}");
    let sent = track_samples(&normal_drive("oldest", 3.0, 1)).len() as u64;
    assert_eq!(accepted.samples_seen, sent);
    drop(clients);
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_stream_whose_client_stops_reading_is_ended() {
    let (_dir, server, clients) = start_server(|config| config.stream_idle_secs = 2).await;
    let samples = track_samples(&normal_drive("reader", 2000.0, 2));
    let (tx, rx) = tokio::sync::mpsc::channel(4);
    tx.send(spoofwatch_tests::start_request("reader", "", false))
        .await
        .expect("queued");
    let replies = DetectionServiceClient::new(stingy_channel(&server).await)
        .stream_detect(tokio_stream::wrappers::ReceiverStream::new(rx))
        .await
        .expect("the call is accepted")
        .into_inner();
    // Send, never read: the replies fill the tiny window and the server's buffer.
    let sender = tokio::spawn(async move {
        for (seq, batch) in (1..).zip(samples.chunks(20)) {
            let request = spoofwatch_tests::batch_request(seq, batch.to_vec());
            if tx.send(request).await.is_err() {
                break;
            }
        }
    });
    let mut detection = clients.detection.clone();
    let deadline = tokio::time::Instant::now() + Duration::from_secs(60);
    loop {
        let session = detection
            .get_session(v1::GetSessionRequest {
                vehicle_id: "reader".into(),
            })
            .await
            .map(tonic::Response::into_inner);
        if session
            .as_ref()
            .is_ok_and(|s| s.samples > 0 && !s.connected)
        {
            break;
        }
        assert!(
            tokio::time::Instant::now() < deadline,
            "the stream of a client that stopped reading was never ended: {session:?}"
        );
        tokio::time::sleep(Duration::from_millis(250)).await;
    }
    sender.abort();
    drop(replies);
    drop(clients);
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_connection_holds_at_most_its_limit_of_streams() {
    let (_dir, server, clients) =
        start_server(|config| config.max_streams_per_connection = 2).await;
    let watch = || {
        let mut alarms = clients.alarms.clone();
        async move { alarms.watch_alarms(v1::WatchAlarmsRequest::default()).await }
    };
    let first = watch().await.expect("a stream").into_inner();
    let _second = watch().await.expect("a stream").into_inner();
    let third = tokio::spawn(watch());
    tokio::time::sleep(Duration::from_secs(1)).await;
    assert!(
        !third.is_finished(),
        "a third stream opened on a connection limited to two"
    );
    drop(first);
    let third = tokio::time::timeout(Duration::from_secs(30), third)
        .await
        .expect("the third stream opens once one closes")
        .expect("joined");
    third.expect("a stream");
    drop(clients);
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_watcher_that_stops_reading_is_let_go() {
    let (_dir, server, clients) = start_server(|config| config.stream_idle_secs = 2).await;
    // Far more events than the call's reply buffer holds: each drive stores an onset and an end.
    let vehicles: Vec<String> = (0..60).map(|i| format!("watched-{i}")).collect();
    let mut drives = tokio::task::JoinSet::new();
    for vehicle in vehicles {
        let clients = clients.clone();
        drives.spawn(
            async move { spoofwatch_tests::stream_frozen_fix_drive(&clients, &vehicle).await },
        );
    }
    while let Some(episodes) = drives.join_next().await {
        assert_eq!(
            episodes.expect("joined").len(),
            1,
            "each drive raises one alarm"
        );
    }
    let stored = stored_events(&clients).await;
    assert!(stored >= 100, "only {stored} events stored");

    // Not one whole event reaches the client until it reads.
    let mut stalled = AlarmServiceClient::new(stingy_channel(&server).await)
        .watch_alarms(v1::WatchAlarmsRequest {
            after_cursor: Some(0),
            ..Default::default()
        })
        .await
        .expect("the watch is accepted")
        .into_inner();
    // Six times the limit: on a machine whose cores are busy elsewhere the server's timer fires
    // late, and the test must not read before it has.
    tokio::time::sleep(Duration::from_secs(12)).await;

    // It reads at last: what was buffered on the way arrives, then the stream ends; a watcher
    // still held would go on to CAUGHT_UP and wait for more.
    let mut delivered = 0;
    let end = tokio::time::timeout(Duration::from_secs(30), async {
        loop {
            match stalled.message().await {
                Ok(Some(event)) => {
                    assert_ne!(
                        event.kind,
                        v1::AlarmEventKind::CaughtUp as i32,
                        "the watcher was held until it caught up ({delivered} of {stored} events read)"
                    );
                    delivered += 1;
                }
                Ok(None) => return Ok(()),
                Err(status) => return Err(status),
            }
        }
    })
    .await
    .expect("the stream of a watcher that stopped reading ends");
    if let Err(status) = end {
        assert_eq!(status.code(), Code::DeadlineExceeded, "{status:?}");
    }
    drop(clients);
    server.stop().await;
}

/// A connection whose client grants each stream a window of 64 bytes: the server can send a
/// stream hardly anything until the client reads.
async fn stingy_channel(server: &TestServer) -> tonic::transport::Channel {
    tonic::transport::Channel::from_shared(server.url())
        .expect("a valid URI")
        .initial_stream_window_size(64)
        .connect()
        .await
        .expect("connect")
}

/// How many alarm events the log holds: a watch from the start that stops when caught up.
async fn stored_events(clients: &Clients) -> usize {
    let mut watch = clients
        .alarms
        .clone()
        .watch_alarms(v1::WatchAlarmsRequest {
            after_cursor: Some(0),
            stop_when_caught_up: true,
            ..Default::default()
        })
        .await
        .expect("a history watch")
        .into_inner();
    let mut events = 0;
    while let Some(event) = watch.message().await.expect("the history") {
        if event.kind != v1::AlarmEventKind::CaughtUp as i32 {
            events += 1;
        }
    }
    events
}
