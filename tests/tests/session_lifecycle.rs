//! Session lifecycle: a second stream for a vehicle takes the session over (the older ends
//! ABORTED, the newer resumes), `reset` starts afresh, the session limit refuses new vehicles
//! with RESOURCE_EXHAUSTED, idle stream-less sessions are evicted, and sessions are listed in pages.

use spoofwatch_proto::v1;
use spoofwatch_tests::{
    Clients, code_of, final_code, normal_drive, open_stream, start_request, start_server,
    start_stream, track_samples,
};
use tonic::Code;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_second_stream_takes_the_session_over_and_resumes_it() {
    let (_dir, server, mut clients) = start_server(|_| {}).await;
    let samples = track_samples(&normal_drive("truck-7", 39.0, 8));

    let (mut older, accepted) = start_stream(&clients, "truck-7", "").await;
    assert!(!accepted.resumed);
    older
        .detect(1, samples[..10].to_vec())
        .await
        .expect("one detection per sample, for this batch");
    older
        .detect(2, samples[10..15].to_vec())
        .await
        .expect("one detection per sample, for this batch");

    // A second connection, as a reconnecting vehicle would have.
    let other = Clients::of(&server).await;
    let (mut newer, accepted) = start_stream(&other, "truck-7", "").await;
    assert_eq!(
        (accepted.resumed, accepted.samples_seen, accepted.last_seq),
        (true, 15, 2),
        "{accepted:?}"
    );
    assert_eq!(accepted.model, "models/default");
    assert_eq!(final_code(&mut older).await, Code::Aborted);

    // The newer stream continues the same trajectory where the older one stopped.
    let detections = newer
        .detect(3, samples[15..25].to_vec())
        .await
        .expect("one detection per sample, for this batch");
    let evidence = detections[0].evidence.as_ref().expect("evidence");
    assert_eq!(evidence.trajectory, 0);
    assert!((evidence.delta_t_s - 1.0).abs() < 1e-12);
    let session = clients
        .detection
        .get_session(v1::GetSessionRequest {
            vehicle_id: "truck-7".into(),
        })
        .await
        .expect("the session exists")
        .into_inner();
    assert_eq!(
        (session.samples, session.last_seq, session.connected),
        (25, 3, true)
    );

    // reset = true starts afresh even though a session exists.
    drop(newer);
    let mut fresh = open_stream(&other, start_request("truck-7", "", true))
        .await
        .expect("the call is accepted");
    match fresh.next().await {
        Ok(Some(v1::stream_detect_response::Kind::Accepted(a))) => {
            assert_eq!((a.resumed, a.samples_seen), (false, 0), "{a:?}");
        }
        other => panic!("expected SessionAccepted, got {other:?}"),
    }
    drop((fresh, clients, other));
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn beyond_the_session_limit_new_vehicles_are_refused() {
    let (_dir, server, mut clients) = start_server(|config| config.max_sessions = 2).await;
    let samples = track_samples(&normal_drive("fleet", 4.0, 2));

    let (mut first, _) = start_stream(&clients, "car-1", "").await;
    let (mut second, _) = start_stream(&clients, "car-2", "").await;
    first
        .detect(1, samples.clone())
        .await
        .expect("one detection per sample, for this batch");
    second
        .detect(1, samples.clone())
        .await
        .expect("one detection per sample, for this batch");

    let refused = open_stream(&clients, start_request("car-3", "", false)).await;
    let code = match refused {
        Ok(mut stream) => final_code(&mut stream).await,
        Err(error) => code_of(&error),
    };
    assert_eq!(code, Code::ResourceExhausted);
    let status = clients
        .detection
        .detect(v1::DetectRequest {
            vehicle_id: "car-3".into(),
            samples: samples.clone(),
            ..v1::DetectRequest::default()
        })
        .await
        .expect_err("no room for a third vehicle");
    assert_eq!(status.code(), Code::ResourceExhausted);

    // Known vehicles and stateless scoring still work.
    first
        .detect(2, samples_after(&samples, 5.0))
        .await
        .expect("one detection per sample, for this batch");
    let stateless = clients
        .detection
        .detect(v1::DetectRequest {
            samples: samples.clone(),
            ..v1::DetectRequest::default()
        })
        .await
        .expect("stateless detection needs no session")
        .into_inner();
    assert_eq!(stateless.detections.len(), samples.len());
    let listed = clients
        .detection
        .list_sessions(v1::ListSessionsRequest::default())
        .await
        .expect("ListSessions")
        .into_inner()
        .sessions;
    let vehicles: Vec<&str> = listed.iter().map(|s| s.vehicle_id.as_str()).collect();
    assert_eq!(vehicles, ["car-1", "car-2"]);
    drop((first, second, clients));
    server.stop().await;
}

/// The same samples shifted `by` seconds later.
fn samples_after(samples: &[v1::Sample], by: f64) -> Vec<v1::Sample> {
    samples
        .iter()
        .map(|s| v1::Sample {
            timestamp_s: s.timestamp_s + by,
            ..*s
        })
        .collect()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn idle_sessions_without_a_stream_are_evicted() {
    let (_dir, server, mut clients) = start_server(|config| config.session_idle_secs = 1).await;
    let samples = track_samples(&normal_drive("idle", 9.0, 4));

    // "streaming" keeps a stream attached; "parked" only had a unary call.
    let (mut streaming, _) = start_stream(&clients, "streaming", "").await;
    streaming
        .detect(1, samples.clone())
        .await
        .expect("one detection per sample, for this batch");
    for vehicle in ["parked", "another"] {
        clients
            .detection
            .detect(v1::DetectRequest {
                vehicle_id: vehicle.into(),
                samples: samples.clone(),
                ..v1::DetectRequest::default()
            })
            .await
            .expect("Detect creates the session");
    }
    // Poll (bounded) until the idle, stream-less sessions are gone.
    let deadline = tokio::time::Instant::now() + std::time::Duration::from_secs(30);
    loop {
        let listed = clients
            .detection
            .list_sessions(v1::ListSessionsRequest::default())
            .await
            .expect("ListSessions")
            .into_inner()
            .sessions;
        let names: Vec<String> = listed.into_iter().map(|s| s.vehicle_id).collect();
        if names == ["streaming"] {
            break;
        }
        assert!(
            tokio::time::Instant::now() < deadline,
            "idle sessions were not evicted: {names:?}"
        );
        tokio::time::sleep(std::time::Duration::from_millis(200)).await;
    }
    let status = clients
        .detection
        .get_session(v1::GetSessionRequest {
            vehicle_id: "parked".into(),
        })
        .await
        .expect_err("the evicted session is gone");
    assert_eq!(status.code(), Code::NotFound);
    // The attached session survived its idleness and goes on.
    streaming
        .detect(2, samples_after(&samples, 10.0))
        .await
        .expect("one detection per sample, for this batch");
    drop((streaming, clients));
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sessions_are_listed_in_pages_and_can_be_reset() {
    let (_dir, server, mut clients) = start_server(|_| {}).await;
    let samples = track_samples(&normal_drive("paged", 9.0, 4));
    for vehicle in ["streaming", "parked", "another"] {
        clients
            .detection
            .detect(v1::DetectRequest {
                vehicle_id: vehicle.into(),
                samples: samples.clone(),
                ..v1::DetectRequest::default()
            })
            .await
            .expect("Detect creates the session");
    }
    let first_page = clients
        .detection
        .list_sessions(v1::ListSessionsRequest {
            page_size: 2,
            page_token: String::new(),
        })
        .await
        .expect("ListSessions")
        .into_inner();
    let names: Vec<&str> = first_page
        .sessions
        .iter()
        .map(|s| s.vehicle_id.as_str())
        .collect();
    assert_eq!(names, ["another", "parked"]);
    let second_page = clients
        .detection
        .list_sessions(v1::ListSessionsRequest {
            page_size: 2,
            page_token: first_page.next_page_token.clone(),
        })
        .await
        .expect("ListSessions")
        .into_inner();
    let names: Vec<&str> = second_page
        .sessions
        .iter()
        .map(|s| s.vehicle_id.as_str())
        .collect();
    assert_eq!(names, ["streaming"]);
    assert!(second_page.next_page_token.is_empty());

    let reset = clients
        .detection
        .reset_session(v1::ResetSessionRequest {
            vehicle_id: "another".into(),
        })
        .await
        .expect("ResetSession")
        .into_inner();
    assert_eq!((reset.samples, reset.trajectories), (0, 0));

    drop(clients);
    server.stop().await;
}
