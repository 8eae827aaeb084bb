//! Shadow evaluation, black-box: with two models on one server, a candidate shadowing every
//! vehicle scores what they send, its would-be alarms are listed apart (ListShadowAlarms) while the
//! real alarms and every detection the vehicles get back are the same, bit for bit, as on a server
//! without the shadow; stopping it leaves its summary; it survives a restart and says how many
//! vehicle restarts it had; and bad requests are refused with their field.

use std::time::Duration;

use spoofwatch_core::scenario::AttackKind;
use spoofwatch_proto::v1;
use spoofwatch_tests::{
    ADMIN_TOKEN, Clients, TestServer, artifact_registered_again, attacked_drive, fingerprint,
    import_model, normal_drive, start_server, start_stream, start_with_roles, test_config,
    token_sha256, track_samples,
};
use tonic::Code;
use tonic_types::StatusExt;

/// The candidate: the bundled model registered again, its notes changed. Any other critical test
/// may open an alarm on another sample than the live one's does (a frozen fix pages at once, before
/// the warning's hold), so only the same network and the same tests make every sample agree; the
/// would-be alarms are still the candidate's own, listed apart.
async fn candidate(clients: &mut Clients) -> String {
    import_model(clients, artifact_registered_again(), "candidate")
        .await
        .name
}

async fn start_shadow(
    clients: &mut Clients,
    model: &str,
    scope: v1::start_shadow_request::Scope,
) -> Result<v1::Shadow, tonic::Status> {
    clients
        .models
        .start_shadow(v1::StartShadowRequest {
            model: model.into(),
            scope: Some(scope),
        })
        .await
        .map(tonic::Response::into_inner)
}

async fn get_shadow(clients: &mut Clients, name: &str) -> v1::Shadow {
    clients
        .models
        .get_shadow(v1::GetShadowRequest { name: name.into() })
        .await
        .expect("GetShadow")
        .into_inner()
}

/// Polls GetShadow every 50 ms until the shadow scored `samples` samples, stored `starts` vehicle
/// starts (first states and restarts) and stored the onsets it counted; panics after 30 s. It scores
/// off the request path, and its writer stores starts and onsets after the worker counted them.
async fn scored(clients: &mut Clients, name: &str, samples: u64, starts: u64) -> v1::Shadow {
    for _ in 0..600 {
        let shadow = get_shadow(clients, name).await;
        let summary = shadow.summary.expect("a summary");
        let onsets = summary.shadow_onsets.unwrap_or_default().warning;
        if summary.samples_scored + summary.samples_shed >= samples
            && summary.vehicles + summary.vehicle_restarts >= starts
            && summary.alarms == onsets
        {
            return get_shadow(clients, name).await;
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    panic!("the shadow never scored {samples} samples and stored {starts} vehicle starts");
}

async fn shadow_alarms(clients: &mut Clients, name: &str) -> Vec<v1::ShadowAlarm> {
    clients
        .models
        .list_shadow_alarms(v1::ListShadowAlarmsRequest {
            shadow: name.into(),
            ..Default::default()
        })
        .await
        .expect("ListShadowAlarms")
        .into_inner()
        .alarms
}

/// The drives: a frozen fix on `frozen` (it alarms), a normal drive on `calm`.
fn drives() -> Vec<(&'static str, Vec<v1::Sample>)> {
    let frozen = attacked_drive("frozen", 240.0, 21, AttackKind::FrozenPosition, 100.0, 60.0);
    vec![
        ("frozen", track_samples(&frozen)),
        ("calm", track_samples(&normal_drive("calm", 240.0, 22))),
    ]
}

/// Streams every drive on the active model (20 samples a batch); returns each vehicle's
/// detections' fingerprint.
async fn stream_drives(clients: &Clients) -> Vec<Vec<(u64, u64, bool, bool, bool)>> {
    let mut fingerprints = Vec::new();
    for (vehicle, samples) in drives() {
        let (mut stream, _) = start_stream(clients, vehicle, "").await;
        let mut detections = Vec::new();
        for (seq, batch) in samples.chunks(20).enumerate() {
            detections.extend(
                stream
                    .detect(seq as u64 + 1, batch.to_vec())
                    .await
                    .expect("scored"),
            );
        }
        stream.finish().await.expect("the stream ends cleanly");
        fingerprints.push(fingerprint(&detections));
    }
    fingerprints
}

fn total_samples() -> u64 {
    drives().iter().map(|(_, s)| s.len() as u64).sum()
}

/// The real alarms as everything the model decided (ids and wall-clock times left out).
async fn real_alarms(clients: &mut Clients) -> Vec<(String, u64, u64, Option<u64>, u64, i32)> {
    let mut alarms: Vec<_> = clients
        .alarms
        .list_alarms(v1::ListAlarmsRequest::default())
        .await
        .expect("ListAlarms")
        .into_inner()
        .alarms
        .into_iter()
        .map(|a| {
            (
                a.vehicle_id,
                a.onset_timestamp_s.to_bits(),
                a.peak_probability.to_bits(),
                a.end_timestamp_s.map(f64::to_bits),
                a.samples,
                a.severity,
            )
        })
        .collect();
    alarms.sort();
    alarms
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_shadow_lists_its_would_be_alarms_and_leaves_the_real_ones_unchanged() {
    // Without a shadow.
    let (_plain_dir, _plain, mut plain) = start_server(|_| {}).await;
    candidate(&mut plain).await;
    let plain_detections = stream_drives(&plain).await;
    let plain_alarms = real_alarms(&mut plain).await;
    assert!(!plain_alarms.is_empty(), "the frozen fix alarms");

    // The same run with a shadow on every vehicle.
    let (_dir, _server, mut clients) = start_server(|_| {}).await;
    let model = candidate(&mut clients).await;
    let shadow = start_shadow(
        &mut clients,
        &model,
        v1::start_shadow_request::Scope::AllVehicles(true),
    )
    .await
    .expect("StartShadow");
    assert!(shadow.running && shadow.all_vehicles);
    assert_eq!(shadow.model, model);
    let detections = stream_drives(&clients).await;
    assert_eq!(
        detections, plain_detections,
        "the replies are unchanged, bit for bit"
    );
    assert_eq!(
        real_alarms(&mut clients).await,
        plain_alarms,
        "the real alarms are unchanged, bit for bit"
    );

    let shadow = scored(&mut clients, &shadow.name, total_samples(), 2).await;
    let summary = shadow.summary.expect("a summary");
    assert_eq!(summary.samples_scored, total_samples(), "nothing shed");
    assert_eq!(summary.samples_shed, 0);
    assert_eq!((summary.vehicles, summary.vehicle_restarts), (2, 0));
    // The same model: both alarm on the same samples.
    assert_eq!((summary.live_only, summary.shadow_only), (0, 0));
    assert!(summary.agree_alarm > 0 && summary.agree_quiet > 0);
    let live = summary.live_onsets.expect("live onsets");
    let would_be = summary.shadow_onsets.expect("shadow onsets");
    assert_eq!(live, would_be);
    assert!(summary.vehicle_hours > 0.12, "{}", summary.vehicle_hours);

    let alarms = shadow_alarms(&mut clients, &shadow.name).await;
    assert_eq!(alarms.len() as u64, would_be.warning);
    assert!(alarms.iter().all(|a| a.model == model), "{alarms:?}");
    assert!(
        alarms.iter().any(|a| a.vehicle_id == "frozen"),
        "{alarms:?}"
    );
    // The same model: the candidate would have alarmed on the vehicles the live model alarmed on.
    let vehicles = |mut ids: Vec<String>| {
        ids.sort();
        ids.dedup();
        ids
    };
    assert_eq!(
        vehicles(alarms.iter().map(|a| a.vehicle_id.clone()).collect()),
        vehicles(plain_alarms.iter().map(|a| a.0.clone()).collect())
    );
    assert!(alarms.iter().all(|a| a.live_alarmed));
    // Still the real ones only: no would-be alarm reached the alarm store.
    assert_eq!(real_alarms(&mut clients).await, plain_alarms);

    // Stopping leaves the summary; the would-be alarms stay listed, none open.
    let stopped = clients
        .models
        .stop_shadow(v1::StopShadowRequest::default())
        .await
        .expect("StopShadow")
        .into_inner();
    assert!(!stopped.running && stopped.stop_time.is_some());
    let again = get_shadow(&mut clients, "").await;
    assert_eq!(again.summary, stopped.summary);
    assert_eq!(
        again.summary.expect("a summary").samples_scored,
        total_samples()
    );
    let after = shadow_alarms(&mut clients, &shadow.name).await;
    assert_eq!(after.len(), alarms.len());
    assert!(after.iter().all(|a| !a.end_reason.is_empty()));
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_shadow_survives_a_restart_and_counts_the_vehicle_restart() {
    let dir = tempfile::tempdir().expect("temp dir");
    let server = TestServer::start(test_config(dir.path())).await;
    let mut clients = Clients::of(&server).await;
    let model = candidate(&mut clients).await;
    let shadow = start_shadow(
        &mut clients,
        &model,
        v1::start_shadow_request::Scope::Share(1.0),
    )
    .await
    .expect("StartShadow");
    let samples = track_samples(&normal_drive("car", 60.0, 3));
    let (mut stream, _) = start_stream(&clients, "car", "").await;
    stream
        .detect(1, samples[..30].to_vec())
        .await
        .expect("scored");
    stream.finish().await.expect("ends");
    scored(&mut clients, &shadow.name, 30, 1).await;
    server.stop().await;

    let server = TestServer::start(test_config(dir.path())).await;
    let mut clients = Clients::of(&server).await;
    let resumed = get_shadow(&mut clients, "").await;
    assert!(resumed.running, "the stored shadow runs again");
    assert_eq!(resumed.name, shadow.name);
    let (mut stream, _) = start_stream(&clients, "car", "").await;
    stream
        .detect(2, samples[30..].to_vec())
        .await
        .expect("scored");
    stream.finish().await.expect("ends");
    let summary = scored(&mut clients, &shadow.name, samples.len() as u64, 2)
        .await
        .summary
        .expect("a summary");
    assert_eq!(
        summary.samples_scored,
        samples.len() as u64,
        "counts of both runs"
    );
    assert_eq!(
        (summary.vehicles, summary.vehicle_restarts),
        (1, 1),
        "the vehicle's shadow state was rebuilt after the restart, and it says so"
    );
    server.stop().await;
}

fn field(status: &tonic::Status) -> String {
    let bad = status
        .get_details_bad_request()
        .unwrap_or_else(|| panic!("a field violation in {status:?}"));
    bad.field_violations[0].field.clone()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bad_shadow_requests_are_refused_with_their_reason() {
    use v1::start_shadow_request::Scope;
    let dir = tempfile::tempdir().expect("temp dir");
    let roles = format!(
        "[tokens]\n\"{}\" = {{ name = \"dashboard\", role = \"operator\" }}\n",
        token_sha256("operator-token"),
    );
    let server = start_with_roles(dir.path(), &roles, None).await;
    let admin = server.connection(Some(ADMIN_TOKEN)).await;
    let mut clients = Clients::new(admin);
    let model = candidate(&mut clients).await;

    let unknown = start_shadow(&mut clients, "models/nope", Scope::AllVehicles(true)).await;
    assert_eq!(unknown.unwrap_err().code(), Code::NotFound);
    for (scope, expected) in [
        (Scope::Share(0.0), "share"),
        (Scope::Share(1.5), "share"),
        (Scope::Share(f64::NAN), "share"),
        (
            Scope::Vehicles(v1::ShadowVehicles::default()),
            "vehicles.vehicle_ids",
        ),
        (
            Scope::Vehicles(v1::ShadowVehicles {
                vehicle_ids: vec!["ok".into(), "not ok".into()],
            }),
            "vehicles.vehicle_ids[1]",
        ),
    ] {
        let refused = start_shadow(&mut clients, &model, scope).await.unwrap_err();
        assert_eq!(refused.code(), Code::InvalidArgument);
        assert_eq!(field(&refused), expected);
    }
    let operator = server.connection(Some("operator-token")).await;
    let refused = operator
        .models()
        .start_shadow(v1::StartShadowRequest {
            model: model.clone(),
            scope: Some(Scope::AllVehicles(true)),
        })
        .await
        .unwrap_err();
    assert_eq!(refused.code(), Code::PermissionDenied);
    assert_eq!(
        get_shadow_code(&mut clients).await,
        Code::NotFound,
        "no shadow started yet"
    );

    start_shadow(&mut clients, &model, Scope::Share(0.5))
        .await
        .expect("StartShadow");
    let second = start_shadow(&mut clients, &model, Scope::AllVehicles(true)).await;
    assert_eq!(second.unwrap_err().code(), Code::FailedPrecondition);
    let deleted = clients
        .models
        .delete_model(v1::DeleteModelRequest {
            name: model.clone(),
        })
        .await;
    assert_eq!(
        deleted.unwrap_err().code(),
        Code::FailedPrecondition,
        "the candidate of a running shadow is not deleted"
    );
    // An operator reads it.
    let read = operator
        .models()
        .get_shadow(v1::GetShadowRequest::default())
        .await
        .expect("an operator reads the shadow")
        .into_inner();
    assert_eq!(read.share, 0.5);
}

async fn get_shadow_code(clients: &mut Clients) -> Code {
    clients
        .models
        .get_shadow(v1::GetShadowRequest::default())
        .await
        .map_or_else(|s| s.code(), |_| Code::Ok)
}
