//! Server lifecycle: reflection (v1 and v1alpha) lists every service, health reports SERVING and
//! flips to NOT_SERVING when shutdown starts, and shutdown with an open stream is bounded.

use std::collections::BTreeSet;
use std::time::{Duration, Instant};

use spoofwatch_tests::{
    TestServer, code_of, health_of, normal_drive, start_server, start_stream, test_config,
    track_samples,
};
use tonic::Code;
use tonic::transport::Channel;
use tonic_health::pb::HealthCheckRequest;
use tonic_health::pb::health_check_response::ServingStatus;
use tonic_reflection::pb::{v1, v1alpha};

/// Every service the server must list through reflection v1 (the reflection service included).
const SERVICES: [&str; 8] = [
    "google.longrunning.Operations",
    "grpc.health.v1.Health",
    "grpc.reflection.v1.ServerReflection",
    "spoofwatch.v1.AlarmService",
    "spoofwatch.v1.DatasetService",
    "spoofwatch.v1.DetectionService",
    "spoofwatch.v1.ModelService",
    "spoofwatch.v1.TrainingService",
];

/// Shutdown grace configured for the test; serve() must return within grace + 1 s (plus slack).
const GRACE_SECS: u64 = 2;
const SHUTDOWN_BOUND: Duration = Duration::from_secs(6);

async fn list_services_v1(channel: Channel) -> BTreeSet<String> {
    use v1::server_reflection_request::MessageRequest;
    use v1::server_reflection_response::MessageResponse;
    let request = v1::ServerReflectionRequest {
        host: String::new(),
        message_request: Some(MessageRequest::ListServices(String::new())),
    };
    let mut replies = v1::server_reflection_client::ServerReflectionClient::new(channel)
        .server_reflection_info(tokio_stream::iter([request]))
        .await
        .expect("reflection v1 answers")
        .into_inner();
    let reply = replies
        .message()
        .await
        .expect("a reflection reply")
        .expect("one reply per request");
    let Some(MessageResponse::ListServicesResponse(list)) = reply.message_response else {
        panic!("expected a service list, got {reply:?}");
    };
    list.service.into_iter().map(|s| s.name).collect()
}

/// Reflection v1alpha: the listed services and the descriptor of the detection service.
async fn list_services_v1alpha(channel: Channel) -> (BTreeSet<String>, usize) {
    use v1alpha::server_reflection_request::MessageRequest;
    use v1alpha::server_reflection_response::MessageResponse;
    let requests = [
        MessageRequest::ListServices(String::new()),
        MessageRequest::FileContainingSymbol("spoofwatch.v1.DetectionService".into()),
    ]
    .map(|m| v1alpha::ServerReflectionRequest {
        host: String::new(),
        message_request: Some(m),
    });
    let mut replies = v1alpha::server_reflection_client::ServerReflectionClient::new(channel)
        .server_reflection_info(tokio_stream::iter(requests))
        .await
        .expect("reflection v1alpha answers")
        .into_inner();
    let mut services = BTreeSet::new();
    let mut descriptors = 0;
    while let Some(reply) = replies.message().await.expect("reflection replies") {
        match reply.message_response {
            Some(MessageResponse::ListServicesResponse(list)) => {
                services.extend(list.service.into_iter().map(|s| s.name));
            }
            Some(MessageResponse::FileDescriptorResponse(files)) => {
                descriptors += files.file_descriptor_proto.len();
            }
            other => panic!("unexpected reflection reply {other:?}"),
        }
    }
    (services, descriptors)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn reflection_lists_every_service_in_both_versions() {
    let dir = tempfile::tempdir().expect("temp dir");
    let server = TestServer::start(test_config(dir.path())).await;
    let channel = server.channel().await;

    let listed = list_services_v1(channel.clone()).await;
    let expected: BTreeSet<String> = SERVICES.iter().map(|s| s.to_string()).collect();
    assert_eq!(listed, expected);

    let (listed, descriptors) = list_services_v1alpha(channel.clone()).await;
    for service in SERVICES
        .iter()
        .filter(|s| !s.starts_with("grpc.reflection"))
    {
        assert!(
            listed.contains(*service),
            "v1alpha lists {service}: {listed:?}"
        );
    }
    assert!(
        descriptors >= 1,
        "v1alpha serves the detection service's descriptor"
    );
    drop(channel);
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn shutdown_turns_health_not_serving_and_ends_open_streams_within_the_bound() {
    let (_dir, mut server, mut clients) =
        start_server(|config| config.shutdown_grace_secs = GRACE_SECS).await;

    for service in [
        "",
        "spoofwatch.v1.DetectionService",
        "spoofwatch.v1.ModelService",
        "spoofwatch.storage",
    ] {
        let status = health_of(&server, service).await;
        assert_eq!(status, ServingStatus::Serving, "service {service:?}");
    }

    let (mut stream, _) = start_stream(&clients, "draining-car", "").await;
    let samples = track_samples(&normal_drive("draining-car", 9.0, 1));
    stream
        .detect(1, samples)
        .await
        .expect("one detection per sample, for this batch");
    let mut watch = clients
        .health
        .watch(HealthCheckRequest {
            service: String::new(),
        })
        .await
        .expect("Health.Watch is accepted")
        .into_inner();
    let first = watch
        .message()
        .await
        .expect("a status")
        .expect("the watch is open");
    assert_eq!(first.status, ServingStatus::Serving as i32);

    let started = Instant::now();
    server.trigger_shutdown();
    loop {
        let update = tokio::time::timeout(Duration::from_secs(10), watch.message())
            .await
            .expect("a health update during shutdown")
            .expect("the watch stream works")
            .expect("the watch stays open until NOT_SERVING is seen");
        if update.status == ServingStatus::NotServing as i32 {
            break;
        }
    }

    let status = loop {
        match stream.next().await {
            Ok(Some(_)) => continue,
            Ok(None) => panic!("the open stream must not end with OK during shutdown"),
            Err(error) => break error,
        }
    };
    assert_eq!(code_of(&status), Code::Unavailable, "{status:?}");
    let remaining = SHUTDOWN_BOUND.saturating_sub(started.elapsed());
    server
        .stop_within(remaining)
        .await
        .expect("serve() ends without error");
    // Held until here: the client keeps its call and a never-ending Health.Watch open, so only
    // the server's own drain (stream ends, bounded wait) can end serve().
    drop((stream, watch, clients));
    eprintln!(
        "serve() returned {:?} after shutdown was triggered",
        started.elapsed()
    );
}
