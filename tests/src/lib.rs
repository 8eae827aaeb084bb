//! Support for the black-box tests: start the real server in-process on a loopback port, connect
//! gRPC clients, build test inputs with `spoofwatch-core`, and read replies with a bound on waiting.
//!
//! Tests talk to the server only through gRPC. The recipe follows tonic's own tests: bind
//! `127.0.0.1:0`, spawn `serve` with a oneshot shutdown, poll health instead of sleeping, and drop
//! clients before triggering shutdown (an open stream holds the connection and delays the drain).

use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::time::Duration;

use spoofwatch_core::data::telemetry::write_tracks;
use spoofwatch_core::sample::{Sample, Track};
use spoofwatch_core::scenario::{AttackKind, AttackSpec, DriveSpec, inject, simulate_drive};
use spoofwatch_proto::longrunning::operations_client::OperationsClient;
use spoofwatch_proto::v1;
use spoofwatch_proto::v1::dataset_service_client::DatasetServiceClient;
use spoofwatch_proto::v1::detection_service_client::DetectionServiceClient;
use spoofwatch_proto::v1::model_service_client::ModelServiceClient;
use spoofwatch_proto::v1::stream_detect_request::Kind as RequestKind;
use spoofwatch_proto::v1::stream_detect_response::Kind as ResponseKind;
use spoofwatch_proto::v1::training_service_client::TrainingServiceClient;
use spoofwatch_server::{Config, ServerError, serve};
use tokio::sync::{mpsc, oneshot};
use tokio::task::JoinHandle;
use tokio_stream::wrappers::ReceiverStream;
use tonic::transport::Channel;
use tonic::{Code, Status, Streaming};
use tonic_health::pb::HealthCheckRequest;
use tonic_health::pb::health_check_response::ServingStatus;
use tonic_health::pb::health_client::HealthClient;

/// Longest a test waits for one reply before failing (generous: debug builds on 2 shared cores).
pub const REPLY_TIMEOUT: Duration = Duration::from_secs(60);
/// Longest a test waits for the server to report SERVING.
const READY_TIMEOUT: Duration = Duration::from_secs(30);

/// A server configuration for tests: a database file in `dir`, a short shutdown grace.
pub fn test_config(dir: &Path) -> Config {
    let mut config = Config::with_database(database_path(dir).display().to_string());
    config.shutdown_grace_secs = 2;
    config
}

/// Where [`test_config`] puts the database inside `dir`.
pub fn database_path(dir: &Path) -> PathBuf {
    dir.join("spoofwatch.db")
}

/// A server running in this process.
pub struct TestServer {
    /// The loopback address it listens on.
    pub addr: SocketAddr,
    shutdown: Option<oneshot::Sender<()>>,
    handle: Option<JoinHandle<Result<(), ServerError>>>,
}

impl TestServer {
    /// Binds a free loopback port, spawns [`serve`] and waits until health reports SERVING.
    pub async fn start(config: Config) -> TestServer {
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0")
            .await
            .expect("bind a loopback port");
        let addr = listener.local_addr().expect("local address");
        let (shutdown, signal) = oneshot::channel::<()>();
        let handle = tokio::spawn(serve(config, listener, async {
            let _ = signal.await;
        }));
        let server = TestServer {
            addr,
            shutdown: Some(shutdown),
            handle: Some(handle),
        };
        server.wait_until_serving().await;
        server
    }

    /// A new connection to the server.
    pub async fn channel(&self) -> Channel {
        connect(self.addr).await
    }

    /// Polls `grpc.health.v1.Health/Check` (overall status) until SERVING.
    async fn wait_until_serving(&self) {
        wait_until_serving(self.addr, READY_TIMEOUT).await;
    }

    /// Fires the shutdown signal (the server starts draining); idempotent.
    pub fn trigger_shutdown(&mut self) {
        if let Some(shutdown) = self.shutdown.take() {
            let _ = shutdown.send(());
        }
    }

    /// Triggers shutdown and waits (at most `bound`) for `serve` to return; panics past the bound.
    pub async fn stop_within(mut self, bound: Duration) -> Result<(), ServerError> {
        self.trigger_shutdown();
        let handle = self
            .handle
            .take()
            .expect("the server task is only joined once");
        tokio::time::timeout(bound, handle)
            .await
            .expect("serve() returned within the shutdown bound")
            .expect("the server task did not panic")
    }

    /// Triggers shutdown and waits for `serve` to return successfully.
    pub async fn stop(self) {
        self.stop_within(Duration::from_secs(30))
            .await
            .expect("serve() ended without error");
    }
}

impl Drop for TestServer {
    fn drop(&mut self) {
        // A test that failed midway must not leave a server running in the other tests' runtime.
        self.trigger_shutdown();
        if let Some(handle) = self.handle.take() {
            handle.abort();
        }
    }
}

/// Connects a channel to `addr` (plaintext HTTP/2).
pub async fn connect(addr: SocketAddr) -> Channel {
    Channel::from_shared(format!("http://{addr}"))
        .expect("a valid URI")
        .connect()
        .await
        .expect("connect to the test server")
}

/// Polls health `Check("")` until SERVING or `bound` passes (then panics).
pub async fn wait_until_serving(addr: SocketAddr, bound: Duration) {
    let deadline = tokio::time::Instant::now() + bound;
    loop {
        if let Ok(channel) = Channel::from_shared(format!("http://{addr}"))
            .expect("a valid URI")
            .connect()
            .await
        {
            let status = HealthClient::new(channel)
                .check(HealthCheckRequest {
                    service: String::new(),
                })
                .await
                .map(|r| r.into_inner().status);
            if matches!(status, Ok(s) if s == ServingStatus::Serving as i32) {
                return;
            }
        }
        assert!(
            tokio::time::Instant::now() < deadline,
            "the server at {addr} did not report SERVING within {bound:?}"
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

/// Typed clients over one channel.
#[derive(Clone)]
pub struct Clients {
    pub detection: DetectionServiceClient<Channel>,
    pub models: ModelServiceClient<Channel>,
    pub datasets: DatasetServiceClient<Channel>,
    pub training: TrainingServiceClient<Channel>,
    pub operations: OperationsClient<Channel>,
    pub health: HealthClient<Channel>,
}

impl Clients {
    /// Clients of every service over `channel`.
    pub fn new(channel: Channel) -> Self {
        Self {
            detection: DetectionServiceClient::new(channel.clone()),
            models: ModelServiceClient::new(channel.clone()),
            datasets: DatasetServiceClient::new(channel.clone()),
            training: TrainingServiceClient::new(channel.clone()),
            operations: OperationsClient::new(channel.clone()),
            health: HealthClient::new(channel),
        }
    }

    /// Clients connected to `server`.
    pub async fn of(server: &TestServer) -> Self {
        Self::new(server.channel().await)
    }
}

/// A core sample on the wire.
pub fn sample_to_proto(s: &Sample) -> v1::Sample {
    v1::Sample {
        timestamp_s: s.timestamp_s,
        latitude_deg: s.latitude_deg,
        longitude_deg: s.longitude_deg,
        speed_mps: s.speed_mps,
        heading_deg: s.heading_deg,
        position_std_m: s.position_std_m,
        speed_std_mps: s.speed_std_mps,
        heading_std_deg: s.heading_std_deg,
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
        .expect("the upload is accepted")
        .into_inner()
}

/// An open `StreamDetect` call: requests go in through a channel, replies are read with a bound.
pub struct DetectStream {
    requests: mpsc::Sender<v1::StreamDetectRequest>,
    replies: Streaming<v1::StreamDetectResponse>,
}

/// The start message of a stream.
pub fn start_message(vehicle_id: &str, model: &str, reset: bool) -> v1::StreamDetectRequest {
    v1::StreamDetectRequest {
        kind: Some(RequestKind::Start(v1::SessionStart {
            vehicle_id: vehicle_id.to_string(),
            model: model.to_string(),
            reset,
        })),
    }
}

/// A batch message.
pub fn batch_message(seq: u64, samples: Vec<v1::Sample>) -> v1::StreamDetectRequest {
    v1::StreamDetectRequest {
        kind: Some(RequestKind::Batch(v1::SampleBatch { seq, samples })),
    }
}

impl DetectStream {
    /// Opens a call whose first message is `first`; `Err` when the call itself is refused.
    pub async fn open(
        client: &mut DetectionServiceClient<Channel>,
        first: v1::StreamDetectRequest,
    ) -> Result<DetectStream, Status> {
        let (requests, outbound) = mpsc::channel(16);
        requests
            .send(first)
            .await
            .expect("the request channel is open");
        let replies = client
            .stream_detect(ReceiverStream::new(outbound))
            .await?
            .into_inner();
        Ok(DetectStream { requests, replies })
    }

    /// Opens a session stream and returns it with its `SessionAccepted`.
    pub async fn start(
        client: &mut DetectionServiceClient<Channel>,
        vehicle_id: &str,
        model: &str,
    ) -> (DetectStream, v1::SessionAccepted) {
        let mut stream = Self::open(client, start_message(vehicle_id, model, false))
            .await
            .expect("the call is accepted");
        match stream.next().await {
            Ok(Some(ResponseKind::Accepted(accepted))) => (stream, accepted),
            other => panic!("expected SessionAccepted for {vehicle_id}, got {other:?}"),
        }
    }

    /// Sends one message.
    pub async fn send(&self, message: v1::StreamDetectRequest) {
        self.requests
            .send(message)
            .await
            .expect("the request stream is open");
    }

    /// Sends a batch of samples.
    pub async fn send_batch(&self, seq: u64, samples: Vec<v1::Sample>) {
        self.send(batch_message(seq, samples)).await;
    }

    /// The next reply: `Ok(None)` when the call ended with OK, `Err` with its status otherwise.
    /// Panics when nothing arrives within [`REPLY_TIMEOUT`].
    pub async fn next(&mut self) -> Result<Option<ResponseKind>, Status> {
        let message = tokio::time::timeout(REPLY_TIMEOUT, self.replies.message())
            .await
            .expect("a reply within the timeout")?;
        Ok(message.map(|m| m.kind.expect("every reply has a kind")))
    }

    /// Sends a batch and returns its detections (panics on anything else).
    pub async fn detect(&mut self, seq: u64, samples: Vec<v1::Sample>) -> Vec<v1::Detection> {
        let count = samples.len();
        self.send_batch(seq, samples).await;
        match self.next().await {
            Ok(Some(ResponseKind::Detections(batch))) => {
                assert_eq!(batch.seq, seq, "the reply echoes the batch's seq");
                assert_eq!(batch.detections.len(), count, "one detection per sample");
                batch.detections
            }
            other => panic!("expected detections for seq {seq}, got {other:?}"),
        }
    }

    /// Sends a batch and returns the ItemError it must cause (panics on anything else).
    pub async fn expect_item_error(
        &mut self,
        seq: u64,
        samples: Vec<v1::Sample>,
    ) -> tonic_types::Status {
        self.send_batch(seq, samples).await;
        match self.next().await {
            Ok(Some(ResponseKind::ItemError(error))) => {
                assert_eq!(error.seq, seq, "the ItemError echoes the batch's seq");
                error.status.expect("an ItemError carries a status")
            }
            other => panic!("expected an ItemError for seq {seq}, got {other:?}"),
        }
    }

    /// Closes the client side (half-close); the server ends the call with OK.
    pub fn close(self) -> Streaming<v1::StreamDetectResponse> {
        drop(self.requests);
        self.replies
    }
}

/// Reads replies until the call ends and returns its final status code (OK when it ended cleanly).
pub async fn final_code(stream: &mut DetectStream) -> Code {
    loop {
        match stream.next().await {
            Ok(Some(_)) => continue,
            Ok(None) => return Code::Ok,
            Err(status) => return status.code(),
        }
    }
}

/// The field violations of a google.rpc.Status carrying a BadRequest detail.
pub fn field_violations(status: &tonic_types::Status) -> Vec<(String, String)> {
    use prost::Message;
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

/// Drains a server-streaming model export into the artifact's bytes.
pub async fn export_model(models: &mut ModelServiceClient<Channel>, name: &str) -> Vec<u8> {
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

/// The name of the active model (exactly one is active).
pub async fn active_model(models: &mut ModelServiceClient<Channel>) -> v1::Model {
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
