//! Area incidents end, black-box: a server with a roles file (a gateway's token and a vehicle's own,
//! two independent credentials, open an incident; an operator reads; the single admin token ends).
//!
//! - Vehicles that disconnect in the middle of their alarms: once their sessions are evicted and
//!   their snapshots expire, their alarms end (at their last alarming sample), and the incident
//!   ends on its own through the correlator (its ENDED event carries no closure).
//! - An admin dismisses an open incident with a reason: operators and vehicles are refused, an
//!   empty or overlong reason is refused naming the field, an unknown id is not found; the
//!   dismissal is returned, stored (GetIncident) and sent to a live WatchIncidents watcher with
//!   its reason and the admin's credential; a second one is refused; the members' alarms stay as
//!   they were and open no new incident; and the area prior stops at once: a probe vehicle driving
//!   through the area alarms as it did before the incident opened, not as it did while it was open.
//! - Across two replicas on one PostgreSQL database: a dismissal through one replica ends the
//!   incident on the other too (its prior within a refresh, its watcher, its reads), and the
//!   correlator, wherever its lease is, forgets it: the same vehicles' new alarms open a new one.

use std::path::Path;
use std::time::Duration;

use spoofwatch_core::geo::{LatLon, displace_fix};
use spoofwatch_core::scenario::AttackKind;
use spoofwatch_proto::v1;
use spoofwatch_server::config::Config;
use spoofwatch_server::store::test_database::TestDatabase;
use spoofwatch_tests::incidents::{attacked_drive, list_incidents, wait_for_incidents};
use spoofwatch_tests::{
    ADMIN_TOKEN, ConnectOptions, Connection, DetectStream, TestServer, stream_samples, test_config,
    token_sha256,
};
use tonic::Code;
use tonic_types::StatusExt;

/// Eviction, expiry and the correlator's 1 s ticks, on shared cores.
const BOUND: Duration = Duration::from_secs(60);

fn roles() -> String {
    format!(
        "[tokens]\n\
         \"{}\" = {{ name = \"bridge\", role = \"gateway\", vehicle_prefixes = [\"gw-\"] }}\n\
         \"{}\" = {{ name = \"car-b\", role = \"vehicle\" }}\n\
         \"{}\" = {{ name = \"dashboard\", role = \"operator\" }}\n",
        token_sha256("bridge-token"),
        token_sha256("car-b-token"),
        token_sha256("dashboard-token"),
    )
}

/// A server with [`roles`] and the single admin token [`ADMIN_TOKEN`], its configuration adjusted
/// by `configure`.
async fn start(dir: &Path, configure: impl FnOnce(&mut Config)) -> TestServer {
    let mut config = test_config(dir);
    configure(&mut config);
    start_with_roles(dir, config).await
}

/// Starts `config` with [`roles`] (written into `dir`) and the admin token [`ADMIN_TOKEN`].
async fn start_with_roles(dir: &Path, mut config: Config) -> TestServer {
    let roles_file = dir.join("roles.toml");
    std::fs::write(&roles_file, roles()).expect("roles file written");
    config.roles_file = Some(roles_file);
    config.auth_token = Some(ADMIN_TOKEN.into());
    TestServer::start_for(
        config,
        &ConnectOptions::with_token(Some(ADMIN_TOKEN.into())),
    )
    .await
}

fn place(centre: LatLon, east_m: f64, north_m: f64) -> LatLon {
    let (lat, lon) = displace_fix(centre.lat_deg, centre.lon_deg, east_m, north_m);
    LatLon::new(lat, lon)
}

/// Three vehicles 9 km apart around `centre` (two of the gateway's, one with its own token), every
/// fix jumping 200 m east from 40 s on: their alarms are open when their streams end.
async fn spoof_three(server: &TestServer, centre: LatLon, prefix: &str) {
    let bridge = server.connection(Some("bridge-token")).await;
    let car_b = server.connection(Some("car-b-token")).await;
    for k in 0..3 {
        let (connection, id) = match k {
            2 => (&car_b, "car-b".to_string()),
            _ => (&bridge, format!("gw-{prefix}{k}")),
        };
        stream_samples(connection, &id, true, 1, &spoofed(&id, centre, k)).await;
    }
}

/// The `k`th (0 to 2) vehicle of a triangle 9 km on a side from `centre`, its fix jumping 200 m
/// east from 40 s on.
fn spoofed(id: &str, centre: LatLon, k: usize) -> Vec<v1::Sample> {
    let (east, north) = [(0.0, 0.0), (9_000.0, 0.0), (4_500.0, 7_794.0)][k];
    let jump = AttackKind::Jump { offset_m: 200.0 };
    attacked_drive(
        id,
        place(centre, east, north),
        60 + k as u64,
        (jump, 90.0, 40.0),
    )
}

/// Every stored incident event, as (kind, incident).
async fn replayed(reader: &Connection) -> Vec<(i32, v1::Incident)> {
    let mut stream = reader
        .alarms()
        .watch_incidents(v1::WatchIncidentsRequest {
            after_cursor: Some(0),
            stop_when_caught_up: true,
        })
        .await
        .expect("WatchIncidents")
        .into_inner();
    let mut events = Vec::new();
    while let Some(event) = stream.message().await.expect("an event") {
        if let Some(incident) = event.incident {
            events.push((event.kind, incident));
        }
    }
    events
}

async fn alarms(reader: &Connection) -> Vec<v1::Alarm> {
    reader
        .alarms()
        .list_alarms(v1::ListAlarmsRequest::default())
        .await
        .expect("ListAlarms")
        .into_inner()
        .alarms
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_incident_ends_once_its_disconnected_vehicles_alarms_expire() {
    let dir = tempfile::tempdir().expect("temp dir");
    let server = start(dir.path(), |config| {
        // Evicted 2 s after their streams end; their snapshots expire 5 s after their last write
        // (seen unchanged for 3 s more); the incident ends as soon as no member alarm is open.
        config.session_idle_secs = 2;
        config.snapshot_every_secs = 1;
        config.snapshot_ttl_secs = 5;
        config.incident_quiet_secs = 0;
    })
    .await;
    let reader = server.connection(Some("dashboard-token")).await;
    spoof_three(&server, LatLon::new(32.3, -110.8), "a").await;

    let ended = wait_for_incidents(&reader, "the incident ends on its own", BOUND, |stored| {
        stored.len() == 1 && !stored[0].open
    })
    .await;
    let incident = &ended[0];
    assert_eq!(incident.vehicles.len(), 3, "{incident:?}");
    assert!(incident.closure.is_none(), "it ended on its own");
    assert!(incident.ended_time.is_some() && incident.ended_s.is_some());
    assert!(
        incident.vehicles.iter().all(|v| !v.alarm_open),
        "{incident:?}"
    );
    // Each member's alarm ended at its last alarming sample (the snapshot's), not deleted.
    let stored = alarms(&reader).await;
    for member in &incident.vehicles {
        let alarm = stored
            .iter()
            .find(|a| a.id == member.alarm_id)
            .unwrap_or_else(|| panic!("{}'s alarm is listed: {stored:?}", member.vehicle_id));
        assert!(alarm.end_time.is_some(), "{alarm:?}");
        assert!(
            alarm.end_timestamp_s.is_some_and(|t| t <= 90.0),
            "{alarm:?}"
        );
    }
    let kinds: Vec<i32> = replayed(&reader).await.iter().map(|(k, _)| *k).collect();
    assert_eq!(
        kinds,
        [
            v1::IncidentEventKind::Opened as i32,
            v1::IncidentEventKind::Ended as i32
        ]
    );
    drop(reader);
    server.stop().await;
}

/// The alarm flags of a probe vehicle driving from `start` with its fix drifting north at 2 m/s
/// from 8 s on, streamed by the admin as `id`. While its trajectory settles (its first 30 s) p̂ ≥ θ
/// counts only on a fix displaced beyond the anchors' gate, or, inside an open incident's area,
/// as on a receiver's spoofing flag: the area prior brings its alarm forward.
async fn probe(admin: &Connection, id: &str, start: LatLon) -> Vec<bool> {
    let drift = AttackKind::RampDrift { velocity_mps: 2.0 };
    let samples = attacked_drive(id, start, 7, (drift, 0.0, 8.0));
    let (stream, _) = DetectStream::start(admin, id, "", true)
        .await
        .expect("the probe's stream opens");
    let mut stream = stream.with_reply_timeout(Duration::from_secs(30));
    let mut flags = Vec::new();
    for (k, batch) in samples.chunks(10).enumerate() {
        let detections = stream
            .detect(k as u64 + 1, batch.to_vec())
            .await
            .expect("the probe's detections");
        flags.extend(detections.iter().map(|d| d.alarm));
    }
    stream.finish().await.expect("the probe's stream ends");
    flags
}

/// The refusal's code and the fields its BadRequest names.
fn refusal(status: &tonic::Status) -> (Code, Vec<String>) {
    let fields = status
        .get_details_bad_request()
        .map(|bad| bad.field_violations.into_iter().map(|v| v.field).collect())
        .unwrap_or_default();
    (status.code(), fields)
}

async fn end(
    connection: &Connection,
    id: i64,
    reason: &str,
) -> Result<v1::Incident, tonic::Status> {
    connection
        .alarms()
        .end_incident(v1::EndIncidentRequest {
            id,
            reason: reason.to_string(),
            dismiss: true,
        })
        .await
        .map(tonic::Response::into_inner)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_admin_dismisses_an_incident_and_its_area_prior_stops() {
    let dir = tempfile::tempdir().expect("temp dir");
    let server = start(dir.path(), |_| {}).await;
    let reader = server.connection(Some("dashboard-token")).await;
    let admin = server.connection(Some(ADMIN_TOKEN)).await;
    let centre = LatLon::new(33.1, -111.6);
    // The triangle's centroid: inside the incident's area.
    let inside = place(centre, 4_500.0, 2_598.0);
    let before = probe(&admin, "probe-before", inside).await;

    spoof_three(&server, centre, "b").await;
    let opened = wait_for_incidents(&reader, "the incident opens", BOUND, |stored| {
        stored.len() == 1 && stored[0].vehicles.len() == 3
    })
    .await;
    let id = opened[0].id;
    let during = probe(&admin, "probe-during", inside).await;
    assert_ne!(during, before, "inside an open incident the prior acts");
    let first_alarm = |flags: &[bool]| flags.iter().position(|a| *a);
    assert!(
        first_alarm(&during) <= first_alarm(&before) || first_alarm(&before).is_none(),
        "the prior brings the alarm forward: {:?} against {:?}",
        first_alarm(&during),
        first_alarm(&before)
    );

    let mut watch = reader
        .alarms()
        .watch_incidents(v1::WatchIncidentsRequest::default())
        .await
        .expect("WatchIncidents")
        .into_inner();
    let caught_up = watch.message().await.expect("an event").expect("caught up");
    assert_eq!(caught_up.kind, v1::IncidentEventKind::CaughtUp as i32);

    // Only an admin, with a reason of one to 500 characters, for an incident that exists.
    let car_b = server.connection(Some("car-b-token")).await;
    for (who, connection) in [("the operator", &reader), ("a vehicle", &car_b)] {
        let refused = end(connection, id, "not mine to end").await.expect_err(who);
        assert_eq!(refused.code(), Code::PermissionDenied, "{who}: {refused:?}");
    }
    for reason in ["", "   ", &"x".repeat(501)] {
        let refused = end(&admin, id, reason).await.expect_err("a bad reason");
        assert_eq!(
            refusal(&refused),
            (Code::InvalidArgument, vec!["reason".into()])
        );
    }
    let refused = end(&admin, 0, "").await.expect_err("a bad id and reason");
    assert_eq!(
        refusal(&refused),
        (Code::InvalidArgument, vec!["id".into(), "reason".into()])
    );
    let unknown = end(&admin, id + 41, "no such").await.expect_err("unknown");
    assert_eq!(unknown.code(), Code::NotFound);
    assert!(
        list_incidents(&reader).await[0].open,
        "nothing refused ended it"
    );

    let reason = "fabricated: two test credentials replayed one recording";
    let dismissed = end(&admin, id, reason)
        .await
        .expect("the admin dismisses it");
    let closure = dismissed.closure.clone().expect("the closure is returned");
    assert!(
        !dismissed.open && dismissed.ended_time.is_some(),
        "{dismissed:?}"
    );
    assert_eq!(closure.kind, v1::IncidentClosureKind::Dismissed as i32);
    assert_eq!(closure.reason, reason);
    assert_eq!(closure.closed_by, "admin token");
    assert_eq!(closure.closed_time, dismissed.ended_time);

    // The area prior stops at once: the probe alarms as it did before the incident.
    let after = probe(&admin, "probe-after", inside).await;
    assert_eq!(
        after, before,
        "the dismissed incident's area no longer lowers thresholds"
    );

    // The live watcher sees the end, with the reason.
    let event = tokio::time::timeout(BOUND, watch.message())
        .await
        .expect("the watcher hears of the end in time")
        .expect("an event")
        .expect("the watch goes on");
    assert_eq!(event.kind, v1::IncidentEventKind::Ended as i32);
    let watched = event.incident.expect("the incident");
    assert_eq!((watched.id, watched.closure), (id, Some(closure.clone())));

    let again = end(&admin, id, "twice").await.expect_err("already ended");
    assert_eq!(again.code(), Code::FailedPrecondition, "{again:?}");

    // Stored with the incident; the correlator writes nothing more to it, and its members' alarms,
    // still open, are neither ended nor deleted, and open no new incident.
    tokio::time::sleep(Duration::from_secs(3)).await;
    let stored = reader
        .alarms()
        .get_incident(v1::GetIncidentRequest { id })
        .await
        .expect("GetIncident")
        .into_inner();
    assert_eq!(stored, dismissed);
    assert_eq!(list_incidents(&reader).await.len(), 1, "no new incident");
    let listed = alarms(&reader).await;
    for member in &stored.vehicles {
        let alarm = listed
            .iter()
            .find(|a| a.id == member.alarm_id)
            .expect("listed");
        assert!(alarm.end_time.is_none(), "{alarm:?}");
    }
    drop((reader, admin, car_b, watch));
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_dismissal_through_one_replica_ends_the_incident_on_both() {
    let Some(database) = TestDatabase::create("incidents_end_across_replicas").await else {
        return;
    };
    let dir = tempfile::tempdir().expect("temp dir");
    let replica = async |instance: &str| {
        let mut config = Config::with_database(&database.url);
        config.shutdown_grace_secs = 2;
        config.instance_id = Some(instance.to_string());
        start_with_roles(dir.path(), config).await
    };
    let a = replica("replica-a").await;
    let b = replica("replica-b").await;
    let (admin_a, admin_b) = (
        a.connection(Some(ADMIN_TOKEN)).await,
        b.connection(Some(ADMIN_TOKEN)).await,
    );
    let centre = LatLon::new(31.7, -110.2);
    let inside = place(centre, 4_500.0, 2_598.0);
    let before = probe(&admin_a, "probe-a-before", inside).await;
    spoof_three(&a, centre, "r").await;
    let opened = wait_for_incidents(&admin_b, "the incident opens", BOUND, |stored| {
        stored.len() == 1 && stored[0].vehicles.len() == 3
    })
    .await;
    let id = opened[0].id;
    assert_ne!(probe(&admin_a, "probe-a-during", inside).await, before);
    let mut watch_a = admin_a
        .alarms()
        .watch_incidents(v1::WatchIncidentsRequest::default())
        .await
        .expect("WatchIncidents")
        .into_inner();
    watch_a
        .message()
        .await
        .expect("an event")
        .expect("caught up");

    let dismissed = end(&admin_b, id, "a drill of two replicas")
        .await
        .expect("dismissed through replica B");
    let closure = dismissed.closure.clone().expect("a closure");
    let event = tokio::time::timeout(BOUND, watch_a.message())
        .await
        .expect("replica A's watcher hears of the end in time")
        .expect("an event")
        .expect("the watch goes on");
    assert_eq!(event.kind, v1::IncidentEventKind::Ended as i32);
    assert_eq!(event.incident.expect("the incident").closure, Some(closure));
    // Replica A reads the open incidents' areas once a second.
    tokio::time::sleep(Duration::from_secs(3)).await;
    assert_eq!(
        probe(&admin_a, "probe-a-after", inside).await,
        before,
        "replica A no longer scores with the dismissed incident's area"
    );
    assert_eq!(list_incidents(&admin_a).await, [dismissed]);

    // The same vehicles spoofed again (fresh sessions): new alarms, a new incident.
    spoof_three(&a, centre, "r").await;
    let stored = wait_for_incidents(&admin_b, "a new incident opens", BOUND, |stored| {
        stored.len() == 2
    })
    .await;
    assert!(
        stored[1].open && stored[1].vehicles.len() == 3,
        "{stored:?}"
    );
    assert!(!stored[0].open && stored[0].closure.is_some(), "{stored:?}");
    drop((admin_a, admin_b, watch_a));
    a.stop().await;
    b.stop().await;
    database.drop_database().await;
}
