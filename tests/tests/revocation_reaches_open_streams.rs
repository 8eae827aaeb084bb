//! A change of the identity files reaches the calls already open, black-box. Once a changed roles
//! file or token file is in force (a new call is answered by it), every open call of a caller it
//! no longer admits ends within 10 s: a revoked token's StreamDetect and StreamDetectFleet, and a
//! revoked vehicle certificate's StreamDetect, with UNAUTHENTICATED saying the credential is no
//! longer accepted; a revoked operator's WatchAlarms and WatchIncidents the same way, without the
//! alarm raised after the revocation; the old admin token's calls once the token file holds a new
//! one; a demoted operator's watch, and a gateway's stream for a vehicle it no longer serves, with
//! PERMISSION_DENIED. Callers the change leaves admitted keep their calls, and a gateway's open
//! fleet stream is served under its new vehicles. The other calls that stay open end the same
//! way: a revoked operator's WatchJob (without the job's next change) and WaitOperation, and a
//! revoked admin's UploadDataset (nothing stored).

use std::time::Duration;

use spoofwatch_proto::longrunning;
use spoofwatch_proto::v1;
use spoofwatch_tests::pki::TestCa;
use spoofwatch_tests::{
    ADMIN_TOKEN, Clients, ConnectOptions, Connection, DetectStream, REPLY_TIMEOUT, TestServer,
    normal_drive, start_with_roles, stream_frozen_fix_drive, telemetry_csv, test_config,
    token_sha256, track_samples, training_fleet, training_request, upload_tracks, with_certificate,
};
use tokio::sync::mpsc;
use tokio::time::Instant;
use tokio_stream::wrappers::ReceiverStream;
use tonic::{Code, Status, Streaming};

/// How long an open call may take to end once the change is in force for new calls.
const END_WITHIN: Duration = Duration::from_secs(10);
/// How long the server may take to put a changed file in force (it looks every 2 s).
const IN_FORCE_WITHIN: Duration = Duration::from_secs(20);

/// Two gateways of `gw-` vehicles and two operators, by token; the tokens in `deny` revoked.
fn token_roles(deny: &[&str]) -> String {
    let deny: Vec<String> = deny
        .iter()
        .map(|t| format!("\"{}\"", token_sha256(t)))
        .collect();
    format!(
        "[tokens]\n\
         \"{}\" = {{ name = \"bridge\", role = \"gateway\", vehicle_prefixes = [\"gw-\"] }}\n\
         \"{}\" = {{ name = \"bridge-2\", role = \"gateway\", vehicle_prefixes = [\"gw-\"] }}\n\
         \"{}\" = {{ name = \"dashboard\", role = \"operator\" }}\n\
         \"{}\" = {{ name = \"dashboard-2\", role = \"operator\" }}\n\
         [deny]\ntokens_sha256 = [{}]\n",
        token_sha256("gateway-token"),
        token_sha256("other-gateway-token"),
        token_sha256("operator-token"),
        token_sha256("other-operator-token"),
        deny.join(", "),
    )
}

async fn connect(server: &TestServer, options: ConnectOptions) -> Connection {
    Connection::connect_with(&server.url(), &options)
        .await
        .expect("connected")
}

async fn with_token(server: &TestServer, token: &str) -> Connection {
    connect(server, ConnectOptions::with_token(Some(token.into()))).await
}

/// The samples of `vehicle`'s 10 s drive: the first five are sent on opening, the rest later.
fn drive(vehicle: &str) -> Vec<v1::Sample> {
    track_samples(&normal_drive(vehicle, 10.0, 1))
}

/// A StreamDetect of `vehicle` (starting over) that has scored its drive's first five samples.
async fn detecting(connection: &Connection, vehicle: &str) -> DetectStream {
    let (stream, _) = DetectStream::start(connection, vehicle, "", true)
        .await
        .unwrap_or_else(|e| panic!("{vehicle}: the stream opens: {e}"));
    let mut stream = stream.with_reply_timeout(REPLY_TIMEOUT);
    stream
        .detect(1, drive(vehicle)[..5].to_vec())
        .await
        .unwrap_or_else(|e| panic!("{vehicle}: detections: {e}"));
    stream
}

/// A fleet message of `vehicles` and their samples.
fn fleet_message(seq: u64, vehicles: &[(&str, &[v1::Sample])]) -> v1::FleetBatch {
    v1::FleetBatch {
        seq,
        vehicles: vehicles
            .iter()
            .map(|(id, samples)| v1::VehicleSamples {
                vehicle_id: id.to_string(),
                samples: samples.to_vec(),
                reset: seq == 1,
                ..Default::default()
            })
            .collect(),
    }
}

/// A StreamDetectFleet call (kept open by the sender) whose first message, `vehicle`'s first five
/// samples, was scored.
async fn fleet_detecting(
    connection: &Connection,
    vehicle: &str,
) -> (mpsc::Sender<v1::FleetBatch>, Streaming<v1::FleetDetections>) {
    let (tx, rx) = mpsc::channel(4);
    let first = fleet_message(1, &[(vehicle, &drive(vehicle)[..5])]);
    tx.send(first).await.expect("queued");
    let mut replies = connection
        .detection()
        .stream_detect_fleet(ReceiverStream::new(rx))
        .await
        .expect("the call is accepted")
        .into_inner();
    let reply = next_reply(&mut replies).await;
    assert!(
        reply.vehicles.iter().all(|v| v.error.is_none()),
        "{reply:?}"
    );
    (tx, replies)
}

async fn next_reply<T>(replies: &mut Streaming<T>) -> T {
    tokio::time::timeout(REPLY_TIMEOUT, replies.message())
        .await
        .expect("a reply in time")
        .expect("a reply, not the call's end")
        .expect("a reply, not the call's end")
}

/// A watch with no cursor, past its first event (CAUGHT_UP: nothing to replay).
async fn caught_up<T: std::fmt::Debug>(
    call: Result<tonic::Response<Streaming<T>>, Status>,
    is_caught_up: impl Fn(&T) -> bool,
) -> Streaming<T> {
    let mut events = call.expect("the watch is accepted").into_inner();
    let first = next_reply(&mut events).await;
    assert!(is_caught_up(&first), "{first:?}");
    events
}

async fn watching_alarms(connection: &Connection) -> Streaming<v1::AlarmEvent> {
    let call = connection
        .alarms()
        .watch_alarms(v1::WatchAlarmsRequest::default())
        .await;
    caught_up(call, |e| e.kind == v1::AlarmEventKind::CaughtUp as i32).await
}

async fn watching_incidents(connection: &Connection) -> Streaming<v1::IncidentEvent> {
    let call = connection
        .alarms()
        .watch_incidents(v1::WatchIncidentsRequest::default())
        .await;
    caught_up(call, |e| e.kind == v1::IncidentEventKind::CaughtUp as i32).await
}

/// Reads `replies` until the call ends, which must be within [`END_WITHIN`]: what it still sent,
/// and the status it ended with.
async fn read_to_end<T: std::fmt::Debug>(replies: &mut Streaming<T>) -> (Vec<T>, Status) {
    let deadline = Instant::now() + END_WITHIN;
    let mut sent = Vec::new();
    loop {
        let Ok(next) = tokio::time::timeout_at(deadline, replies.message()).await else {
            panic!(
                "the call did not end within 10 s of the change being in force; it sent {sent:?}"
            )
        };
        match next {
            Ok(Some(message)) => sent.push(message),
            Ok(None) => return (sent, Status::ok("")),
            Err(status) => return (sent, status),
        }
    }
}

/// The status a StreamDetect ends with, which must be within [`END_WITHIN`] and before any other
/// reply.
async fn detect_stream_end(stream: &mut DetectStream) -> Status {
    let next = tokio::time::timeout(END_WITHIN, stream.next())
        .await
        .expect("the stream ends within 10 s of the change being in force");
    match next {
        Err(error) => error.status().expect("a gRPC status").clone(),
        Ok(reply) => panic!("expected the stream's end, got {reply:?}"),
    }
}

/// Asserts that an open call ended because its credential was revoked.
fn assert_revoked(status: &Status, call: &str) {
    assert_eq!(status.code(), Code::Unauthenticated, "{call}: {status:?}");
    assert!(
        status.message().contains("no longer accepted") && status.message().contains("revoked"),
        "{call}: {}",
        status.message()
    );
}

/// Waits until `probe` (a new call) is answered with `wanted`: the changed file is in force.
async fn until_answered(probe: impl AsyncFn() -> Code, wanted: Code) {
    let deadline = Instant::now() + IN_FORCE_WITHIN;
    loop {
        let answer = probe().await;
        if answer == wanted {
            return;
        }
        assert!(
            Instant::now() < deadline,
            "the changed file was not in force within {IN_FORCE_WITHIN:?}: {answer:?}, not {wanted:?}"
        );
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
}

/// A new ListModels call's answer.
async fn list_models(connection: &Connection) -> Code {
    let answer = connection
        .models()
        .list_models(v1::ListModelsRequest::default())
        .await;
    answer.map_or_else(|status| status.code(), |_| Code::Ok)
}

/// A new Detect call's answer, for `vehicle`.
async fn detect(connection: &Connection, vehicle: &str) -> Code {
    let answer = connection
        .detection()
        .detect(v1::DetectRequest {
            vehicle_id: vehicle.into(),
            samples: drive(vehicle)[..2].to_vec(),
            ..Default::default()
        })
        .await;
    answer.map_or_else(|status| status.code(), |_| Code::Ok)
}

/// The first ONSET of `vehicle` a watch sends (other events are skipped).
async fn onset_of(events: &mut Streaming<v1::AlarmEvent>, vehicle: &str) -> v1::AlarmEvent {
    loop {
        let event = next_reply(events).await;
        if event.kind == v1::AlarmEventKind::Onset as i32
            && event
                .alarm
                .as_ref()
                .is_some_and(|a| a.vehicle_id == vehicle)
        {
            return event;
        }
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn revoked_tokens_end_their_open_streams_and_watches_before_a_later_alarm() {
    let dir = tempfile::tempdir().expect("temp dir");
    let server = start_with_roles(dir.path(), &token_roles(&[]), None).await;
    let gateway = with_token(&server, "gateway-token").await;
    let other_gateway = with_token(&server, "other-gateway-token").await;
    let operator = with_token(&server, "operator-token").await;
    let other_operator = with_token(&server, "other-operator-token").await;
    let mut revoked_stream = detecting(&gateway, "gw-1").await;
    let mut kept_stream = detecting(&other_gateway, "gw-2").await;
    let (fleet_tx, mut revoked_fleet) = fleet_detecting(&gateway, "gw-3").await;
    let mut revoked_alarms = watching_alarms(&operator).await;
    let mut revoked_incidents = watching_incidents(&operator).await;
    let mut kept_alarms = watching_alarms(&other_operator).await;

    std::fs::write(
        dir.path().join("roles.toml"),
        token_roles(&["gateway-token", "operator-token"]),
    )
    .expect("roles file rewritten");
    until_answered(async || list_models(&gateway).await, Code::Unauthenticated).await;

    // An alarm raised once the revocation is in force reaches the operator still admitted ...
    let admin = Clients::new(with_token(&server, ADMIN_TOKEN).await);
    assert!(!stream_frozen_fix_drive(&admin, "car-late").await.is_empty());
    onset_of(&mut kept_alarms, "car-late").await;
    // ... and not the revoked one, whose watches end with nothing after CAUGHT_UP.
    let (sent, status) = read_to_end(&mut revoked_alarms).await;
    assert!(
        sent.is_empty(),
        "WatchAlarms sent after the revocation: {sent:?}"
    );
    assert_revoked(&status, "WatchAlarms");
    let (sent, status) = read_to_end(&mut revoked_incidents).await;
    assert!(sent.is_empty(), "WatchIncidents sent: {sent:?}");
    assert_revoked(&status, "WatchIncidents");
    // The revoked gateway's streams ended too; the other gateway's goes on.
    assert_revoked(
        &detect_stream_end(&mut revoked_stream).await,
        "StreamDetect",
    );
    let (sent, status) = read_to_end(&mut revoked_fleet).await;
    assert!(sent.is_empty(), "StreamDetectFleet sent: {sent:?}");
    assert_revoked(&status, "StreamDetectFleet");
    let rest = drive("gw-2")[5..].to_vec();
    let detections = kept_stream
        .detect(2, rest.clone())
        .await
        .expect("the stream of a caller still admitted goes on");
    assert_eq!(detections.len(), rest.len());
    kept_stream.finish().await.expect("it ends with OK");

    drop((fleet_tx, revoked_stream, kept_alarms, admin));
    drop((gateway, other_gateway, operator, other_operator));
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_revoked_vehicle_certificate_ends_its_open_stream() {
    let dir = tempfile::tempdir().expect("temp dir");
    let ca = TestCa::new(dir.path(), "fleet");
    let admin = ca.client(dir.path(), "fleet-admin");
    let roles = "[certificates]\n\"fleet-admin\" = { role = \"admin\" }\n";
    let server = start_with_roles(dir.path(), roles, Some((&ca, &admin))).await;
    let truck7 = connect(
        &server,
        with_certificate(&ca, &ca.client(dir.path(), "truck-7")),
    )
    .await;
    let truck8 = connect(
        &server,
        with_certificate(&ca, &ca.client(dir.path(), "truck-8")),
    )
    .await;
    let mut revoked = detecting(&truck7, "truck-7").await;
    let mut kept = detecting(&truck8, "truck-8").await;

    std::fs::write(
        dir.path().join("roles.toml"),
        format!("{roles}[deny]\ncertificates = [\"truck-7\"]\n"),
    )
    .expect("roles file rewritten");
    until_answered(async || list_models(&truck7).await, Code::Unauthenticated).await;

    let status = detect_stream_end(&mut revoked).await;
    assert_revoked(&status, "StreamDetect");
    assert!(status.message().contains("\"truck-7\""), "{status:?}");
    kept.detect(2, drive("truck-8")[5..].to_vec())
        .await
        .expect("truck-8's stream goes on");
    kept.finish().await.expect("it ends with OK");
    drop((revoked, truck7, truck8));
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_new_admin_token_file_ends_the_old_tokens_open_calls() {
    let dir = tempfile::tempdir().expect("temp dir");
    let token_file = dir.path().join("admin-token");
    std::fs::write(&token_file, "old-admin-token\n").expect("token file written");
    let mut config = test_config(dir.path());
    config.auth_token_file = Some(token_file.clone());
    let old = ConnectOptions::with_token(Some("old-admin-token".into()));
    let server = TestServer::start_for(config, &old).await;
    let admin = connect(&server, old).await;
    let mut stream = detecting(&admin, "car-1").await;
    let mut alarms = watching_alarms(&admin).await;

    std::fs::write(&token_file, "new-admin-token\n").expect("token file rewritten");
    until_answered(async || list_models(&admin).await, Code::Unauthenticated).await;

    for (call, status) in [
        ("StreamDetect", detect_stream_end(&mut stream).await),
        ("WatchAlarms", read_to_end(&mut alarms).await.1),
    ] {
        assert_eq!(status.code(), Code::Unauthenticated, "{call}: {status:?}");
        assert!(
            status.message().contains("no longer accepted"),
            "{call}: {status:?}"
        );
    }
    let new = with_token(&server, "new-admin-token").await;
    assert_eq!(list_models(&new).await, Code::Ok);
    drop((stream, admin, new));
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_demoted_callers_open_calls_end_with_permission_denied_and_a_gateway_streams_on_under_its_new_vehicles()
 {
    let dir = tempfile::tempdir().expect("temp dir");
    let server = start_with_roles(dir.path(), &token_roles(&[]), None).await;
    let gateway = with_token(&server, "gateway-token").await;
    let operator = with_token(&server, "operator-token").await;
    let mut stream = detecting(&gateway, "gw-1").await;
    let (fleet_tx, mut fleet) = fleet_detecting(&gateway, "gw-3").await;
    let mut alarms = watching_alarms(&operator).await;

    // The bridge now serves `eu-` vehicles; the dashboard becomes a gateway, which may not read.
    std::fs::write(
        dir.path().join("roles.toml"),
        token_roles(&[])
            .replacen("[\"gw-\"]", "[\"eu-\"]", 1)
            .replace(
                "name = \"dashboard\", role = \"operator\"",
                "name = \"dashboard\", role = \"gateway\", all_vehicles = true",
            ),
    )
    .expect("roles file rewritten");
    until_answered(async || detect(&gateway, "eu-probe").await, Code::Ok).await;

    let status = detect_stream_end(&mut stream).await;
    assert_eq!(status.code(), Code::PermissionDenied, "{status:?}");
    assert!(status.message().contains("\"gw-1\""), "{status:?}");
    let (sent, status) = read_to_end(&mut alarms).await;
    assert!(
        sent.is_empty(),
        "WatchAlarms sent after the demotion: {sent:?}"
    );
    assert_eq!(status.code(), Code::PermissionDenied, "{status:?}");
    assert!(status.message().contains("WatchAlarms"), "{status:?}");

    // The fleet stream names its vehicles per message: it goes on, under the new vehicles.
    let message = fleet_message(
        2,
        &[("gw-3", &drive("gw-3")[5..]), ("eu-5", &drive("eu-5")[..5])],
    );
    fleet_tx.send(message).await.expect("queued");
    let reply = next_reply(&mut fleet).await;
    let refused = reply.vehicles[0].error.as_ref().expect("gw-3 is refused");
    assert_eq!(
        Code::from(refused.code),
        Code::PermissionDenied,
        "{reply:?}"
    );
    assert!(reply.vehicles[1].error.is_none(), "{reply:?}");
    assert_eq!(reply.vehicles[1].detections.len(), 5);
    drop(fleet_tx);
    let (sent, status) = read_to_end(&mut fleet).await;
    assert!(sent.is_empty() && status.code() == Code::Ok, "{status:?}");

    drop((stream, gateway, operator));
    server.stop().await;
}

/// [`token_roles`] with an admin token `console-token` besides the single admin token.
fn token_roles_with_console(deny: &[&str]) -> String {
    token_roles(deny).replacen(
        "[deny]",
        &format!(
            "\"{}\" = {{ name = \"console\", role = \"admin\" }}\n[deny]",
            token_sha256("console-token")
        ),
        1,
    )
}

fn job_state(metadata: &v1::JobMetadata) -> v1::JobState {
    v1::JobState::try_from(metadata.state).expect("a known job state")
}

async fn watching_job(connection: &Connection, name: &str) -> Streaming<v1::JobMetadata> {
    let mut updates = connection
        .training()
        .watch_job(v1::WatchJobRequest {
            name: name.to_string(),
        })
        .await
        .expect("WatchJob is accepted")
        .into_inner();
    let first = next_reply(&mut updates).await;
    assert!(
        matches!(
            job_state(&first),
            v1::JobState::Queued | v1::JobState::Running
        ),
        "{first:?}"
    );
    updates
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_revoked_callers_job_watch_wait_and_upload_end_before_the_jobs_next_change() {
    let dir = tempfile::tempdir().expect("temp dir");
    let roles_file = dir.path().join("roles.toml");
    std::fs::write(&roles_file, token_roles_with_console(&[])).expect("roles file written");
    let mut config = test_config(dir.path());
    config.roles_file = Some(roles_file.clone());
    config.auth_token = Some(ADMIN_TOKEN.into());
    // One job runs at a time: the second stays queued until it is cancelled.
    config.max_running_jobs = 1;
    let server = TestServer::start_for(
        config,
        &ConnectOptions::with_token(Some(ADMIN_TOKEN.into())),
    )
    .await;
    let mut admin = Clients::new(with_token(&server, ADMIN_TOKEN).await);
    // Twenty copies of the training fleet (40,000 rows): each job trains for seconds at least
    // (early stopping waits 12 epochs), so the second is still queued or running when it is
    // cancelled below.
    let fleet: Vec<_> = (0..20)
        .flat_map(|copy| {
            training_fleet().into_iter().map(move |mut track| {
                track.vehicle_id = format!("{}-{copy}", track.vehicle_id);
                track
            })
        })
        .collect();
    let dataset = upload_tracks(&mut admin, "fleet", &fleet).await;
    let mut jobs = Vec::new();
    for epochs in [200, 200] {
        let job = admin
            .training
            .create_training_job(training_request(&dataset.name, epochs, false))
            .await
            .expect("the job is queued")
            .into_inner();
        jobs.push(job.name);
    }
    // Queued behind the first (one job runs at a time), or running once the first stopped early.
    let queued = jobs[1].clone();

    let operator = with_token(&server, "operator-token").await;
    let other_operator = with_token(&server, "other-operator-token").await;
    let mut revoked_watch = watching_job(&operator, &queued).await;
    let mut kept_watch = watching_job(&other_operator, &queued).await;
    let mut operations = operator.operations();
    let wait_for = queued.clone();
    let revoked_wait = tokio::spawn(async move {
        operations
            .wait_operation(longrunning::WaitOperationRequest {
                name: wait_for,
                timeout: Some(prost_types::Duration {
                    seconds: 120,
                    nanos: 0,
                }),
            })
            .await
    });
    // The console admin's upload: its header and a first chunk sent, the rest to come.
    let console = with_token(&server, "console-token").await;
    let (upload_tx, upload_rx) = mpsc::channel(4);
    let csv = telemetry_csv(&training_fleet());
    for kind in [
        v1::upload_dataset_request::Kind::Header(v1::UploadDatasetHeader {
            display_name: "half an upload".into(),
        }),
        v1::upload_dataset_request::Kind::CsvChunk(csv[..csv.len() / 2].to_vec()),
    ] {
        upload_tx
            .send(v1::UploadDatasetRequest { kind: Some(kind) })
            .await
            .expect("queued");
    }
    let mut datasets = console.datasets();
    let upload = tokio::spawn(async move {
        datasets
            .upload_dataset(ReceiverStream::new(upload_rx))
            .await
    });

    std::fs::write(
        &roles_file,
        token_roles_with_console(&["operator-token", "console-token"]),
    )
    .expect("roles file rewritten");
    until_answered(async || list_models(&operator).await, Code::Unauthenticated).await;

    // The job's next change, once the revocation is in force, reaches the watcher still admitted
    // and not the revoked one.
    admin
        .operations
        .cancel_operation(longrunning::CancelOperationRequest {
            name: queued.clone(),
        })
        .await
        .expect("the queued job is cancelled");
    loop {
        let update = next_reply(&mut kept_watch).await;
        if job_state(&update) == v1::JobState::Cancelled {
            break;
        }
    }
    // (It may have sent the job's start or epochs before the change: not its cancellation.)
    let (sent, status) = read_to_end(&mut revoked_watch).await;
    assert!(
        sent.iter()
            .all(|update| job_state(update) != v1::JobState::Cancelled),
        "WatchJob sent after the revocation: {sent:?}"
    );
    assert_revoked(&status, "WatchJob");
    let waited = tokio::time::timeout(END_WITHIN, revoked_wait)
        .await
        .expect("the wait ends")
        .expect("the task ran");
    assert_revoked(&waited.expect_err("the wait is ended"), "WaitOperation");
    let uploaded = tokio::time::timeout(END_WITHIN, upload)
        .await
        .expect("the upload ends")
        .expect("the task ran");
    assert_revoked(&uploaded.expect_err("the upload is ended"), "UploadDataset");
    drop(upload_tx);
    let stored = admin
        .datasets
        .list_datasets(v1::ListDatasetsRequest::default())
        .await
        .expect("ListDatasets")
        .into_inner()
        .datasets;
    assert_eq!(
        stored.len(),
        1,
        "nothing of the ended upload is stored: {stored:?}"
    );

    // The first job stops here, if it has not stopped early.
    let _ = admin
        .operations
        .cancel_operation(longrunning::CancelOperationRequest {
            name: jobs[0].clone(),
        })
        .await;
    drop((admin, operator, other_operator, console));
    server.stop().await;
}
