//! Area incidents rest on independent evidence, black-box: a server with a roles file, whose callers
//! send vehicles whose every fix jumps 200 m east (a consistent spoofing), as the attacks on
//! incidents did.
//!
//! - One gateway token inventing three vehicle ids 9 km apart raises three alarms (each recording
//!   the gateway's token) and opens no incident: its vehicles are one source.
//! - Two credentials (the gateway's two vehicles and a vehicle token's own) open one, listing both
//!   credentials; a gateway the roles file says forwards independent receivers opens one alone.
//! - A gateway's streams opened before the roles file marks it as forwarding independent receivers
//!   raise their later alarms under the new grant: its three vehicles then open an incident.
//! - Ten made-up vehicles, each placed 9 km east of where the incident's centre is by then, join
//!   it but cannot walk it: its centre stays where its first members were captured and its area
//!   within the configured radius plus the margin.

use std::time::Duration;

use spoofwatch_core::geo::{LatLon, displace_fix, wgs84_local_displacement};
use spoofwatch_core::scenario::AttackKind;
use spoofwatch_proto::v1;
use spoofwatch_tests::incidents::{
    attacked_drive, incident_vehicles, list_incidents, wait_for_incidents,
};
use spoofwatch_tests::{
    Connection, DetectStream, REPLY_TIMEOUT, TestServer, start_with_roles, stream_samples,
    token_sha256,
};

/// The correlator's 1 s ticks, the alarm writer's batching, on shared cores.
const INCIDENT_BOUND: Duration = Duration::from_secs(40);
/// Every captured fix jumps this far east (m).
const JUMP_EAST_M: f64 = 200.0;
/// The server's default incident radius and margin (m).
const RADIUS_M: f64 = 10_000.0;
const MARGIN_M: f64 = 1_000.0;

/// A bridge gateway (its vehicles one source), a vehicle token, and a relay gateway forwarding
/// independent receivers.
fn roles() -> String {
    format!(
        "[tokens]\n\
         \"{}\" = {{ name = \"bridge\", role = \"gateway\", vehicle_prefixes = [\"gw-\"] }}\n\
         \"{}\" = {{ name = \"car-b\", role = \"vehicle\" }}\n\
         \"{}\" = {{ name = \"relay\", role = \"gateway\", vehicle_prefixes = [\"rl-\"], \
         independent_receivers = true }}\n\
         \"{}\" = {{ name = \"dashboard\", role = \"operator\" }}\n",
        token_sha256("bridge-token"),
        token_sha256("car-b-token"),
        token_sha256("relay-token"),
        token_sha256("dashboard-token"),
    )
}

/// The credential an alarm of `name`'s token records.
fn token_credential(name: &str, token: &str) -> String {
    format!("token {name} sha256:{}", &token_sha256(token)[..16])
}

/// `east_m`/`north_m` from `centre`.
fn place(centre: LatLon, east_m: f64, north_m: f64) -> LatLon {
    let (lat, lon) = displace_fix(centre.lat_deg, centre.lon_deg, east_m, north_m);
    LatLon::new(lat, lon)
}

/// A vehicle starting at `start`, driving 90 s at 1 Hz, whose fix jumps 200 m east from 40 s on.
fn captured(id: &str, start: LatLon, seed: u64) -> Vec<v1::Sample> {
    let jump = AttackKind::Jump {
        offset_m: JUMP_EAST_M,
    };
    attacked_drive(id, start, seed, (jump, 90.0, 40.0))
}

async fn stream_captured(connection: &Connection, id: &str, start: LatLon, seed: u64) {
    stream_samples(connection, id, true, 1, &captured(id, start, seed)).await;
}

fn centre(incident: &v1::Incident) -> LatLon {
    LatLon::new(incident.centre_latitude_deg, incident.centre_longitude_deg)
}

async fn start(dir: &std::path::Path) -> (TestServer, Connection) {
    let server = start_with_roles(dir, &roles(), None).await;
    let reader = server.connection(Some("dashboard-token")).await;
    (server, reader)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn one_credential_opens_no_incident_and_independent_ones_do() {
    let dir = tempfile::tempdir().expect("temp dir");
    let (server, reader) = start(dir.path()).await;
    let bridge = server.connection(Some("bridge-token")).await;
    let car_b = server.connection(Some("car-b-token")).await;
    let relay = server.connection(Some("relay-token")).await;
    // Three areas 100 km apart, each of three vehicles 9 km from each other.
    let area = |k: f64| LatLon::new(32.0 + k * 0.9, -110.9);
    let triangle = [(0.0, 0.0), (9_000.0, 0.0), (4_500.0, 7_794.0)];

    // Area A: one gateway token, three vehicle ids.
    for (k, (east, north)) in triangle.iter().enumerate() {
        let id = format!("gw-a{k}");
        stream_captured(&bridge, &id, place(area(0.0), *east, *north), 10 + k as u64).await;
    }
    // Area B: two of the gateway's vehicles and one vehicle with its own token.
    for (k, (east, north)) in triangle.iter().enumerate() {
        let (connection, id) = match k {
            2 => (&car_b, "car-b".to_string()),
            _ => (&bridge, format!("gw-b{k}")),
        };
        stream_captured(
            connection,
            &id,
            place(area(1.0), *east, *north),
            20 + k as u64,
        )
        .await;
    }
    // Area C: a gateway forwarding independent receivers, alone.
    for (k, (east, north)) in triangle.iter().enumerate() {
        let id = format!("rl-c{k}");
        stream_captured(&relay, &id, place(area(2.0), *east, *north), 30 + k as u64).await;
    }

    // The correlator reads the alarms in the order they were stored: once B's and C's incidents
    // are open, A's alarms were read too.
    wait_for_incidents(
        &reader,
        "the incidents of areas B and C",
        INCIDENT_BOUND,
        |stored| stored.len() >= 2 && stored.iter().all(|i| i.vehicles.len() == 3),
    )
    .await;
    tokio::time::sleep(Duration::from_secs(2)).await;
    let stored = list_incidents(&reader).await;
    assert_eq!(
        stored.len(),
        2,
        "no incident of the gateway alone: {stored:?}"
    );
    assert_eq!(incident_vehicles(&stored[0]), ["car-b", "gw-b0", "gw-b1"]);
    assert_eq!(stored[0].sources, 2);
    let mut credentials = stored[0].credentials.clone();
    credentials.sort();
    assert_eq!(
        credentials,
        [
            token_credential("bridge", "bridge-token"),
            token_credential("car-b", "car-b-token"),
        ]
    );
    assert_eq!(incident_vehicles(&stored[1]), ["rl-c0", "rl-c1", "rl-c2"]);
    assert_eq!(stored[1].sources, 3, "each receiver its own source");
    assert_eq!(
        stored[1].credentials,
        [token_credential("relay", "relay-token")]
    );

    // The gateway's vehicles of area A did alarm, each alarm recording the gateway's token.
    let alarms = reader
        .alarms()
        .list_alarms(v1::ListAlarmsRequest::default())
        .await
        .expect("ListAlarms")
        .into_inner()
        .alarms;
    let area_a: Vec<_> = alarms
        .iter()
        .filter(|a| a.vehicle_id.starts_with("gw-a"))
        .map(|a| (a.vehicle_id.as_str(), a.credential.clone()))
        .collect();
    let bridge_credential = Some(token_credential("bridge", "bridge-token"));
    assert_eq!(
        area_a,
        [
            ("gw-a0", bridge_credential.clone()),
            ("gw-a1", bridge_credential.clone()),
            ("gw-a2", bridge_credential),
        ],
        "{alarms:?}"
    );
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn chained_joins_cannot_walk_an_incident_beyond_its_radius() {
    let dir = tempfile::tempdir().expect("temp dir");
    let (server, reader) = start(dir.path()).await;
    let relay = server.connection(Some("relay-token")).await;
    let origin = LatLon::new(33.5, -111.5);
    for (k, (east, north)) in [(0.0, 0.0), (0.0, 2_000.0), (0.0, -2_000.0)]
        .into_iter()
        .enumerate()
    {
        let id = format!("rl-d{k}");
        stream_captured(&relay, &id, place(origin, east, north), 40 + k as u64).await;
    }
    let opened = wait_for_incidents(
        &reader,
        "the incident of three receivers",
        INCIDENT_BOUND,
        |stored| stored.len() == 1 && stored[0].vehicles.len() == 3,
    )
    .await;
    let first_centre = centre(&opened[0]);

    // Each made-up vehicle 9 km east of the centre as it is by then, after the previous one joined.
    for k in 1..=10 {
        let now = centre(&list_incidents(&reader).await[0]);
        let id = format!("rl-made-up-{k}");
        stream_captured(&relay, &id, place(now, 9_000.0, 0.0), 100 + k).await;
        wait_for_incidents(&reader, &format!("{id} joins"), INCIDENT_BOUND, |stored| {
            stored[0].vehicles.iter().any(|v| v.vehicle_id == id)
        })
        .await;
    }
    let stored = list_incidents(&reader).await;
    assert_eq!(stored.len(), 1, "{stored:?}");
    let incident = &stored[0];
    assert_eq!(incident.vehicles.len(), 13);
    let moved = wgs84_local_displacement(first_centre, centre(incident));
    assert!(
        moved[0].hypot(moved[1]) < 1.0,
        "the centre stays where the incident opened (moved {moved:?})"
    );
    assert!(
        incident.radius_m <= RADIUS_M + MARGIN_M,
        "the area stays within the radius: {} m",
        incident.radius_m
    );
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_gateway_marked_independent_while_its_streams_are_open_counts_each_vehicle_on_them() {
    let dir = tempfile::tempdir().expect("temp dir");
    let (server, reader) = start(dir.path()).await;
    let bridge = server.connection(Some("bridge-token")).await;
    let origin = LatLon::new(34.5, -112.0);
    let triangle = [(0.0, 0.0), (9_000.0, 0.0), (4_500.0, 7_794.0)];
    // The bridge's three streams open, and score their vehicles' drives up to the capture at 40 s,
    // while the roles file still counts its vehicles as one source.
    let mut streams = Vec::new();
    for (k, (east, north)) in triangle.iter().enumerate() {
        let id = format!("gw-e{k}");
        let samples = captured(&id, place(origin, *east, *north), 50 + k as u64);
        let (stream, _) = DetectStream::start(&bridge, &id, "", true)
            .await
            .unwrap_or_else(|e| panic!("{id}: the stream opens: {e}"));
        let mut stream = stream.with_reply_timeout(REPLY_TIMEOUT);
        stream
            .detect(1, samples[..30].to_vec())
            .await
            .unwrap_or_else(|e| panic!("{id}: detections: {e}"));
        streams.push((stream, samples));
    }

    // The roles file now marks the bridge as forwarding independent receivers (and admits a probe
    // token, by which the change is seen to be in force).
    let changed = roles().replacen(
        "vehicle_prefixes = [\"gw-\"] }",
        "vehicle_prefixes = [\"gw-\"], independent_receivers = true }",
        1,
    ) + &format!(
        "\"{}\" = {{ name = \"probe\", role = \"operator\" }}\n",
        token_sha256("probe-token")
    );
    std::fs::write(dir.path().join("roles.toml"), changed).expect("roles file rewritten");
    let probe = server.connection(Some("probe-token")).await;
    let deadline = tokio::time::Instant::now() + Duration::from_secs(20);
    while list_incidents_answer(&probe).await != tonic::Code::Ok {
        assert!(
            tokio::time::Instant::now() < deadline,
            "the changed roles file was not in force within 20 s"
        );
        tokio::time::sleep(Duration::from_millis(200)).await;
    }

    // The captures arrive on the streams opened before the change: each vehicle is its own source.
    for (stream, samples) in &mut streams {
        stream
            .detect(2, samples[30..].to_vec())
            .await
            .expect("the stream goes on under the new grant");
    }
    for (stream, _) in streams {
        stream.finish().await.expect("it ends with OK");
    }
    let stored = wait_for_incidents(
        &reader,
        "the incident of the bridge's three receivers",
        INCIDENT_BOUND,
        |stored| stored.len() == 1 && stored[0].vehicles.len() == 3,
    )
    .await;
    assert_eq!(incident_vehicles(&stored[0]), ["gw-e0", "gw-e1", "gw-e2"]);
    assert_eq!(stored[0].sources, 3, "each receiver its own source");
    assert_eq!(
        stored[0].credentials,
        [token_credential("bridge", "bridge-token")]
    );
    server.stop().await;
}

/// What a new ListIncidents call through `connection` is answered with.
async fn list_incidents_answer(connection: &Connection) -> tonic::Code {
    connection
        .alarms()
        .list_incidents(v1::ListIncidentsRequest::default())
        .await
        .map_or_else(|status| status.code(), |_| tonic::Code::Ok)
}
