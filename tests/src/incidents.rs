//! Area incidents in black-box tests: the attacked drives that open them, and reading them back
//! (the stored list, waiting for it to reach a state, an incident's vehicles).
//!
//! Owns nothing but these reads. Must not start servers or stream samples (the crate root does).

use std::time::{Duration, Instant};

use spoofwatch_client::Connection;
use spoofwatch_core::geo::LatLon;
use spoofwatch_core::scenario::{AttackKind, AttackSpec, DriveSpec, inject, simulate_drive};
use spoofwatch_proto::v1;

use crate::track_samples;

/// Every stored incident (ListIncidents' first page, which holds all a test makes).
pub async fn list_incidents(reader: &Connection) -> Vec<v1::Incident> {
    reader
        .alarms()
        .list_incidents(v1::ListIncidentsRequest::default())
        .await
        .expect("ListIncidents")
        .into_inner()
        .incidents
}

/// Waits up to `within` until the stored incidents satisfy `done`; returns them, or fails the test
/// with `what` and the last list.
pub async fn wait_for_incidents(
    reader: &Connection,
    what: &str,
    within: Duration,
    done: impl Fn(&[v1::Incident]) -> bool,
) -> Vec<v1::Incident> {
    let deadline = Instant::now() + within;
    loop {
        let stored = list_incidents(reader).await;
        if done(&stored) {
            return stored;
        }
        assert!(Instant::now() < deadline, "{what}: {stored:?}");
        tokio::time::sleep(Duration::from_millis(250)).await;
    }
}

/// An incident's vehicle ids, sorted.
pub fn incident_vehicles(incident: &v1::Incident) -> Vec<&str> {
    let mut ids: Vec<&str> = incident
        .vehicles
        .iter()
        .map(|v| v.vehicle_id.as_str())
        .collect();
    ids.sort_unstable();
    ids
}

/// A 90 s drive at 1 Hz from `start`, attacked from `onset_s` to its end by `kind` in
/// `direction_deg`: the vehicles the incident tests place near each other.
pub fn attacked_drive(
    id: &str,
    start: LatLon,
    seed: u64,
    (kind, direction_deg, onset_s): (AttackKind, f64, f64),
) -> Vec<v1::Sample> {
    let spec = DriveSpec {
        duration_s: 90.0,
        seed,
        start_lat_deg: start.lat_deg,
        start_lon_deg: start.lon_deg,
        ..DriveSpec::default()
    };
    let drive = simulate_drive(&spec, id).expect("a valid drive");
    let attack = AttackSpec {
        kind,
        direction_deg,
        onset_s,
        duration_s: 90.0 - onset_s,
        seed: None,
    };
    track_samples(&inject(&drive, &attack).expect("a valid attack").track)
}
