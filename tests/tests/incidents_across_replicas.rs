//! Area incidents across replicas, for real: two server processes on one PostgreSQL database behind
//! the shipped HAProxy configuration. The vehicles of one spoofed area (every fix displaced by the
//! same 150 m to the east) stream through the balancer and land on both replicas: the incident
//! forms once (one correlator at a time, by lease). The replica holding the lease is killed
//! (`kill -9`, no chance to give the lease up); the other takes the lease over and continues the
//! same incident: vehicles spoofed afterwards join it, and no second incident opens.
//!
//! Needs PostgreSQL (`SPOOFWATCH_TEST_POSTGRES_URL`) and HAProxy (`SPOOFWATCH_HAPROXY`); skipped
//! without them unless `SPOOFWATCH_REQUIRE_POSTGRES=1` / `SPOOFWATCH_REQUIRE_HAPROXY=1`.

use std::time::{Duration, Instant};

use spoofwatch_core::geo::displace_fix;
use spoofwatch_core::scenario::{AttackKind, AttackSpec, DriveSpec, inject, simulate_drive};
use spoofwatch_proto::v1;
use spoofwatch_server::store::test_database::TestDatabase;
use spoofwatch_tests::balancer::{Balancer, REPLICAS, haproxy};
use spoofwatch_tests::replica_process::ReplicaProcess;
use spoofwatch_tests::{Clients, Connection, sessions_on, stream_samples, track_samples};

/// The server binary built with these tests.
const REPLICA_BIN: &str = env!("CARGO_BIN_EXE_spoofwatch-test-replica");
/// The correlator's lease (10 s) plus a few of its 1 s ticks and the alarm writer's batching.
const INCIDENT_BOUND: Duration = Duration::from_secs(40);
/// The area's centre.
const CENTRE: (f64, f64) = (32.23, -110.95);
/// Every captured fix is moved this far east (m).
const TRANSLATION_EAST_M: f64 = 150.0;

/// A vehicle `east_m`/`north_m` from the centre, driving 120 s at 1 Hz, whose fix is moved 150 m
/// east from 40 s on.
fn captured_vehicle(index: usize, east_m: f64, north_m: f64) -> (String, Vec<v1::Sample>) {
    let id = format!("area-car-{index}");
    let (lat, lon) = displace_fix(CENTRE.0, CENTRE.1, east_m, north_m);
    let spec = DriveSpec {
        duration_s: 120.0,
        seed: 500 + index as u64,
        start_lat_deg: lat,
        start_lon_deg: lon,
        ..DriveSpec::default()
    };
    let drive = simulate_drive(&spec, &id).expect("a valid drive");
    let attack = AttackSpec {
        kind: AttackKind::Jump {
            offset_m: TRANSLATION_EAST_M,
        },
        direction_deg: 90.0,
        onset_s: 40.0,
        duration_s: 80.0,
        seed: None,
    };
    let track = inject(&drive, &attack).expect("a valid attack").track;
    (id, track_samples(&track))
}

/// The stored incidents, through `clients`.
async fn incidents(clients: &Clients) -> Vec<v1::Incident> {
    clients
        .alarms
        .clone()
        .list_incidents(v1::ListIncidentsRequest::default())
        .await
        .expect("ListIncidents")
        .into_inner()
        .incidents
}

/// Waits until the stored incidents satisfy `done`.
async fn wait_for_incidents(clients: &Clients, what: &str, done: impl Fn(&[v1::Incident]) -> bool) {
    let deadline = Instant::now() + INCIDENT_BOUND;
    loop {
        let stored = incidents(clients).await;
        if done(&stored) {
            return;
        }
        assert!(Instant::now() < deadline, "{what}: {stored:?}");
        tokio::time::sleep(Duration::from_millis(250)).await;
    }
}

/// The instance whose process holds the correlator's lease now.
async fn lease_holder(database: &str) -> String {
    let pool = sqlx::PgPool::connect(database).await.expect("connect");
    let owner: Option<String> =
        sqlx::query_scalar("SELECT owner FROM incident_correlator WHERE id = 1")
            .fetch_one(&pool)
            .await
            .expect("the correlator row");
    pool.close().await;
    let owner = owner.expect("a server holds the lease");
    owner.split('#').next().unwrap_or_default().to_string()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn one_incident_forms_across_replicas_and_survives_its_correlator_s_kill() {
    let Some(haproxy) = haproxy() else {
        return;
    };
    let Some(database) = TestDatabase::create("incidents_across_replicas").await else {
        return;
    };
    let mut replicas = vec![
        Some(ReplicaProcess::start(
            REPLICA_BIN,
            &database.url,
            REPLICAS[0],
        )),
        Some(ReplicaProcess::start(
            REPLICA_BIN,
            &database.url,
            REPLICAS[1],
        )),
    ];
    let addrs = [0, 1].map(|k| replicas[k].as_ref().expect("started").addr);
    let lb_dir = tempfile::tempdir().expect("temp dir");
    let balancer = Balancer::start(&haproxy, lb_dir.path(), addrs);
    for replica in REPLICAS {
        balancer.wait_for(replica, "UP", Some("L7OK")).await;
    }
    let through_lb = Connection::connect(format!("http://{}", balancer.addr), None)
        .await
        .expect("connect to the balancer");
    let lb_clients = Clients::new(through_lb.clone());

    // Six vehicles a few km apart, spoofed alike: they spread over both replicas.
    let first_wave: Vec<_> = (0..6)
        .map(|k| {
            let angle = k as f64 * std::f64::consts::TAU / 6.0;
            captured_vehicle(k, 2_500.0 * angle.sin(), 2_500.0 * angle.cos())
        })
        .collect();
    for (id, samples) in &first_wave {
        stream_samples(&through_lb, id, true, 1, samples).await;
    }
    let mut placement = Vec::new();
    for replica in replicas.iter().flatten() {
        placement.push(sessions_on(&replica.clients().await).await);
    }
    assert!(
        placement.iter().all(|on| !on.is_empty()),
        "the area's vehicles are on both replicas: {placement:?}"
    );

    wait_for_incidents(&lb_clients, "one incident of the six vehicles", |stored| {
        stored.len() == 1 && stored[0].vehicles.len() == 6
    })
    .await;
    let incident = &incidents(&lb_clients).await[0];
    assert_eq!(incident.kind(), v1::IncidentKind::Translation);
    assert!(
        (incident.offset_east_m - TRANSLATION_EAST_M).abs() < 20.0
            && incident.offset_north_m.abs() < 20.0,
        "the estimate is the common translation: {incident:?}"
    );

    // kill -9 the replica that correlates; HAProxy takes it out.
    let holder = lease_holder(&database.url).await;
    let killed = REPLICAS
        .iter()
        .position(|r| *r == holder)
        .unwrap_or_else(|| panic!("the holder {holder:?} is one of the replicas"));
    drop(replicas[killed].take());
    balancer.wait_for(REPLICAS[killed], "DOWN", None).await;

    // Two more vehicles are spoofed alike: the other replica takes the lease over and adds them to
    // the same incident.
    for k in 6..8 {
        let (id, samples) = captured_vehicle(k, 1_000.0 * (k as f64 - 6.5), -1_500.0);
        stream_samples(&through_lb, &id, true, 1, &samples).await;
    }
    wait_for_incidents(
        &lb_clients,
        "the same incident with eight vehicles",
        |stored| stored.len() == 1 && stored[0].vehicles.len() == 8,
    )
    .await;
    assert_ne!(
        lease_holder(&database.url).await,
        holder,
        "the survivor holds the lease"
    );
    let events = lb_clients
        .alarms
        .clone()
        .watch_incidents(v1::WatchIncidentsRequest {
            after_cursor: Some(0),
            stop_when_caught_up: true,
        })
        .await
        .expect("WatchIncidents")
        .into_inner();
    let kinds: Vec<v1::IncidentEventKind> =
        tokio_stream::StreamExt::collect::<Vec<_>>(tokio_stream::StreamExt::map(events, |event| {
            event.expect("an event").kind()
        }))
        .await;
    let opened = kinds
        .iter()
        .filter(|k| **k == v1::IncidentEventKind::Opened)
        .count();
    assert_eq!(opened, 1, "the incident formed once: {kinds:?}");
    assert!(
        !kinds.contains(&v1::IncidentEventKind::Ended),
        "it is still open: {kinds:?}"
    );

    drop((through_lb, lb_clients, balancer, replicas));
    database.drop_database().await;
}
