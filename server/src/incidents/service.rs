//! ListIncidents, GetIncident and WatchIncidents (on the AlarmService): stored incidents and the
//! incident event log on the wire. WatchIncidents is the shared watch of `crate::event_log`, with
//! WatchAlarms' cursor and resume semantics.
//!
//! It only reads: incidents are written by the correlator (`super::correlator`).

use spoofwatch_core::geo::LatLon;
use spoofwatch_core::incident::{Incident, IncidentVehicle, Spoofing};
use spoofwatch_proto::v1;
use spoofwatch_proto::wire::convert::timestamp_from_ms;
use tonic::Status;

use crate::edge::page_request;
use crate::event_log::EventLog;
use crate::event_log::feed::Feed;
use crate::status::{invalid_field, not_found};
use crate::store::{
    IncidentEventKind, IncidentRow, IncidentState, LoggedIncidentEvent, Store, StoreError,
};

/// The incident event log (no filter: every incident).
#[derive(Debug)]
pub struct IncidentLog;

/// The live feed of stored incident events.
pub type IncidentFeed = Feed<IncidentLog>;

impl EventLog for IncidentLog {
    type Event = LoggedIncidentEvent;
    type Filter = ();
    type Message = v1::IncidentEvent;
    const NAME: &'static str = "incident";
    const LISTING_RPC: &'static str = "ListIncidents";

    fn position(event: &LoggedIncidentEvent) -> i64 {
        event.position
    }

    async fn read(
        store: &Store,
        after: i64,
        through: i64,
        _filter: Option<&()>,
        limit: u32,
    ) -> Result<Vec<LoggedIncidentEvent>, StoreError> {
        store.incident_events_after(after, through, limit).await
    }

    async fn latest(store: &Store) -> Result<i64, StoreError> {
        store.latest_incident_position().await
    }

    fn wanted(_filter: Option<&()>, _event: &LoggedIncidentEvent) -> bool {
        true
    }

    fn message(logged: &LoggedIncidentEvent) -> v1::IncidentEvent {
        let kind = match logged.kind {
            IncidentEventKind::Opened => v1::IncidentEventKind::Opened,
            IncidentEventKind::Joined => v1::IncidentEventKind::Joined,
            IncidentEventKind::Ended => v1::IncidentEventKind::Ended,
        };
        let ended_at_ms = (logged.kind == IncidentEventKind::Ended).then_some(logged.stored_at_ms);
        v1::IncidentEvent {
            cursor: logged.position,
            kind: kind as i32,
            incident: Some(incident_to_proto(
                logged.incident_id,
                &logged.body,
                logged.opened_at_ms,
                ended_at_ms,
            )),
        }
    }

    fn caught_up(cursor: i64) -> v1::IncidentEvent {
        v1::IncidentEvent {
            cursor,
            kind: v1::IncidentEventKind::CaughtUp as i32,
            incident: None,
        }
    }
}

/// ListIncidents.
pub async fn list(
    store: &Store,
    request: &v1::ListIncidentsRequest,
) -> Result<v1::ListIncidentsResponse, Status> {
    let state = match v1::IncidentStateFilter::try_from(request.state) {
        Ok(v1::IncidentStateFilter::Unspecified) => IncidentState::Any,
        Ok(v1::IncidentStateFilter::Open) => IncidentState::Open,
        Ok(v1::IncidentStateFilter::Ended) => IncidentState::Ended,
        Err(_) => {
            return Err(invalid_field(
                "state",
                format!("unknown state {}", request.state),
            ));
        }
    };
    let page = store
        .list_incidents(
            state,
            &page_request(request.page_size, &request.page_token)?,
        )
        .await?;
    Ok(v1::ListIncidentsResponse {
        incidents: page.items.iter().map(row_to_proto).collect(),
        next_page_token: page.next_page_token.unwrap_or_default(),
    })
}

/// GetIncident.
pub async fn get(store: &Store, request: &v1::GetIncidentRequest) -> Result<v1::Incident, Status> {
    if request.id <= 0 {
        return Err(invalid_field(
            "id",
            format!("must be a positive incident id, got {}", request.id),
        ));
    }
    match store.get_incident(request.id).await? {
        Some(row) => Ok(row_to_proto(&row)),
        None => Err(not_found("incident", &request.id.to_string())),
    }
}

fn row_to_proto(row: &IncidentRow) -> v1::Incident {
    incident_to_proto(row.id, &row.body, row.opened_at_ms, row.ended_at_ms)
}

/// A stored incident on the wire. A body this build cannot read (written by a newer server) is
/// sent with its id and times only, and logged.
fn incident_to_proto(
    id: i64,
    body: &serde_json::Value,
    opened_at_ms: i64,
    ended_at_ms: Option<i64>,
) -> v1::Incident {
    let mut wire = match serde_json::from_value::<Incident>(body.clone()) {
        Ok(incident) => incident_body_to_proto(&incident),
        Err(error) => {
            tracing::warn!(incident = id, %error, "a stored incident could not be read");
            v1::Incident::default()
        }
    };
    wire.id = id;
    wire.opened_time = Some(timestamp_from_ms(opened_at_ms));
    wire.ended_time = ended_at_ms.map(timestamp_from_ms);
    wire
}

fn incident_body_to_proto(incident: &Incident) -> v1::Incident {
    let mut wire = v1::Incident {
        centre_latitude_deg: incident.centre.lat_deg,
        centre_longitude_deg: incident.centre.lon_deg,
        radius_m: incident.radius_m,
        onset_s: incident.onset_s,
        confirmed_s: incident.confirmed_s,
        last_evidence_s: incident.last_evidence_s,
        ended_s: incident.ended_s,
        open: incident.is_open(),
        confidence: incident.confidence,
        vehicles: incident.vehicles.iter().map(vehicle_to_proto).collect(),
        credentials: incident
            .credentials()
            .into_iter()
            .map(str::to_string)
            .collect(),
        sources: u32::try_from(incident.source_count()).unwrap_or(u32::MAX),
        ..v1::Incident::default()
    };
    match incident.spoofing {
        Spoofing::FalsePosition { position } => {
            wire.set_kind(v1::IncidentKind::FalsePosition);
            wire.false_latitude_deg = position.lat_deg;
            wire.false_longitude_deg = position.lon_deg;
        }
        Spoofing::Translation { offset_m } => {
            wire.set_kind(v1::IncidentKind::Translation);
            [wire.offset_east_m, wire.offset_north_m] = offset_m;
        }
        Spoofing::Drift { drift_mps } => {
            wire.set_kind(v1::IncidentKind::Drift);
            [wire.drift_east_mps, wire.drift_north_mps] = drift_mps;
        }
    }
    wire
}

fn vehicle_to_proto(vehicle: &IncidentVehicle) -> v1::IncidentVehicle {
    let LatLon { lat_deg, lon_deg } = vehicle.anchor();
    v1::IncidentVehicle {
        vehicle_id: vehicle.vehicle_id.clone(),
        alarm_id: vehicle.alarm_id,
        onset_s: vehicle.onset_s,
        latitude_deg: lat_deg,
        longitude_deg: lon_deg,
        offset_east_m: vehicle.offset_m[0],
        offset_north_m: vehicle.offset_m[1],
        drift_east_mps: vehicle.drift_mps[0],
        drift_north_mps: vehicle.drift_mps[1],
        alarm_open: vehicle.alarm_open,
        credential: vehicle.credential.clone(),
    }
}
