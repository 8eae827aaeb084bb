//! One source takes part in a bounded number of open area incidents, black-box
//! (`--incident-max-per-source`, 3 by default): a server with a roles file, whose callers send
//! vehicles whose every fix jumps 200 m east (a consistent spoofing), in areas 100 km apart.
//!
//! A bridge gateway (all its vehicles one source) has one vehicle in each of three incidents, opened
//! with a relay gateway's independent receivers. Its fourth vehicle, captured inside a fourth open
//! incident, alarms but joins it not; its fifth and sixth, captured in an area where only one other
//! receiver alarms yet, open nothing with it, and the incident that opens there once two more
//! receivers alarm holds the receivers alone.

use std::time::Duration;

use spoofwatch_core::geo::{LatLon, displace_fix};
use spoofwatch_core::scenario::AttackKind;
use spoofwatch_proto::v1;
use spoofwatch_tests::incidents::{attacked_drive, incident_vehicles, wait_for_incidents};
use spoofwatch_tests::{Connection, start_with_roles, stream_samples, token_sha256};

/// The correlator's 1 s ticks, the alarm writer's batching, on shared cores.
const INCIDENT_BOUND: Duration = Duration::from_secs(40);
/// The server's default `--incident-max-per-source`.
const BOUND: usize = 3;

fn roles() -> String {
    format!(
        "[tokens]\n\
         \"{}\" = {{ name = \"bridge\", role = \"gateway\", vehicle_prefixes = [\"gw-\"] }}\n\
         \"{}\" = {{ name = \"relay\", role = \"gateway\", vehicle_prefixes = [\"rl-\"], \
         independent_receivers = true }}\n\
         \"{}\" = {{ name = \"dashboard\", role = \"operator\" }}\n",
        token_sha256("bridge-token"),
        token_sha256("relay-token"),
        token_sha256("dashboard-token"),
    )
}

/// The spoofed areas, 100 km apart.
fn area(k: usize) -> LatLon {
    LatLon::new(32.0 + k as f64 * 0.9, -110.9)
}

/// `east_m`/`north_m` from area `k`'s corner; the vehicles of an area lie within 9 km of each
/// other.
fn place(k: usize, east_m: f64, north_m: f64) -> LatLon {
    let corner = area(k);
    let (lat, lon) = displace_fix(corner.lat_deg, corner.lon_deg, east_m, north_m);
    LatLon::new(lat, lon)
}

const TRIANGLE: [(f64, f64); 3] = [(0.0, 0.0), (9_000.0, 0.0), (4_500.0, 7_794.0)];

/// A vehicle starting at `start`, driving 90 s at 1 Hz, whose fix jumps 200 m east from 40 s on.
async fn stream_captured(connection: &Connection, id: &str, start: LatLon, seed: u64) {
    let jump = AttackKind::Jump { offset_m: 200.0 };
    let samples = attacked_drive(id, start, seed, (jump, 90.0, 40.0));
    stream_samples(connection, id, true, 1, &samples).await;
}

fn has_vehicle(incident: &v1::Incident, id: &str) -> bool {
    incident.vehicles.iter().any(|v| v.vehicle_id == id)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_source_takes_part_in_at_most_its_bound_of_open_incidents() {
    let dir = tempfile::tempdir().expect("temp dir");
    let server = start_with_roles(dir.path(), &roles(), None).await;
    let reader = server.connection(Some("dashboard-token")).await;
    let bridge = server.connection(Some("bridge-token")).await;
    let relay = server.connection(Some("relay-token")).await;

    // Areas 0..3: the bridge's vehicle and two receivers each, one incident each.
    for k in 0..BOUND {
        let [(e0, n0), (e1, n1), (e2, n2)] = TRIANGLE;
        let seed = 10 * k as u64;
        stream_captured(&bridge, &format!("gw-{k}"), place(k, e0, n0), seed).await;
        stream_captured(&relay, &format!("rl-{k}a"), place(k, e1, n1), seed + 1).await;
        stream_captured(&relay, &format!("rl-{k}b"), place(k, e2, n2), seed + 2).await;
    }
    let stored = wait_for_incidents(
        &reader,
        "the bridge's three incidents",
        INCIDENT_BOUND,
        |stored| stored.len() == BOUND && stored.iter().all(|i| i.vehicles.len() == 3),
    )
    .await;
    for (k, incident) in stored.iter().enumerate() {
        assert_eq!(
            incident_vehicles(incident),
            [format!("gw-{k}"), format!("rl-{k}a"), format!("rl-{k}b")],
            "{stored:?}"
        );
    }

    // Area 3: three receivers open an incident; the bridge's vehicle captured in it joins not,
    // and a receiver streamed after it does (so the correlator has read the bridge's alarm).
    let k = BOUND;
    for (j, (east, north)) in TRIANGLE.iter().enumerate() {
        let id = format!("rl-{k}{}", ['a', 'b', 'c'][j]);
        stream_captured(&relay, &id, place(k, *east, *north), 40 + j as u64).await;
    }
    wait_for_incidents(
        &reader,
        "the receivers' incident of area 3",
        INCIDENT_BOUND,
        |stored| stored.len() == BOUND + 1 && stored[BOUND].vehicles.len() == 3,
    )
    .await;
    stream_captured(&bridge, "gw-3", place(k, 4_500.0, -2_000.0), 50).await;
    stream_captured(&relay, "rl-3d", place(k, 4_500.0, 5_000.0), 51).await;
    let stored = wait_for_incidents(&reader, "rl-3d joins", INCIDENT_BOUND, |stored| {
        stored.len() == BOUND + 1 && has_vehicle(&stored[BOUND], "rl-3d")
    })
    .await;
    assert_eq!(
        incident_vehicles(&stored[BOUND]),
        ["rl-3a", "rl-3b", "rl-3c", "rl-3d"],
        "the bridge at its bound joins no fourth incident"
    );

    // Area 4: two of the bridge's vehicles and one receiver would open an incident (two sources,
    // three vehicles); at its bound the bridge opens none, and the receivers open one alone.
    let k = BOUND + 1;
    stream_captured(&bridge, "gw-4a", place(k, 0.0, 0.0), 60).await;
    stream_captured(&bridge, "gw-4b", place(k, 9_000.0, 0.0), 61).await;
    stream_captured(&relay, "rl-4a", place(k, 4_500.0, 7_794.0), 62).await;
    stream_captured(&relay, "rl-4b", place(k, 4_500.0, 2_000.0), 63).await;
    stream_captured(&relay, "rl-4c", place(k, 2_000.0, 4_000.0), 64).await;
    let stored = wait_for_incidents(
        &reader,
        "the receivers' incident of area 4",
        INCIDENT_BOUND,
        |stored| stored.len() == BOUND + 2 && stored[BOUND + 1].vehicles.len() == 3,
    )
    .await;
    assert_eq!(
        incident_vehicles(&stored[BOUND + 1]),
        ["rl-4a", "rl-4b", "rl-4c"],
        "the bridge at its bound opens none"
    );
    let bridge_in = stored
        .iter()
        .filter(|i| i.vehicles.iter().any(|v| v.vehicle_id.starts_with("gw-")))
        .count();
    assert_eq!(bridge_in, BOUND, "{stored:?}");

    // Beyond the bound the bridge's vehicles still alarm.
    let alarms = reader
        .alarms()
        .list_alarms(v1::ListAlarmsRequest::default())
        .await
        .expect("ListAlarms")
        .into_inner()
        .alarms;
    let mut alarmed: Vec<&str> = alarms
        .iter()
        .map(|a| a.vehicle_id.as_str())
        .filter(|id| id.starts_with("gw-"))
        .collect();
    alarmed.sort_unstable();
    alarmed.dedup();
    assert_eq!(
        alarmed,
        ["gw-0", "gw-1", "gw-2", "gw-3", "gw-4a", "gw-4b"],
        "{alarms:?}"
    );
    server.stop().await;
}
