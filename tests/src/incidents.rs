//! Reading a server's area incidents in black-box tests: the stored list, waiting for it to reach
//! a state, and an incident's vehicles.
//!
//! Owns nothing but these reads. Must not start servers or stream samples (the crate root does).

use std::time::{Duration, Instant};

use spoofwatch_client::Connection;
use spoofwatch_proto::v1;

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
