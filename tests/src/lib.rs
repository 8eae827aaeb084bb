//! What the black-box tests share: start the real server in-process on a loopback port, connect
//! the client library's `Connection` to it, open `DetectStream`s whose replies are awaited with a
//! bound, and build test inputs (drives, attacks, uploads) with `spoofwatch-core`.
//!
//! Tests talk to the server only through gRPC. The recipe follows tonic's own tests: the server
//! crate's `InProcessServer` binds `127.0.0.1:0` and spawns `serve` with a oneshot shutdown; poll
//! health instead of sleeping, and drop
//! clients before triggering shutdown (an open stream holds the connection and delays the drain).
//! Test-specific assertions stay in the test files (one per behaviour under `tests/`); this crate
//! must not grow a second implementation of anything the client library already has. `pki` makes
//! the certificates of the TLS tests.

pub mod balancer;
pub mod incidents;
pub mod pki;
pub mod replica_process;

use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::time::Duration;

use prost::Message;
pub use spoofwatch_client::detect_stream::{
    BatchOutcome, BatchReply, batch_request, start_request,
};
pub use spoofwatch_client::{
    AuthenticatedChannel, ClientError, ConnectOptions, Connection, DetectStream,
};
use spoofwatch_core::data::telemetry::write_tracks;
use spoofwatch_core::model::artifact::ModelArtifact;
use spoofwatch_core::sample::Track;
use spoofwatch_core::scenario::{AttackKind, AttackSpec, DriveSpec, inject, simulate_drive};
use spoofwatch_core::severity::CriticalTest;
use spoofwatch_proto::longrunning;
use spoofwatch_proto::longrunning::operation;
use spoofwatch_proto::longrunning::operations_client::OperationsClient;
use spoofwatch_proto::v1;
use spoofwatch_proto::v1::alarm_service_client::AlarmServiceClient;
use spoofwatch_proto::v1::dataset_service_client::DatasetServiceClient;
use spoofwatch_proto::v1::detection_service_client::DetectionServiceClient;
use spoofwatch_proto::v1::model_service_client::ModelServiceClient;
use spoofwatch_proto::v1::training_service_client::TrainingServiceClient;
use spoofwatch_proto::wire::convert::sample_to_proto;
use spoofwatch_server::Config;
use spoofwatch_server::inprocess::{InProcessError, InProcessServer};
use spoofwatch_server::models::registry::BUNDLED_MODEL;
use spoofwatch_server::store::AlarmEventRow;
use tonic::Code;
use tonic::transport::Channel;
use tonic_health::pb::HealthCheckRequest;
pub use tonic_health::pb::health_check_response::ServingStatus;
use tonic_health::pb::health_client::HealthClient;

/// Longest a test waits for one reply before failing (generous: debug builds on 2 shared cores).
pub const REPLY_TIMEOUT: Duration = Duration::from_secs(60);
/// GETs `/metrics` at `addr` and returns the exposition text (the answer must be 200 OK).
pub async fn scrape(addr: SocketAddr) -> String {
    use http_body_util::{BodyExt, Empty};
    use hyper::body::Bytes;
    use hyper_util::client::legacy::Client;
    use hyper_util::rt::TokioExecutor;

    let client = Client::builder(TokioExecutor::new()).build_http::<Empty<Bytes>>();
    let uri: hyper::Uri = format!("http://{addr}/metrics").parse().expect("a URI");
    let response = tokio::time::timeout(REPLY_TIMEOUT, client.get(uri))
        .await
        .expect("the metrics endpoint answers in time")
        .expect("the metrics endpoint answers");
    assert_eq!(response.status(), hyper::StatusCode::OK);
    let body = response.into_body().collect().await.expect("the body");
    String::from_utf8(body.to_bytes().to_vec()).expect("UTF-8")
}

/// Longest a test waits for the server to report SERVING.
const READY_TIMEOUT: Duration = Duration::from_secs(30);

/// A server configuration for tests: a database file in `dir`, a short shutdown grace.
pub fn test_config(dir: &Path) -> Config {
    let mut config = Config::with_database(database_path(dir).display().to_string());
    config.shutdown_grace_secs = 2;
    config
}

/// A fresh server on a database in a new temporary directory, its [`test_config`] adjusted by
/// `configure`, and clients connected to it. The directory must outlive the server.
pub async fn start_server(
    configure: impl FnOnce(&mut Config),
) -> (tempfile::TempDir, TestServer, Clients) {
    let dir = tempfile::tempdir().expect("temp dir");
    let mut config = test_config(dir.path());
    configure(&mut config);
    let server = TestServer::start(config).await;
    let clients = Clients::of(&server).await;
    (dir, server, clients)
}

/// Where [`test_config`] puts the database inside `dir`.
pub fn database_path(dir: &Path) -> PathBuf {
    dir.join("spoofwatch.db")
}

/// A server running in this process (the server crate's [`InProcessServer`]), ready when
/// [`TestServer::start`] returns.
pub struct TestServer {
    /// The loopback address it listens on.
    pub addr: SocketAddr,
    /// Whether it speaks TLS (its configuration names a certificate).
    tls: bool,
    server: InProcessServer,
}

impl TestServer {
    /// Starts `config` (plaintext) on a free loopback port and waits until health reports SERVING.
    pub async fn start(config: Config) -> TestServer {
        Self::start_for(config, &ConnectOptions::default()).await
    }

    /// Starts `config` and waits until a client connecting with `client` (e.g. trusting the test
    /// CA of a TLS server) sees health SERVING.
    pub async fn start_for(config: Config, client: &ConnectOptions) -> TestServer {
        let tls = config.tls_cert.is_some();
        let server = InProcessServer::start_with(config)
            .await
            .expect("start the in-process server");
        let addr = server.addr();
        let server = TestServer { addr, tls, server };
        wait_until_serving_with(&server.url(), client, READY_TIMEOUT).await;
        server
    }

    /// Starts `config` on 127.0.0.1:`port` (e.g. the port of a server that just stopped, so its
    /// clients reconnect to this one) and waits until health reports SERVING (plaintext).
    pub async fn start_on_port(config: Config, port: u16) -> TestServer {
        let server = InProcessServer::start_on_port(config, port)
            .await
            .expect("start the in-process server on the given port");
        let addr = server.addr();
        let server = TestServer {
            addr,
            tls: false,
            server,
        };
        wait_until_serving_with(&server.url(), &ConnectOptions::default(), READY_TIMEOUT).await;
        server
    }

    /// The server's URL (`https://` when it speaks TLS).
    pub fn url(&self) -> String {
        if self.tls {
            format!("https://{}", self.addr)
        } else {
            self.server.url()
        }
    }

    /// Where the server answers `GET /metrics` (started with `config.metrics_listen` set).
    pub fn metrics_addr(&self) -> Option<SocketAddr> {
        self.server.metrics_addr()
    }

    /// A new plain channel to a plaintext server (for services the client library does not
    /// cover, or calls it would not make).
    pub async fn channel(&self) -> Channel {
        Channel::from_shared(self.url())
            .expect("a valid URI")
            .connect()
            .await
            .expect("connect to the test server")
    }

    /// A new client connection to the server, sending `token` when given.
    pub async fn connection(&self, token: Option<&str>) -> Connection {
        Connection::connect(self.url(), token.map(str::to_string))
            .await
            .expect("connect to the test server")
    }

    /// Fires the shutdown signal (the server starts draining); idempotent.
    pub fn trigger_shutdown(&mut self) {
        self.server.trigger_shutdown();
    }

    /// Triggers shutdown and waits (at most `bound`) for `serve` to return; panics past the bound.
    pub async fn stop_within(self, bound: Duration) -> Result<(), InProcessError> {
        tokio::time::timeout(bound, self.server.shutdown())
            .await
            .expect("serve() returned within the shutdown bound")
    }

    /// Triggers shutdown and waits for `serve` to return successfully.
    pub async fn stop(self) {
        self.stop_within(Duration::from_secs(30))
            .await
            .expect("serve() ended without error");
    }
}

/// Waits (see [`Connection::wait_until_serving`]) until the server at `url` reports SERVING to a
/// client connecting with `client`; panics after `bound`.
pub async fn wait_until_serving_with(url: &str, client: &ConnectOptions, bound: Duration) {
    if let Err(error) = Connection::wait_until_serving(url, client, bound).await {
        panic!("{error}");
    }
}

/// Typed clients over one [`Connection`].
#[derive(Clone)]
pub struct Clients {
    pub connection: Connection,
    pub detection: DetectionServiceClient<AuthenticatedChannel>,
    pub models: ModelServiceClient<AuthenticatedChannel>,
    pub datasets: DatasetServiceClient<AuthenticatedChannel>,
    pub training: TrainingServiceClient<AuthenticatedChannel>,
    pub operations: OperationsClient<AuthenticatedChannel>,
    pub alarms: AlarmServiceClient<AuthenticatedChannel>,
    pub health: HealthClient<AuthenticatedChannel>,
}

impl Clients {
    /// Clients of every service over `connection`.
    pub fn new(connection: Connection) -> Self {
        Self {
            detection: connection.detection(),
            models: connection.models(),
            datasets: connection.datasets(),
            training: connection.training(),
            operations: connection.operations(),
            alarms: connection.alarms(),
            health: connection.health(),
            connection,
        }
    }

    /// Clients connected to `server` (no token).
    pub async fn of(server: &TestServer) -> Self {
        Self::new(server.connection(None).await)
    }
}

/// The hex SHA-256 of a token, as a roles file names it.
pub fn token_sha256(token: &str) -> String {
    use sha2::{Digest, Sha256};
    Sha256::digest(token.as_bytes())
        .iter()
        .map(|b| format!("{b:02x}"))
        .collect()
}

/// The single admin token of the servers [`start_with_roles`] starts without TLS.
pub const ADMIN_TOKEN: &str = "s3cret";

/// A server whose roles file (`<dir>/roles.toml`, rewritten by tests to change who may do what)
/// holds `roles`, with its metrics served. Without `tls` its admin is [`ADMIN_TOKEN`]; with it,
/// the server requires client certificates of the CA and is reached as the certificate given.
pub async fn start_with_roles(
    dir: &Path,
    roles: &str,
    tls: Option<(&pki::TestCa, &pki::CertFiles)>,
) -> TestServer {
    let roles_file = dir.join("roles.toml");
    std::fs::write(&roles_file, roles).expect("roles file written");
    let mut config = test_config(dir);
    config.roles_file = Some(roles_file);
    config.metrics_listen = Some(SocketAddr::from(([127, 0, 0, 1], 0)));
    match tls {
        None => {
            config.auth_token = Some(ADMIN_TOKEN.into());
            TestServer::start_for(
                config,
                &ConnectOptions::with_token(Some(ADMIN_TOKEN.into())),
            )
            .await
        }
        Some((ca, admin_files)) => {
            let server_files = ca.server(dir);
            config.tls_cert = Some(server_files.cert);
            config.tls_key = Some(server_files.key);
            config.tls_client_ca = Some(ca.cert.clone());
            TestServer::start_for(config, &with_certificate(ca, admin_files)).await
        }
    }
}

/// Connects trusting `ca` and presenting the client certificate `files`.
pub fn with_certificate(ca: &pki::TestCa, files: &pki::CertFiles) -> ConnectOptions {
    ConnectOptions {
        ca_cert: Some(ca.cert.clone()),
        client_cert: Some(files.cert.clone()),
        client_key: Some(files.key.clone()),
        ..ConnectOptions::default()
    }
}

/// The wire samples of a track.
pub fn track_samples(track: &Track) -> Vec<v1::Sample> {
    track
        .records
        .iter()
        .map(|r| sample_to_proto(&r.sample))
        .collect()
}

/// A simulated normal drive of `duration_s` seconds at 1 Hz.
pub fn normal_drive(vehicle_id: &str, duration_s: f64, seed: u64) -> Track {
    let spec = DriveSpec {
        duration_s,
        seed,
        ..DriveSpec::default()
    };
    simulate_drive(&spec, vehicle_id).expect("a valid drive spec")
}

/// A simulated drive with one injected attack of `kind` from `onset_s` for `duration_s` seconds.
pub fn attacked_drive(
    vehicle_id: &str,
    drive_s: f64,
    seed: u64,
    kind: AttackKind,
    onset_s: f64,
    duration_s: f64,
) -> Track {
    let base = normal_drive(vehicle_id, drive_s, seed);
    let attack = AttackSpec {
        kind,
        direction_deg: 45.0,
        onset_s,
        duration_s,
        seed: Some(seed),
    };
    let mut injected = inject(&base, &attack).expect("a valid attack").track;
    // Keep the plain vehicle id (the injected one carries `#<attack>`, fine for CSV but long).
    injected.vehicle_id = vehicle_id.to_string();
    injected
}

/// Bytes per uploaded CSV chunk (a ~2,000-row dataset spans several).
const UPLOAD_CHUNK_BYTES: usize = 16 * 1024;

/// `tracks` as a labelled telemetry CSV.
pub fn telemetry_csv(tracks: &[Track]) -> Vec<u8> {
    let mut csv = Vec::new();
    write_tracks(&mut csv, tracks).expect("the tracks serialise");
    csv
}

/// Uploads `tracks` as a telemetry CSV in chunks through `DatasetService.UploadDataset`.
pub async fn upload_tracks(
    clients: &mut Clients,
    display_name: &str,
    tracks: &[Track],
) -> v1::Dataset {
    try_upload_tracks(clients, display_name, tracks)
        .await
        .expect("the upload is accepted")
}

/// [`upload_tracks`], returning the status of a refused upload.
pub async fn try_upload_tracks(
    clients: &mut Clients,
    display_name: &str,
    tracks: &[Track],
) -> Result<v1::Dataset, tonic::Status> {
    use v1::upload_dataset_request::Kind;
    let csv = telemetry_csv(tracks);
    let header = Kind::Header(v1::UploadDatasetHeader {
        display_name: display_name.to_string(),
    });
    let messages: Vec<v1::UploadDatasetRequest> = std::iter::once(header)
        .chain(
            csv.chunks(UPLOAD_CHUNK_BYTES)
                .map(|c| Kind::CsvChunk(c.to_vec())),
        )
        .map(|kind| v1::UploadDatasetRequest { kind: Some(kind) })
        .collect();
    clients
        .datasets
        .upload_dataset(tokio_stream::iter(messages))
        .await
        .map(tonic::Response::into_inner)
}

/// Opens a session stream for `vehicle_id` (reset = false) whose replies must each arrive within
/// [`REPLY_TIMEOUT`], and returns it with its `SessionAccepted`.
pub async fn start_stream(
    clients: &Clients,
    vehicle_id: &str,
    model: &str,
) -> (DetectStream, v1::SessionAccepted) {
    let mut stream = open_stream(clients, start_request(vehicle_id, model, false))
        .await
        .expect("the call is accepted");
    let accepted = stream
        .accepted()
        .await
        .unwrap_or_else(|e| panic!("expected SessionAccepted for {vehicle_id}: {e}"));
    (stream, accepted)
}

/// Sends `batches` (numbered from `first_seq`) on a stream of `vehicle` through `model` (empty: the
/// active one), ends it, and returns its `SessionAccepted` and the batches' detections.
pub async fn stream_batches(
    clients: &Clients,
    (vehicle, model): (&str, &str),
    batches: &[Vec<v1::Sample>],
    first_seq: u64,
) -> (v1::SessionAccepted, Vec<v1::Detection>) {
    let (mut stream, accepted) = start_stream(clients, vehicle, model).await;
    let mut detections = Vec::new();
    for (seq, batch) in (first_seq..).zip(batches) {
        detections.extend(
            stream
                .detect(seq, batch.clone())
                .await
                .expect("one detection per sample"),
        );
    }
    stream.finish().await.expect("the stream ends with OK");
    (accepted, detections)
}

/// Opens a call whose first message is `first` (replies bounded by [`REPLY_TIMEOUT`]); `Err` when
/// the call itself is refused.
pub async fn open_stream(
    clients: &Clients,
    first: v1::StreamDetectRequest,
) -> Result<DetectStream, ClientError> {
    Ok(DetectStream::open(&clients.connection, first)
        .await?
        .with_reply_timeout(REPLY_TIMEOUT))
}

/// The status code a failed call or stream ended with (panics when it is not a gRPC status).
pub fn code_of(error: &ClientError) -> Code {
    error
        .status()
        .unwrap_or_else(|| panic!("expected a gRPC status, got {error}"))
        .code()
}

/// Reads replies until the call ends and returns its final status code (OK when it ended cleanly).
pub async fn final_code(stream: &mut DetectStream) -> Code {
    loop {
        match stream.next().await {
            Ok(Some(_)) => continue,
            Ok(None) => return Code::Ok,
            Err(error) => return code_of(&error),
        }
    }
}

/// The field violations of a google.rpc.Status carrying a BadRequest detail.
pub fn field_violations(status: &tonic_types::Status) -> Vec<(String, String)> {
    status
        .details
        .iter()
        .filter(|any| any.type_url.ends_with("google.rpc.BadRequest"))
        .flat_map(|any| {
            tonic_types::pb::BadRequest::decode(any.value.as_slice())
                .expect("a decodable BadRequest")
                .field_violations
        })
        .map(|v| (v.field, v.description))
        .collect()
}

/// A critical test the black-box tests give the bundled model in place of its own (`docs/detector.md`
/// §7.4): an alarm turns critical once the anchor NIS stays at or beyond 400 for 1 s (a large jump),
/// or once the logit of p̂ above 5, summed over seconds, reaches 10. Made up for the tests (not
/// chosen on validation hours) and quicker to escalate than the bundled one: what is under test is
/// the severity's path through the server.
pub const TEST_CRITICAL: CriticalTest = CriticalTest {
    reference_logit: 5.0,
    threshold: 10.0,
    gate: 400.0,
    decisive_s: 1.0,
    frozen_fix_s: None,
    held_jump: None,
    held_step: None,
    held_offset: None,
};

/// The bundled default model's artifact with [`TEST_CRITICAL`] in place of its own critical level.
pub fn artifact_with_critical_level() -> Vec<u8> {
    let mut artifact = ModelArtifact::from_slice(BUNDLED_MODEL).expect("the bundled model");
    artifact.critical = Some(TEST_CRITICAL);
    artifact
        .to_vec()
        .expect("the artifact with a critical level is valid")
}

/// The bundled default model's artifact without a critical level, as every model made before
/// severities existed: it raises warnings only.
pub fn artifact_without_critical_level() -> Vec<u8> {
    let mut artifact = ModelArtifact::from_slice(BUNDLED_MODEL).expect("the bundled model");
    artifact.critical = None;
    artifact
        .to_vec()
        .expect("the artifact without a critical level is valid")
}

/// The bundled default model's artifact registered again under other notes: the same network and
/// tests, so a server holding both decides every sample alike.
pub fn artifact_registered_again() -> Vec<u8> {
    let mut artifact = ModelArtifact::from_slice(BUNDLED_MODEL).expect("the bundled model");
    artifact.provenance.notes = "the bundled model, registered again".into();
    artifact
        .to_vec()
        .expect("the artifact registered again is valid")
}

/// Drains a server-streaming model export into the artifact's bytes.
pub async fn export_model(
    models: &mut ModelServiceClient<AuthenticatedChannel>,
    name: &str,
) -> Vec<u8> {
    let mut chunks = models
        .export_model(v1::ExportModelRequest {
            name: name.to_string(),
        })
        .await
        .expect("ExportModel is accepted")
        .into_inner();
    let mut bytes = Vec::new();
    while let Some(chunk) = chunks.message().await.expect("every chunk arrives") {
        bytes.extend_from_slice(&chunk.data);
    }
    bytes
}

/// Uploads an artifact in two chunks under `display_name` (not activated).
pub async fn import_model(
    clients: &mut Clients,
    artifact: Vec<u8>,
    display_name: &str,
) -> v1::Model {
    use v1::import_model_request::Kind;
    let (head, tail) = artifact.split_at(artifact.len() / 2);
    let messages = [
        Kind::Header(v1::ImportModelHeader {
            display_name: display_name.into(),
            activate: false,
        }),
        Kind::Chunk(head.to_vec()),
        Kind::Chunk(tail.to_vec()),
    ]
    .map(|kind| v1::ImportModelRequest { kind: Some(kind) });
    clients
        .models
        .import_model(tokio_stream::iter(messages))
        .await
        .expect("ImportModel accepts an exported artifact")
        .into_inner()
}

/// The name of the active model (exactly one is active).
pub async fn active_model(models: &mut ModelServiceClient<AuthenticatedChannel>) -> v1::Model {
    let listed = models
        .list_models(v1::ListModelsRequest::default())
        .await
        .expect("ListModels works")
        .into_inner()
        .models;
    let mut active: Vec<v1::Model> = listed.into_iter().filter(|m| m.active).collect();
    assert_eq!(active.len(), 1, "exactly one model is active");
    active.remove(0)
}

/// Sends a batch and returns the ItemError status it must cause (panics on anything else; the
/// stream checks that the ItemError echoes the batch's seq).
pub async fn expect_item_error(
    stream: &mut DetectStream,
    seq: u64,
    samples: Vec<v1::Sample>,
) -> tonic_types::Status {
    stream
        .send_batch(seq, samples)
        .await
        .expect("the request stream is open");
    match stream.recv().await {
        Ok(BatchReply {
            outcome: BatchOutcome::Rejected(status),
            ..
        }) => status,
        other => panic!("expected an ItemError for seq {seq}, got {other:?}"),
    }
}

/// Five 400 s drives (2,005 rows): two normal, three with ramp attacks placed so that the
/// chronological 70/15/15 split has both classes in training and in validation.
pub fn training_fleet() -> Vec<Track> {
    let ramp = AttackKind::RampDrift { velocity_mps: 1.5 };
    vec![
        normal_drive("sim-0", 400.0, 11),
        attacked_drive("sim-1", 400.0, 12, ramp, 150.0, 100.0),
        attacked_drive("sim-2", 400.0, 13, ramp, 250.0, 100.0),
        normal_drive("sim-3", 400.0, 14),
        attacked_drive("sim-4", 400.0, 15, ramp, 300.0, 80.0),
    ]
}

/// A training job on `dataset` with seed 7 and `max_epochs` epochs, of the `v2` evidence, which trains
/// the job tests' tiny fleet ([`training_fleet`]) in seconds. The fleet-fit tests train the default
/// (`v3`) through the server.
pub fn training_request(
    dataset: &str,
    max_epochs: u32,
    activate: bool,
) -> v1::CreateTrainingJobRequest {
    v1::CreateTrainingJobRequest {
        datasets: vec![dataset.to_string()],
        spec: Some(v1::TrainingSpec {
            seed: 7,
            max_epochs,
            feature_schema: "v2".to_string(),
            ..v1::TrainingSpec::default()
        }),
        display_name: format!("tiny {max_epochs}-epoch model"),
        activate,
        ..v1::CreateTrainingJobRequest::default()
    }
}

/// An operation's `JobMetadata` (it must carry one).
pub fn metadata_of(operation: &longrunning::Operation) -> v1::JobMetadata {
    let any = operation
        .metadata
        .as_ref()
        .expect("an operation carries metadata");
    assert_eq!(
        any.type_url,
        "type.googleapis.com/spoofwatch.v1.JobMetadata"
    );
    v1::JobMetadata::decode(any.value.as_slice()).expect("decodable JobMetadata")
}

/// Waits (server side, at most 60 s per call) until the operation is done.
pub async fn wait_done(
    operations: &mut OperationsClient<AuthenticatedChannel>,
    name: &str,
) -> longrunning::Operation {
    for _ in 0..5 {
        let operation = operations
            .wait_operation(longrunning::WaitOperationRequest {
                name: name.to_string(),
                timeout: Some(prost_types::Duration {
                    seconds: 60,
                    nanos: 0,
                }),
            })
            .await
            .expect("WaitOperation works")
            .into_inner();
        if operation.done {
            return operation;
        }
    }
    panic!("{name} did not finish within 5 minutes");
}

/// The model a finished training operation registered.
pub fn trained_model(operation: &longrunning::Operation) -> v1::Model {
    let Some(operation::Result::Response(any)) = &operation.result else {
        panic!("a succeeded training operation has a response: {operation:?}");
    };
    assert_eq!(
        any.type_url,
        "type.googleapis.com/spoofwatch.v1.TrainingJobResult"
    );
    let result = v1::TrainingJobResult::decode(any.value.as_slice()).expect("decodable result");
    assert!(
        result.validation.is_some(),
        "validation metrics are reported"
    );
    result.model.expect("the result names the registered model")
}

/// One confirmed alarm as the detections show it: onset time, last alarming sample's time, peak
/// probability and number of alarming samples.
#[derive(Debug, PartialEq)]
pub struct Episode {
    pub onset_s: f64,
    pub last_s: f64,
    pub peak: f64,
    pub samples: i64,
}

/// Streams a 240 s drive whose fix freezes for 60 s (from 100 s) through the bundled model, 20
/// samples per batch; returns the alarm episodes the detections show.
pub async fn stream_frozen_fix_drive(clients: &Clients, vehicle_id: &str) -> Vec<Episode> {
    let frozen = AttackKind::FrozenPosition;
    let track = attacked_drive(vehicle_id, 240.0, 21, frozen, 100.0, 60.0);
    let (mut stream, _) = start_stream(clients, vehicle_id, "models/default").await;
    let mut episodes: Vec<Episode> = Vec::new();
    for (seq, batch) in track_samples(&track).chunks(20).enumerate() {
        for d in stream
            .detect(seq as u64 + 1, batch.to_vec())
            .await
            .expect("one detection per sample, for this batch")
        {
            if d.alarm_onset {
                episodes.push(Episode {
                    onset_s: d.timestamp_s,
                    last_s: d.timestamp_s,
                    peak: d.probability,
                    samples: 1,
                });
            } else if d.alarm {
                let open = episodes.last_mut().expect("an alarm follows its onset");
                open.last_s = d.timestamp_s;
                open.peak = open.peak.max(d.probability);
                open.samples += 1;
            }
        }
    }
    episodes
}

/// Stored alarm events (newest first, as the store lists them) as episodes, oldest first; every
/// event must be closed.
pub fn stored_episodes(events: &[AlarmEventRow]) -> Vec<Episode> {
    events
        .iter()
        .rev()
        .map(|e| Episode {
            onset_s: e.onset_timestamp_s,
            last_s: e
                .end_timestamp_s
                .expect("the alarm ended with a sample time"),
            peak: e.peak_probability,
            samples: e.samples,
        })
        .collect()
}

/// What must be identical: the bits of every output the model computes, and the alarm flags.
pub fn fingerprint(detections: &[v1::Detection]) -> Vec<(u64, u64, bool, bool, bool)> {
    detections
        .iter()
        .map(|d| {
            (
                d.timestamp_s.to_bits(),
                d.probability.to_bits(),
                d.alarm,
                d.alarm_onset,
                d.alarm_end,
            )
        })
        .collect()
}

/// The stored alarms of `vehicle` as (onset, end, peak, samples, open), oldest first.
pub async fn alarms_of(
    clients: &mut Clients,
    vehicle: &str,
) -> Vec<(f64, Option<f64>, f64, u64, bool)> {
    let mut alarms = clients
        .alarms
        .list_alarms(v1::ListAlarmsRequest {
            vehicle_id: vehicle.to_string(),
            ..Default::default()
        })
        .await
        .expect("ListAlarms")
        .into_inner()
        .alarms;
    alarms.sort_by(|a, b| a.onset_timestamp_s.total_cmp(&b.onset_timestamp_s));
    alarms
        .into_iter()
        .map(|a| {
            (
                a.onset_timestamp_s,
                a.end_timestamp_s,
                a.peak_probability,
                a.samples,
                a.end_time.is_none(),
            )
        })
        .collect()
}

/// The stored alarms of `vehicle` of at least `severity` (an `AlarmSeverity` number; 0 for every
/// alarm), oldest first.
pub async fn listed_alarms(clients: &mut Clients, vehicle: &str, severity: i32) -> Vec<v1::Alarm> {
    let mut alarms = clients
        .alarms
        .list_alarms(v1::ListAlarmsRequest {
            vehicle_id: vehicle.to_string(),
            severity,
            ..Default::default()
        })
        .await
        .expect("ListAlarms")
        .into_inner()
        .alarms;
    alarms.sort_by_key(|a| a.id);
    alarms
}

/// Every stored alarm event of `vehicle` of at least `severity` (0 for every event), replayed by
/// WatchAlarms from the start; the CAUGHT_UP event is left out.
pub async fn replayed_alarm_events(
    clients: &mut Clients,
    vehicle: &str,
    severity: i32,
) -> Vec<v1::AlarmEvent> {
    let mut stream = clients
        .alarms
        .watch_alarms(v1::WatchAlarmsRequest {
            vehicle_id: vehicle.to_string(),
            after_cursor: Some(0),
            stop_when_caught_up: true,
            severity,
        })
        .await
        .expect("WatchAlarms")
        .into_inner();
    let mut events = Vec::new();
    while let Some(event) = stream.message().await.expect("the replay goes on") {
        if event.kind != v1::AlarmEventKind::CaughtUp as i32 {
            events.push(event);
        }
    }
    events
}

/// The health status the server reports for `service` ("" = overall).
pub async fn health_of(server: &TestServer, service: &str) -> ServingStatus {
    let status = HealthClient::new(server.channel().await)
        .check(HealthCheckRequest {
            service: service.to_string(),
        })
        .await
        .expect("health answers")
        .into_inner()
        .status;
    ServingStatus::try_from(status).expect("a known serving status")
}

/// Polls `service`'s health every 50 ms until it is `wanted`; panics after 30 s.
pub async fn wait_for_health(server: &TestServer, service: &str, wanted: ServingStatus) {
    for _ in 0..600 {
        if health_of(server, service).await == wanted {
            return;
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    panic!("health of {service:?} never became {wanted:?}");
}

/// Streams `samples` (seq from `first_seq`) for `vehicle` through `connection` on one stream
/// opened with `reset`; returns its SessionAccepted.
pub async fn stream_samples(
    connection: &Connection,
    vehicle: &str,
    reset: bool,
    first_seq: u64,
    samples: &[v1::Sample],
) -> v1::SessionAccepted {
    let (stream, accepted) = DetectStream::start(connection, vehicle, "", reset)
        .await
        .unwrap_or_else(|e| panic!("{vehicle}: the stream opens: {e}"));
    let mut stream = stream.with_reply_timeout(REPLY_TIMEOUT);
    for (k, batch) in samples.chunks(5).enumerate() {
        let detections = stream
            .detect(first_seq + k as u64, batch.to_vec())
            .await
            .unwrap_or_else(|e| panic!("{vehicle}: detections: {e}"));
        assert_eq!(detections.len(), batch.len());
    }
    stream.finish().await.expect("the stream ends cleanly");
    accepted
}

/// The vehicle ids with a session on the replica behind `clients`.
pub async fn sessions_on(clients: &Clients) -> Vec<String> {
    clients
        .detection
        .clone()
        .list_sessions(v1::ListSessionsRequest::default())
        .await
        .expect("ListSessions")
        .into_inner()
        .sessions
        .into_iter()
        .map(|s| s.vehicle_id)
        .collect()
}
