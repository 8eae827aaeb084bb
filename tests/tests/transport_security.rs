//! Transport: TLS (a client trusting the server's CA gets through; a plaintext client or one
//! trusting another CA does not), mutual TLS (clients without a certificate, or with one from
//! another CA, are refused), unusable TLS files stop the server with their flag and path,
//! `host:port` addresses, gzip requests, and the stream idle timeout (the stream ends with
//! DEADLINE_EXCEEDED and the session resumes on a new one).

use std::path::Path;
use std::time::Duration;

use spoofwatch_proto::v1;
use spoofwatch_proto::v1::model_service_client::ModelServiceClient;
use spoofwatch_tests::pki::TestCa;
use spoofwatch_tests::{
    ConnectOptions, Connection, TestServer, start_server, start_stream, test_config,
};
use tokio_stream::wrappers::ReceiverStream;
use tonic::Code;
use tonic::codec::CompressionEncoding;

/// Lists the models over a new connection to `address` made with `options`; `Err` describes
/// whatever failed (the connection, the handshake or the call).
async fn list_models(address: &str, options: &ConnectOptions) -> Result<usize, String> {
    let connection = Connection::connect_with(address, options)
        .await
        .map_err(|e| e.to_string())?;
    let models = connection
        .models()
        .list_models(v1::ListModelsRequest::default())
        .await
        .map_err(|status| format!("{status:?}"))?;
    Ok(models.into_inner().models.len())
}

fn trusting(ca: &Path) -> ConnectOptions {
    ConnectOptions {
        ca_cert: Some(ca.to_path_buf()),
        ..ConnectOptions::default()
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn tls_serves_clients_that_trust_its_ca_and_refuses_the_others() {
    let dir = tempfile::tempdir().expect("temp dir");
    let ca = TestCa::new(dir.path(), "fleet");
    let other_ca = TestCa::new(dir.path(), "other");
    let server_files = ca.server(dir.path());
    let mut config = test_config(dir.path());
    config.tls_cert = Some(server_files.cert);
    config.tls_key = Some(server_files.key);
    let server = TestServer::start_for(config, &trusting(&ca.cert)).await;
    let port = server.addr.port();

    // The server's CA, by URL and by bare host:port (which becomes https:// with a TLS file).
    assert_eq!(
        list_models(&format!("https://127.0.0.1:{port}"), &trusting(&ca.cert)).await,
        Ok(1)
    );
    assert_eq!(
        list_models(&format!("127.0.0.1:{port}"), &trusting(&ca.cert)).await,
        Ok(1)
    );
    assert_eq!(
        list_models(&format!("https://localhost:{port}"), &trusting(&ca.cert)).await,
        Ok(1)
    );
    // Plaintext to a TLS server, another CA, or the web PKI roots: refused.
    let no_tls = ConnectOptions::default();
    let plaintext = list_models(&format!("http://127.0.0.1:{port}"), &no_tls).await;
    assert!(plaintext.is_err(), "a plaintext client got through");
    let other = list_models(
        &format!("https://127.0.0.1:{port}"),
        &trusting(&other_ca.cert),
    )
    .await
    .expect_err("a client trusting another CA got through");
    assert!(other.contains("certificate"), "{other}");
    let web_roots = list_models(&format!("https://127.0.0.1:{port}"), &no_tls).await;
    assert!(web_roots.is_err(), "the web PKI trusted a test CA");
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn mutual_tls_refuses_clients_without_a_certificate_of_its_client_ca() {
    let dir = tempfile::tempdir().expect("temp dir");
    let ca = TestCa::new(dir.path(), "fleet");
    let vehicles_ca = TestCa::new(dir.path(), "vehicles");
    let rogue_ca = TestCa::new(dir.path(), "rogue");
    let server_files = ca.server(dir.path());
    let vehicle = vehicles_ca.client(dir.path(), "truck-7");
    let rogue = rogue_ca.client(dir.path(), "truck-7");
    let mut config = test_config(dir.path());
    config.tls_cert = Some(server_files.cert);
    config.tls_key = Some(server_files.key);
    config.tls_client_ca = Some(vehicles_ca.cert.clone());
    let with_cert = |files: &spoofwatch_tests::pki::CertFiles| ConnectOptions {
        client_cert: Some(files.cert.clone()),
        client_key: Some(files.key.clone()),
        ..trusting(&ca.cert)
    };
    let server = TestServer::start_for(config, &with_cert(&vehicle)).await;
    let url = server.url();

    // The vehicle's certificate gets through the handshake, and acts as its vehicle: it may not
    // list models (what each role may do: tests/tests/authorization.rs).
    let listed = list_models(&url, &with_cert(&vehicle)).await;
    assert!(
        listed
            .as_ref()
            .is_err_and(|e| e.contains("PermissionDenied")),
        "{listed:?}"
    );
    assert!(
        list_models(&url, &trusting(&ca.cert)).await.is_err(),
        "a client without a certificate got through"
    );
    assert!(
        list_models(&url, &with_cert(&rogue)).await.is_err(),
        "a client certificate of another CA got through"
    );
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_unusable_tls_file_stops_the_server_naming_its_flag_and_path() {
    let dir = tempfile::tempdir().expect("temp dir");
    let ca = TestCa::new(dir.path(), "fleet");
    let server_files = ca.server(dir.path());
    let missing = dir.path().join("missing-key.pem");
    let mut config = test_config(dir.path());
    config.tls_cert = Some(server_files.cert.clone());
    config.tls_key = Some(missing.clone());
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0")
        .await
        .expect("bound");
    let error = spoofwatch_server::serve(config, listener, std::future::pending())
        .await
        .expect_err("a missing key file is a startup error");
    let text = error.to_string();
    assert!(
        text.contains("--tls-key") && text.contains(&missing.display().to_string()),
        "{text}"
    );

    // A certificate file given as the key: no private key in it.
    let mut config = test_config(dir.path());
    config.tls_cert = Some(server_files.cert.clone());
    config.tls_key = Some(server_files.cert.clone());
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0")
        .await
        .expect("bound");
    let error = spoofwatch_server::serve(config, listener, std::future::pending())
        .await
        .expect_err("a key file without a key is a startup error");
    assert!(error.to_string().contains("private key"), "{error}");

    // Another certificate's key.
    let other = ca.client(dir.path(), "other");
    let mut config = test_config(dir.path());
    config.tls_cert = Some(server_files.cert.clone());
    config.tls_key = Some(other.key);
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0")
        .await
        .expect("bound");
    let error = spoofwatch_server::serve(config, listener, std::future::pending())
        .await
        .expect_err("a key that is not the certificate's is a startup error");
    assert!(
        error.to_string().contains("--tls-cert/--tls-key"),
        "{error}"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_bare_host_and_port_means_plaintext_without_tls_files() {
    let (_dir, server, clients) = start_server(|_| {}).await;
    let address = server.addr.to_string();
    assert_eq!(
        list_models(&address, &ConnectOptions::default()).await,
        Ok(1)
    );
    drop(clients);
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn gzip_requests_are_accepted_and_answered() {
    let (_dir, server, clients) = start_server(|_| {}).await;
    // A plain tonic client that compresses its requests (as grpcurl or another stack may).
    let mut models = ModelServiceClient::new(server.channel().await)
        .send_compressed(CompressionEncoding::Gzip)
        .accept_compressed(CompressionEncoding::Gzip);
    let listed = models
        .list_models(v1::ListModelsRequest::default())
        .await
        .expect("a gzip request is accepted")
        .into_inner();
    assert_eq!(listed.models.len(), 1);
    let gzip = ConnectOptions {
        gzip: true,
        ..ConnectOptions::default()
    };
    let connection = Connection::connect_with(&server.url(), &gzip)
        .await
        .expect("connected");
    let samples =
        spoofwatch_tests::track_samples(&spoofwatch_tests::normal_drive("van-1", 30.0, 3));
    let detected = connection
        .detection()
        .detect(v1::DetectRequest {
            samples: samples.clone(),
            ..v1::DetectRequest::default()
        })
        .await
        .expect("a gzip detection request is answered")
        .into_inner();
    assert_eq!(detected.detections.len(), samples.len());
    drop((clients, connection));
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_idle_limit_counts_from_the_last_message_not_the_start() {
    let (_dir, server, clients) = start_server(|config| config.stream_idle_secs = 1).await;
    let (mut stream, _) = start_stream(&clients, "truck-7", "").await;
    let samples =
        spoofwatch_tests::track_samples(&spoofwatch_tests::normal_drive("truck-7", 20.0, 4));
    // Three times the limit in all, each gap shorter than it: the stream stays open.
    for (seq, sample) in (1..=6).zip(&samples) {
        tokio::time::sleep(Duration::from_millis(500)).await;
        stream
            .detect(seq, vec![*sample])
            .await
            .expect("a stream that keeps talking stays open");
    }
    let started = tokio::time::Instant::now();
    let status = loop {
        match stream.next().await {
            Ok(Some(_)) => continue,
            Ok(None) => panic!("the silent stream ended with OK"),
            Err(error) => break error.status().expect("a gRPC status").clone(),
        }
    };
    assert_eq!(status.code(), Code::DeadlineExceeded, "{status:?}");
    assert!(
        started.elapsed() < Duration::from_secs(5),
        "the stream ended {:?} after its last message",
        started.elapsed()
    );
    drop(clients);
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn silent_streams_end_with_deadline_exceeded_and_the_session_resumes() {
    let (_dir, server, mut clients) = start_server(|config| config.stream_idle_secs = 1).await;

    // StreamDetect: accepted, then silence.
    let (mut silent, accepted) = start_stream(&clients, "truck-9", "").await;
    assert!(!accepted.resumed);
    let samples =
        spoofwatch_tests::track_samples(&spoofwatch_tests::normal_drive("truck-9", 20.0, 4));
    silent
        .detect(1, samples[..10].to_vec())
        .await
        .expect("one detection per sample");
    let ended = loop {
        match silent.next().await {
            Ok(Some(_)) => continue,
            Ok(None) => panic!("the silent stream ended with OK"),
            Err(error) => break error,
        }
    };
    let status = ended.status().expect("a gRPC status");
    assert_eq!(status.code(), Code::DeadlineExceeded, "{status:?}");
    assert!(
        status.message().contains("--stream-idle-secs"),
        "{status:?}"
    );
    let (resumed, accepted) = start_stream(&clients, "truck-9", "").await;
    assert_eq!((accepted.resumed, accepted.samples_seen), (true, 10));
    resumed
        .finish()
        .await
        .expect("the resumed stream ends cleanly");

    // StreamDetectFleet: nothing at all.
    let (fleet_tx, fleet_rx) = tokio::sync::mpsc::channel::<v1::FleetBatch>(1);
    let mut fleet = clients
        .detection
        .stream_detect_fleet(ReceiverStream::new(fleet_rx))
        .await
        .expect("the call is accepted")
        .into_inner();
    let status = fleet.message().await.expect_err("the idle stream ends");
    assert_eq!(status.code(), Code::DeadlineExceeded, "{status:?}");
    drop(fleet_tx);

    // An upload that sends its header and stops.
    let (upload_tx, upload_rx) = tokio::sync::mpsc::channel::<v1::UploadDatasetRequest>(1);
    upload_tx
        .send(v1::UploadDatasetRequest {
            kind: Some(v1::upload_dataset_request::Kind::Header(
                v1::UploadDatasetHeader {
                    display_name: "stalled".into(),
                },
            )),
        })
        .await
        .expect("queued");
    let status = clients
        .datasets
        .upload_dataset(ReceiverStream::new(upload_rx))
        .await
        .expect_err("the stalled upload ends");
    assert_eq!(status.code(), Code::DeadlineExceeded, "{status:?}");
    drop(upload_tx);
    drop(clients);
    server.stop().await;
}
