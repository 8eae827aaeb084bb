//! Who may do what, black-box: every RPC × every role (vehicle, gateway, operator, admin, and the
//! single admin token) from a table, with token identities; vehicles outside a caller's scope are
//! PERMISSION_DENIED on every detection call; under mutual TLS a certificate is the vehicle its
//! CN names unless the roles file says otherwise, a revoked one is refused, and a changed roles
//! file applies without a restart. Refusals are counted in the metrics.

use std::time::Duration;

use spoofwatch_proto::longrunning;
use spoofwatch_proto::v1;
use spoofwatch_tests::pki::{CertFiles, TestCa};
use spoofwatch_tests::{
    ConnectOptions, Connection, TestServer, normal_drive, start_with_roles, token_sha256,
    track_samples, with_certificate,
};
use tokio_stream::StreamExt;
use tonic::Code;

/// The roles file of the token tests: one token per role.
fn token_roles() -> String {
    format!(
        "[tokens]\n\
         \"{}\" = {{ name = \"car-1\", role = \"vehicle\" }}\n\
         \"{}\" = {{ name = \"bridge\", role = \"gateway\", vehicle_prefixes = [\"gw-\"] }}\n\
         \"{}\" = {{ name = \"dashboard\", role = \"operator\" }}\n\
         \"{}\" = {{ name = \"second-admin\", role = \"admin\" }}\n",
        token_sha256("vehicle-token"),
        token_sha256("gateway-token"),
        token_sha256("operator-token"),
        token_sha256("admin-token"),
    )
}

async fn connect(server: &TestServer, options: ConnectOptions) -> Connection {
    Connection::connect_with(&server.url(), &options)
        .await
        .expect("connected")
}

fn code<T>(result: Result<T, tonic::Status>) -> Code {
    result.map_or_else(|status| status.code(), |_| Code::Ok)
}

fn samples(vehicle: &str) -> Vec<v1::Sample> {
    track_samples(&normal_drive(vehicle, 5.0, 1))
}

/// What a StreamDetect call for `vehicle` is answered: the call's refusal, or its first reply's
/// (the session accepted, or the stream's end status).
async fn stream_detect(connection: &Connection, vehicle: &str) -> Code {
    let start = v1::StreamDetectRequest {
        kind: Some(v1::stream_detect_request::Kind::Start(v1::SessionStart {
            vehicle_id: vehicle.into(),
            ..Default::default()
        })),
    };
    let (tx, rx) = tokio::sync::mpsc::channel(4);
    tx.send(start).await.expect("queued");
    let call = connection
        .detection()
        .stream_detect(tokio_stream::wrappers::ReceiverStream::new(rx))
        .await;
    let mut replies = match call {
        Ok(response) => response.into_inner(),
        Err(status) => return status.code(),
    };
    let first = tokio::time::timeout(Duration::from_secs(30), replies.next())
        .await
        .expect("a first reply in time");
    drop(tx);
    match first {
        Some(Ok(_)) => Code::Ok,
        Some(Err(status)) => status.code(),
        None => Code::Ok,
    }
}

/// A StreamDetectFleet message with one vehicle: the call's refusal, or that vehicle's status.
async fn fleet_detect(connection: &Connection, vehicle: &str) -> Code {
    let batch = v1::FleetBatch {
        seq: 1,
        vehicles: vec![v1::VehicleSamples {
            vehicle_id: vehicle.into(),
            samples: samples(vehicle),
            // Starts over: the other calls may have scored these samples' times already.
            reset: true,
            ..Default::default()
        }],
    };
    let call = connection
        .detection()
        .stream_detect_fleet(tokio_stream::iter([batch]))
        .await;
    let mut replies = match call {
        Ok(response) => response.into_inner(),
        Err(status) => return status.code(),
    };
    match replies.next().await {
        Some(Ok(reply)) => reply.vehicles[0]
            .error
            .as_ref()
            .map_or(Code::Ok, |status| Code::from(status.code)),
        Some(Err(status)) => status.code(),
        None => Code::Unknown,
    }
}

/// The answer to `rpc`, called with a harmless request naming `vehicle` where it names one.
async fn call(rpc: &str, connection: &Connection, vehicle: &str) -> Code {
    let mut detection = connection.detection();
    let mut models = connection.models();
    let mut datasets = connection.datasets();
    let mut training = connection.training();
    let mut operations = connection.operations();
    let mut alarms = connection.alarms();
    let none = |kind: &str| format!("{kind}/000000000000");
    match rpc {
        "StreamDetect" => stream_detect(connection, vehicle).await,
        "Detect" => code(
            detection
                .detect(v1::DetectRequest {
                    vehicle_id: vehicle.into(),
                    samples: samples(vehicle),
                    ..Default::default()
                })
                .await,
        ),
        "StreamDetectFleet" => fleet_detect(connection, vehicle).await,
        "ListSessions" => code(
            detection
                .list_sessions(v1::ListSessionsRequest::default())
                .await,
        ),
        "GetSession" => code(
            detection
                .get_session(v1::GetSessionRequest {
                    vehicle_id: vehicle.into(),
                })
                .await,
        ),
        "ResetSession" => code(
            detection
                .reset_session(v1::ResetSessionRequest {
                    vehicle_id: "nobody-streams-this".into(),
                })
                .await,
        ),
        "ListModels" => code(models.list_models(v1::ListModelsRequest::default()).await),
        "GetModel" => code(
            models
                .get_model(v1::GetModelRequest {
                    name: none("models"),
                })
                .await,
        ),
        "ExportModel" => code(
            models
                .export_model(v1::ExportModelRequest {
                    name: none("models"),
                })
                .await,
        ),
        "SetActiveModel" => code(
            models
                .set_active_model(v1::SetActiveModelRequest {
                    name: none("models"),
                })
                .await,
        ),
        "DeleteModel" => code(
            models
                .delete_model(v1::DeleteModelRequest {
                    name: none("models"),
                })
                .await,
        ),
        "ImportModel" => code(
            models
                .import_model(tokio_stream::iter(Vec::<v1::ImportModelRequest>::new()))
                .await,
        ),
        // No scope: refused after the role check, so that no shadow starts.
        "StartShadow" => code(
            models
                .start_shadow(v1::StartShadowRequest {
                    model: none("models"),
                    scope: None,
                })
                .await,
        ),
        "GetShadow" => code(
            models
                .get_shadow(v1::GetShadowRequest {
                    name: "shadows/999999".into(),
                })
                .await,
        ),
        "StopShadow" => code(
            models
                .stop_shadow(v1::StopShadowRequest {
                    name: "shadows/999999".into(),
                })
                .await,
        ),
        "ListShadowAlarms" => code(
            models
                .list_shadow_alarms(v1::ListShadowAlarmsRequest {
                    shadow: "shadows/999999".into(),
                    ..Default::default()
                })
                .await,
        ),
        "UploadDataset" => code(
            datasets
                .upload_dataset(tokio_stream::iter(Vec::<v1::UploadDatasetRequest>::new()))
                .await,
        ),
        "ImportDataset" => code(
            datasets
                .import_dataset(v1::ImportDatasetRequest::default())
                .await,
        ),
        "ListDatasets" => code(
            datasets
                .list_datasets(v1::ListDatasetsRequest::default())
                .await,
        ),
        "GetDataset" => code(
            datasets
                .get_dataset(v1::GetDatasetRequest {
                    name: none("datasets"),
                })
                .await,
        ),
        "DeleteDataset" => code(
            datasets
                .delete_dataset(v1::DeleteDatasetRequest {
                    name: none("datasets"),
                })
                .await,
        ),
        "ListAlarms" => code(alarms.list_alarms(v1::ListAlarmsRequest::default()).await),
        "WatchAlarms" => code(alarms.watch_alarms(v1::WatchAlarmsRequest::default()).await),
        "ListIncidents" => code(
            alarms
                .list_incidents(v1::ListIncidentsRequest::default())
                .await,
        ),
        "GetIncident" => code(alarms.get_incident(v1::GetIncidentRequest { id: 1 }).await),
        "WatchIncidents" => code(
            alarms
                .watch_incidents(v1::WatchIncidentsRequest::default())
                .await,
        ),
        "EndIncident" => code(
            alarms
                .end_incident(v1::EndIncidentRequest {
                    id: 1,
                    reason: "a drill".into(),
                    dismiss: true,
                })
                .await,
        ),
        "CreateTrainingJob" => code(
            training
                .create_training_job(v1::CreateTrainingJobRequest::default())
                .await,
        ),
        "CreateEvaluationJob" => code(
            training
                .create_evaluation_job(v1::CreateEvaluationJobRequest::default())
                .await,
        ),
        "WatchJob" => code(
            training
                .watch_job(v1::WatchJobRequest {
                    name: none("operations"),
                })
                .await,
        ),
        "ListOperations" => code(
            operations
                .list_operations(longrunning::ListOperationsRequest::default())
                .await,
        ),
        "GetOperation" => code(
            operations
                .get_operation(longrunning::GetOperationRequest {
                    name: none("operations"),
                })
                .await,
        ),
        "WaitOperation" => code(
            operations
                .wait_operation(longrunning::WaitOperationRequest {
                    name: none("operations"),
                    timeout: None,
                })
                .await,
        ),
        "DeleteOperation" => code(
            operations
                .delete_operation(longrunning::DeleteOperationRequest {
                    name: none("operations"),
                })
                .await,
        ),
        "CancelOperation" => code(
            operations
                .cancel_operation(longrunning::CancelOperationRequest {
                    name: none("operations"),
                })
                .await,
        ),
        other => panic!("no call for {other}"),
    }
}

/// Every RPC, and which of vehicle, gateway, operator, admin may make it.
const MATRIX: &[(&str, [bool; 4])] = &[
    ("StreamDetect", [true, true, false, true]),
    ("Detect", [true, true, false, true]),
    ("StreamDetectFleet", [true, true, false, true]),
    ("ListSessions", [false, false, true, true]),
    ("GetSession", [false, false, true, true]),
    ("ResetSession", [false, false, false, true]),
    ("ListModels", [false, false, true, true]),
    ("GetModel", [false, false, true, true]),
    ("ExportModel", [false, false, true, true]),
    ("SetActiveModel", [false, false, false, true]),
    ("DeleteModel", [false, false, false, true]),
    ("ImportModel", [false, false, false, true]),
    ("StartShadow", [false, false, false, true]),
    ("GetShadow", [false, false, true, true]),
    ("StopShadow", [false, false, false, true]),
    ("ListShadowAlarms", [false, false, true, true]),
    ("UploadDataset", [false, false, false, true]),
    ("ImportDataset", [false, false, false, true]),
    ("ListDatasets", [false, false, true, true]),
    ("GetDataset", [false, false, true, true]),
    ("DeleteDataset", [false, false, false, true]),
    ("ListAlarms", [false, false, true, true]),
    ("WatchAlarms", [false, false, true, true]),
    ("ListIncidents", [false, false, true, true]),
    ("GetIncident", [false, false, true, true]),
    ("WatchIncidents", [false, false, true, true]),
    ("EndIncident", [false, false, false, true]),
    ("CreateTrainingJob", [false, false, false, true]),
    ("CreateEvaluationJob", [false, false, false, true]),
    ("WatchJob", [false, false, true, true]),
    ("ListOperations", [false, false, true, true]),
    ("GetOperation", [false, false, true, true]),
    ("WaitOperation", [false, false, true, true]),
    ("DeleteOperation", [false, false, false, true]),
    ("CancelOperation", [false, false, false, true]),
];

fn check(role: &str, rpc: &str, allowed: bool, answer: Code) {
    if allowed {
        assert!(
            !matches!(answer, Code::PermissionDenied | Code::Unauthenticated),
            "{role} may call {rpc}, got {answer:?}"
        );
    } else {
        assert_eq!(answer, Code::PermissionDenied, "{role} must not call {rpc}");
    }
}

/// The value of `spoofwatch_permission_denied_total` for `role` summed over methods.
async fn denied_count(server: &TestServer, role: &str) -> f64 {
    let addr = server.metrics_addr().expect("metrics are served");
    let body = spoofwatch_tests::scrape(addr).await;
    body.lines()
        .filter(|line| {
            line.starts_with("spoofwatch_permission_denied_total{")
                && line.contains(&format!("role=\"{role}\""))
        })
        .filter_map(|line| line.rsplit(' ').next()?.parse::<f64>().ok())
        .sum()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_rpc_by_every_token_role_follows_the_table() {
    let dir = tempfile::tempdir().expect("temp dir");
    let server = start_with_roles(dir.path(), &token_roles(), None).await;
    let roles = [
        ("vehicle", "vehicle-token", "car-1", 0),
        ("gateway", "gateway-token", "gw-7", 1),
        ("operator", "operator-token", "car-1", 2),
        ("admin (roles file)", "admin-token", "car-1", 3),
        ("admin (the single token)", "s3cret", "car-1", 3),
    ];
    for (role, token, vehicle, column) in roles {
        let connection = connect(&server, ConnectOptions::with_token(Some(token.into()))).await;
        for &(rpc, allowed) in MATRIX {
            let answer = call(rpc, &connection, vehicle).await;
            check(role, rpc, allowed[column], answer);
        }
    }
    // The table covers every RPC the server serves: one per path of the schema.
    assert_eq!(MATRIX.len(), 35);
    assert!(denied_count(&server, "operator").await >= 3.0);
    assert!(denied_count(&server, "vehicle").await >= 20.0);

    // Unknown, wrong or missing tokens are unidentified, not denied.
    for token in [Some("nope"), None] {
        let connection = connect(
            &server,
            ConnectOptions::with_token(token.map(str::to_string)),
        )
        .await;
        assert_eq!(
            call("ListModels", &connection, "car-1").await,
            Code::Unauthenticated
        );
        assert_eq!(
            call("Detect", &connection, "car-1").await,
            Code::Unauthenticated
        );
    }
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_vehicle_or_gateway_acts_only_for_its_own_vehicles() {
    let dir = tempfile::tempdir().expect("temp dir");
    let server = start_with_roles(dir.path(), &token_roles(), None).await;
    let vehicle = connect(
        &server,
        ConnectOptions::with_token(Some("vehicle-token".into())),
    )
    .await;
    let gateway = connect(
        &server,
        ConnectOptions::with_token(Some("gateway-token".into())),
    )
    .await;
    for rpc in ["StreamDetect", "Detect", "StreamDetectFleet"] {
        assert_eq!(
            call(rpc, &vehicle, "car-1").await,
            Code::Ok,
            "{rpc} for itself"
        );
        assert_eq!(
            call(rpc, &vehicle, "car-2").await,
            Code::PermissionDenied,
            "{rpc}"
        );
        assert_eq!(
            call(rpc, &gateway, "gw-9").await,
            Code::Ok,
            "{rpc} in its prefix"
        );
        assert_eq!(
            call(rpc, &gateway, "car-1").await,
            Code::PermissionDenied,
            "{rpc}"
        );
    }
    // A stateless Detect (no vehicle) touches no session: any detecting caller may make it.
    let stateless = vehicle
        .detection()
        .detect(v1::DetectRequest {
            samples: samples("car-9"),
            ..Default::default()
        })
        .await;
    assert_eq!(code(stateless), Code::Ok);
    // One fleet message, one vehicle in scope and one not: the other is refused alone.
    let batch = v1::FleetBatch {
        seq: 1,
        vehicles: ["gw-1", "car-1"]
            .map(|id| v1::VehicleSamples {
                vehicle_id: id.into(),
                samples: samples(id),
                ..Default::default()
            })
            .to_vec(),
    };
    let reply = gateway
        .detection()
        .stream_detect_fleet(tokio_stream::iter([batch]))
        .await
        .expect("the call is accepted")
        .into_inner()
        .next()
        .await
        .expect("a reply")
        .expect("a fleet reply");
    assert!(reply.vehicles[0].error.is_none());
    assert_eq!(reply.vehicles[0].detections.len(), samples("gw-1").len());
    let refused = reply.vehicles[1].error.as_ref().expect("refused");
    assert_eq!(Code::from(refused.code), Code::PermissionDenied);
    assert!(refused.message.contains("car-1"), "{}", refused.message);
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn certificates_are_their_vehicle_by_default_and_the_roles_file_reloads() {
    let dir = tempfile::tempdir().expect("temp dir");
    let ca = TestCa::new(dir.path(), "fleet");
    let admin = ca.client(dir.path(), "fleet-admin");
    let truck7 = ca.client(dir.path(), "truck-7");
    let gateway = ca.client(dir.path(), "gateway-eu-1");
    let operator = ca.client(dir.path(), "ops-dashboard");
    let revoked = ca.client(dir.path(), "truck-13");
    let roles = "[certificates]\n\
                 \"fleet-admin\" = { role = \"admin\" }\n\
                 \"gateway-eu-1\" = { role = \"gateway\", vehicle_prefixes = [\"eu-\"] }\n\
                 \"ops-dashboard\" = { role = \"operator\" }\n\
                 [deny]\ncertificates = [\"truck-13\"]\n";
    let server = start_with_roles(dir.path(), roles, Some((&ca, &admin))).await;

    let as_cert = |files: &CertFiles| with_certificate(&ca, files);
    let truck = connect(&server, as_cert(&truck7)).await;
    for &(rpc, allowed) in MATRIX {
        check(
            "certificate truck-7",
            rpc,
            allowed[0],
            call(rpc, &truck, "truck-7").await,
        );
    }
    // The certificate of truck-7 can neither reset truck-8 nor stream as it.
    assert_eq!(
        stream_detect(&truck, "truck-8").await,
        Code::PermissionDenied
    );
    assert_eq!(
        call("ResetSession", &truck, "truck-8").await,
        Code::PermissionDenied
    );
    let gateway = connect(&server, as_cert(&gateway)).await;
    for &(rpc, allowed) in MATRIX {
        check(
            "certificate gateway",
            rpc,
            allowed[1],
            call(rpc, &gateway, "eu-3").await,
        );
    }
    assert_eq!(
        call("Detect", &gateway, "us-3").await,
        Code::PermissionDenied
    );
    let operator = connect(&server, as_cert(&operator)).await;
    for &(rpc, allowed) in MATRIX {
        check(
            "certificate operator",
            rpc,
            allowed[2],
            call(rpc, &operator, "truck-7").await,
        );
    }
    let admin_connection = connect(&server, as_cert(&admin)).await;
    for &(rpc, allowed) in MATRIX {
        check(
            "certificate admin",
            rpc,
            allowed[3],
            call(rpc, &admin_connection, "truck-7").await,
        );
    }
    let revoked_connection = connect(&server, as_cert(&revoked)).await;
    assert_eq!(
        call("Detect", &revoked_connection, "truck-13").await,
        Code::Unauthenticated
    );

    // Revoke truck-7 in the file: within seconds its calls are refused, without a restart.
    std::fs::write(
        dir.path().join("roles.toml"),
        roles.replace("[\"truck-13\"]", "[\"truck-13\", \"truck-7\"]"),
    )
    .expect("roles file rewritten");
    let deadline = tokio::time::Instant::now() + Duration::from_secs(20);
    while call("Detect", &truck, "truck-7").await != Code::Unauthenticated {
        assert!(
            tokio::time::Instant::now() < deadline,
            "the revocation did not apply"
        );
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
    // A broken file, and one truncated to nothing (an editor's write, a ConfigMap caught
    // mid-update), keep what is in force: the revocation, the admin, the gateway's scope.
    for broken in ["[certificates\n", ""] {
        std::fs::write(dir.path().join("roles.toml"), broken).expect("written");
        tokio::time::sleep(Duration::from_secs(5)).await;
        assert_eq!(
            call("Detect", &truck, "truck-7").await,
            Code::Unauthenticated,
            "{broken:?}"
        );
        assert_eq!(call("ListModels", &admin_connection, "").await, Code::Ok);
        let answer = call("Detect", &gateway, "eu-3").await;
        check("certificate gateway", "Detect", true, answer);
    }
    drop((
        truck,
        gateway,
        operator,
        admin_connection,
        revoked_connection,
    ));
    server.stop().await;
}
