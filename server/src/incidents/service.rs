//! ListIncidents, GetIncident, WatchIncidents and EndIncident (on the AlarmService): stored
//! incidents and the incident event log on the wire, and an admin's end of an incident.
//! WatchIncidents is the shared watch of `crate::event_log`, with WatchAlarms' cursor and resume
//! semantics.
//!
//! Incidents are written by the correlator (`super::correlator`); the one write here is
//! EndIncident's closure ([`end`]), which the correlator then honours. It must not touch alarms:
//! an incident's end leaves its vehicles' alarms as they are.

use spoofwatch_core::geo::LatLon;
use spoofwatch_core::incident::{Incident, IncidentVehicle, Spoofing};
use spoofwatch_proto::v1;
use spoofwatch_proto::wire::convert::timestamp_from_ms;
use tokio::sync::Notify;
use tonic::Status;

use super::areas::IncidentAreas;
use super::correlator::refresh_areas;
use super::settings::IncidentTimeline;
use crate::edge::page_request;
use crate::event_log::EventLog;
use crate::event_log::feed::Feed;
use crate::status::{failed_precondition, invalid_argument, invalid_field, not_found};
use crate::store::{
    CloseOutcome, Closure, ClosureKind, IncidentEventKind, IncidentRow, IncidentState,
    LoggedIncidentEvent, Store, StoreError, StoredClosure, now_unix_ms,
};
use crate::telemetry;

/// The longest EndIncident reason (characters): a sentence or two for the audit record.
pub const MAX_REASON_CHARS: usize = 500;

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
        let ended = logged.kind == IncidentEventKind::Ended;
        let no_closure = StoredClosure::default();
        v1::IncidentEvent {
            cursor: logged.position,
            kind: kind as i32,
            incident: Some(incident_to_proto(
                logged.incident_id,
                &logged.body,
                logged.opened_at_ms,
                ended.then_some(logged.stored_at_ms),
                // Only the ENDED event of an incident ended by hand is the closure's.
                if ended { &logged.closure } else { &no_closure },
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

/// Who ends an incident through EndIncident, and what the server that serves the call updates at
/// once.
pub struct Ender<'a> {
    /// The caller's credential label (never a secret).
    pub by: &'a str,
    /// The timeline incidents are placed on (the end's `ended_s`).
    pub timeline: IncidentTimeline,
    /// This server's area prior: the ended incident's area leaves it before the call returns.
    pub areas: &'a IncidentAreas,
    /// Told once the ENDED event is stored (this server's live feed reads it at once; the other
    /// replicas' feeds within their poll).
    pub stored: &'a Notify,
}

/// EndIncident: ends (or dismisses) an open incident by hand, records the closure with it and logs
/// its ENDED event in one transaction; this server's area prior drops it at once, every other
/// server's within its correlator tick, and the correlator lets go of it on its next step.
pub async fn end(
    store: &Store,
    request: &v1::EndIncidentRequest,
    ender: &Ender<'_>,
) -> Result<v1::Incident, Status> {
    let reason = checked_reason(request)?;
    let closure = Closure {
        kind: if request.dismiss {
            ClosureKind::Dismissed
        } else {
            ClosureKind::Ended
        },
        reason,
        by: ender.by.to_string(),
    };
    let now_ms = now_unix_ms();
    let timeline = ender.timeline;
    let outcome = store
        .close_incident(request.id, &closure, now_ms, |body| {
            let mut incident =
                serde_json::from_value::<Incident>(body).map_err(|error| invalid_body(&error))?;
            // On the samples timeline the server's clock is not the vehicles': the end is placed
            // at the latest evidence.
            let at_s = match timeline {
                IncidentTimeline::Wall => now_ms as f64 / 1000.0,
                IncidentTimeline::Samples => incident.last_evidence_s,
            };
            incident.end_by_hand(at_s);
            serde_json::to_value(&incident).map_err(|error| invalid_body(&error))
        })
        .await?;
    let row = match outcome {
        CloseOutcome::Closed(row) => row,
        CloseOutcome::NotFound => return Err(not_found("incident", &request.id.to_string())),
        CloseOutcome::AlreadyEnded(row) => return Err(already_ended(&row)),
    };
    let wire = row_to_proto(&row);
    tracing::warn!(
        incident = row.id,
        closure = closure.kind.as_str(),
        reason = %closure.reason,
        by = %closure.by,
        vehicles = wire.vehicles.len(),
        credentials = ?wire.credentials,
        "area incident ended by hand: its area no longer lowers vehicles' thresholds"
    );
    telemetry::incident_ended();
    ender.stored.notify_one();
    if let Err(error) = refresh_areas(store, ender.areas).await {
        tracing::warn!(%error, "could not refresh the incident areas; the next tick retries");
    }
    Ok(wire)
}

/// The request's reason, trimmed, once the id and the reason are valid (every violation named).
fn checked_reason(request: &v1::EndIncidentRequest) -> Result<String, Status> {
    let mut violations = Vec::new();
    if request.id <= 0 {
        violations.push((
            "id".to_string(),
            format!("must be a positive incident id, got {}", request.id),
        ));
    }
    let reason = request.reason.trim();
    let chars = reason.chars().count();
    let problem = if reason.is_empty() {
        Some("is required: say why the incident ends, for the audit record".to_string())
    } else if chars > MAX_REASON_CHARS {
        Some(format!(
            "must be at most {MAX_REASON_CHARS} characters, got {chars}"
        ))
    } else if reason.chars().any(char::is_control) {
        Some("must be one line of text: no control characters".to_string())
    } else {
        None
    };
    if let Some(problem) = problem {
        violations.push(("reason".to_string(), problem));
    }
    if violations.is_empty() {
        Ok(reason.to_string())
    } else {
        Err(invalid_argument(violations))
    }
}

fn invalid_body(error: &serde_json::Error) -> StoreError {
    StoreError::InvalidValue {
        field: "incidents.body_json",
        reason: error.to_string(),
    }
}

/// FAILED_PRECONDITION for an incident that has already ended: a closure is recorded once.
fn already_ended(row: &IncidentRow) -> Status {
    let how = match row.closure.get() {
        Some(closure) => format!(
            "was {} by hand by {}",
            match closure.kind {
                ClosureKind::Ended => "ended",
                ClosureKind::Dismissed => "dismissed",
            },
            closure.by
        ),
        None => "ended on its own (no vehicle of it alarmed for the quiet time)".to_string(),
    };
    let when = row
        .ended_at_ms
        .map(|ms| format!(" at {}", timestamp_from_ms(ms)))
        .unwrap_or_default();
    failed_precondition(
        "INCIDENT_ALREADY_ENDED",
        format!(
            "incident {} {how}{when}; an ended incident's closure is never rewritten",
            row.id
        ),
    )
}

fn row_to_proto(row: &IncidentRow) -> v1::Incident {
    incident_to_proto(
        row.id,
        &row.body,
        row.opened_at_ms,
        row.ended_at_ms,
        &row.closure,
    )
}

/// A stored incident on the wire. A body this build cannot read (written by a newer server) is
/// sent with its id and times only, and logged.
fn incident_to_proto(
    id: i64,
    body: &serde_json::Value,
    opened_at_ms: i64,
    ended_at_ms: Option<i64>,
    closure: &StoredClosure,
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
    wire.open = wire.open && ended_at_ms.is_none();
    wire.closure = closure.get().map(|closure| v1::IncidentClosure {
        kind: match closure.kind {
            ClosureKind::Ended => v1::IncidentClosureKind::Ended,
            ClosureKind::Dismissed => v1::IncidentClosureKind::Dismissed,
        } as i32,
        reason: closure.reason,
        closed_by: closure.by,
        closed_time: ended_at_ms.map(timestamp_from_ms),
    });
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
