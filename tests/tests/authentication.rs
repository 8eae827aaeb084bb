//! A configured bearer token guards every service except health: no token or a wrong one is
//! UNAUTHENTICATED, the right one works.

use spoofwatch_proto::v1;
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
