//! A configured bearer token guards every service except health and reflection: no token or a
//! wrong one is UNAUTHENTICATED, the right one works with the scheme in any case, and reflection
//! (the public schema) stays open.

use spoofwatch_proto::v1;
use spoofwatch_proto::v1::model_service_client::ModelServiceClient;
use spoofwatch_tests::start_server;
use tonic::Code;
use tonic_health::pb::HealthCheckRequest;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_configured_token_guards_every_service_but_health() {
    // start() polls health without a token: health stays open.
    let (_dir, server, mut clients) =
        start_server(|config| config.auth_token = Some("s3cret".into())).await;

    let status = clients
        .models
        .list_models(v1::ListModelsRequest::default())
        .await
        .expect_err("no token");
    assert_eq!(status.code(), Code::Unauthenticated);
    let status = clients
        .detection
        .detect(v1::DetectRequest::default())
        .await
        .expect_err("no token");
    assert_eq!(status.code(), Code::Unauthenticated);
    let status = server
        .connection(Some("wrong"))
        .await
        .models()
        .list_models(v1::ListModelsRequest::default())
        .await
        .expect_err("a wrong token");
    assert_eq!(status.code(), Code::Unauthenticated);
    let models = server
        .connection(Some("s3cret"))
        .await
        .models()
        .list_models(v1::ListModelsRequest::default())
        .await
        .expect("the right token works")
        .into_inner();
    assert_eq!(models.models.len(), 1);
    clients
        .health
        .check(HealthCheckRequest::default())
        .await
        .expect("health needs no token");
    drop(clients);
    server.stop().await;
}

/// ListModels over a plain channel with `authorization` set to `header` (none when `None`).
async fn list_models_with(
    server: &spoofwatch_tests::TestServer,
    header: Option<&str>,
) -> Result<(), tonic::Status> {
    let mut request = tonic::Request::new(v1::ListModelsRequest::default());
    if let Some(header) = header {
        request.metadata_mut().insert(
            "authorization",
            header.parse().expect("an ASCII header value"),
        );
    }
    ModelServiceClient::new(server.channel().await)
        .list_models(request)
        .await
        .map(drop)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_scheme_is_case_insensitive_and_only_the_exact_token_passes() {
    let (_dir, server, clients) =
        start_server(|config| config.auth_token = Some("s3cret".into())).await;
    for accepted in ["Bearer s3cret", "bearer s3cret", "BEARER s3cret"] {
        list_models_with(&server, Some(accepted))
            .await
            .unwrap_or_else(|status| panic!("{accepted:?} refused: {status:?}"));
    }
    for refused in [
        None,
        Some("Bearer"),
        Some("Bearer "),
        Some("s3cret"),
        Some("Basic s3cret"),
        Some("Bearer s3cre"),
        Some("Bearer s3cret2"),
        Some("Bearer S3CRET"),
    ] {
        let status = list_models_with(&server, refused)
            .await
            .expect_err("refused");
        assert_eq!(status.code(), Code::Unauthenticated, "{refused:?}");
    }
    drop(clients);
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn reflection_serves_the_public_schema_without_a_token() {
    use tonic_reflection::pb::v1::ServerReflectionRequest;
    use tonic_reflection::pb::v1::server_reflection_client::ServerReflectionClient;
    use tonic_reflection::pb::v1::server_reflection_request::MessageRequest;
    use tonic_reflection::pb::v1::server_reflection_response::MessageResponse;

    let (_dir, server, clients) =
        start_server(|config| config.auth_token = Some("s3cret".into())).await;
    let request = ServerReflectionRequest {
        host: String::new(),
        message_request: Some(MessageRequest::ListServices(String::new())),
    };
    let reply = ServerReflectionClient::new(server.channel().await)
        .server_reflection_info(tokio_stream::iter([request]))
        .await
        .expect("reflection needs no token")
        .into_inner()
        .message()
        .await
        .expect("a reflection reply")
        .expect("one reply per request");
    let Some(MessageResponse::ListServicesResponse(list)) = reply.message_response else {
        panic!("expected a service list, got {reply:?}");
    };
    assert!(
        list.service
            .iter()
            .any(|s| s.name == "spoofwatch.v1.DetectionService"),
        "{list:?}"
    );
    drop(clients);
    server.stop().await;
}
