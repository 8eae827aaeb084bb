//! The AlarmService RPCs: ListAlarms reads the store; WatchAlarms follows the alarm event log
//! (`crate::event_log::watch`: replay from a cursor, CAUGHT_UP, then live events, with one cursor
//! semantics on every replica), for as long as the identities in force admit its caller.
//! ListIncidents, GetIncident, WatchIncidents and EndIncident are served by
//! `crate::incidents::service` on the same service.

use std::sync::Arc;

use spoofwatch_core::severity::Severity;
use spoofwatch_proto::v1;
use spoofwatch_proto::v1::alarm_service_server::AlarmService;
use spoofwatch_proto::wire::VehicleId;
use spoofwatch_proto::wire::convert::severity_from_proto;
use tokio::sync::Notify;
use tokio_util::sync::CancellationToken;
use tonic::{Request, Response, Status};

use super::feed::{AlarmFeed, AlarmLog, AlarmWatchFilter};
use super::wire::alarm_to_proto;
use crate::access::Caller;
use crate::edge::{optional_model_name, optional_vehicle_id, page_request};
use crate::event_log::watch::{self, WatchContext, WatchRequest, WatchStream};
use crate::idle::StreamIdle;
use crate::incidents::areas::IncidentAreas;
use crate::incidents::service::{self as incidents, Ender, IncidentFeed, IncidentLog};
use crate::incidents::settings::IncidentTimeline;
use crate::status::invalid_field;
use crate::store::{AlarmFilter, AlarmState, Store};

/// The AlarmService implementation.
#[derive(Debug, Clone)]
pub struct AlarmApi {
    pub store: Store,
    pub feed: Arc<AlarmFeed>,
    pub incident_feed: Arc<IncidentFeed>,
    /// Told when EndIncident stored an ENDED event (as the correlator tells it).
    pub incidents_stored: Arc<Notify>,
    /// This server's area prior (EndIncident drops the ended incident's area at once).
    pub incident_areas: Arc<IncidentAreas>,
    /// The timeline incidents are placed on.
    pub incident_timeline: IncidentTimeline,
    /// Cancelled when the server starts draining.
    pub shutdown: CancellationToken,
    /// How long a watcher may leave a pending event unread.
    pub stream_idle: StreamIdle,
}

/// A `vehicle_id` filter: empty = every vehicle.
fn vehicle_filter(vehicle_id: &str) -> Result<Option<String>, Status> {
    Ok(optional_vehicle_id("vehicle_id", vehicle_id)?.map(VehicleId::into_string))
}

/// A `severity` filter: the least severity wanted (UNSPECIFIED: warning, every alarm).
fn min_severity(number: i32) -> Result<Severity, Status> {
    severity_from_proto(number)
        .map(Option::unwrap_or_default)
        .map_err(|number| {
            invalid_field(
                "severity",
                format!(
                    "unknown severity {number}: use ALARM_SEVERITY_WARNING (1) or \
                     ALARM_SEVERITY_CRITICAL (2), or leave it unset for every alarm"
                ),
            )
        })
}

/// The WatchAlarms filter: `None` when it asks for every event of the fleet.
fn watch_filter(r: &v1::WatchAlarmsRequest) -> Result<Option<AlarmWatchFilter>, Status> {
    let filter = AlarmWatchFilter {
        vehicle_id: vehicle_filter(&r.vehicle_id)?,
        min_severity: min_severity(r.severity)?,
    };
    Ok((filter != AlarmWatchFilter::default()).then_some(filter))
}

/// An optional timestamp field as unix milliseconds (sub-millisecond parts are truncated).
fn timestamp_ms(
    field: &str,
    timestamp: Option<&prost_types::Timestamp>,
) -> Result<Option<i64>, Status> {
    let Some(t) = timestamp else {
        return Ok(None);
    };
    if !(0..1_000_000_000).contains(&t.nanos) {
        return Err(invalid_field(
            format!("{field}.nanos"),
            format!("must be in [0, 999999999], got {}", t.nanos),
        ));
    }
    t.seconds
        .checked_mul(1000)
        .and_then(|ms| ms.checked_add(i64::from(t.nanos / 1_000_000)))
        .map(Some)
        .ok_or_else(|| {
            invalid_field(
                format!("{field}.seconds"),
                format!("{} is out of range", t.seconds),
            )
        })
}

/// The ListAlarms filters, validated.
fn list_filter(r: &v1::ListAlarmsRequest) -> Result<AlarmFilter, Status> {
    let onset_from_ms = timestamp_ms("onset_after", r.onset_after.as_ref())?;
    let onset_before_ms = timestamp_ms("onset_before", r.onset_before.as_ref())?;
    if let (Some(from), Some(before)) = (onset_from_ms, onset_before_ms)
        && before <= from
    {
        return Err(invalid_field(
            "onset_before",
            "must be later than onset_after",
        ));
    }
    let state = match v1::AlarmStateFilter::try_from(r.state) {
        Ok(v1::AlarmStateFilter::Unspecified) => AlarmState::Any,
        Ok(v1::AlarmStateFilter::Open) => AlarmState::Open,
        Ok(v1::AlarmStateFilter::Closed) => AlarmState::Closed,
        Err(_) => {
            return Err(invalid_field("state", format!("unknown state {}", r.state)));
        }
    };
    Ok(AlarmFilter {
        vehicle_id: vehicle_filter(&r.vehicle_id)?,
        model_id: optional_model_name("model", &r.model)?.map(|m| m.id().to_string()),
        onset_from_ms,
        onset_before_ms,
        state,
        min_severity: min_severity(r.severity)?,
    })
}

#[tonic::async_trait]
impl AlarmService for AlarmApi {
    type WatchAlarmsStream = WatchStream<AlarmLog>;
    type WatchIncidentsStream = WatchStream<IncidentLog>;

    async fn list_alarms(
        &self,
        request: Request<v1::ListAlarmsRequest>,
    ) -> Result<Response<v1::ListAlarmsResponse>, Status> {
        let r = request.into_inner();
        let filter = list_filter(&r)?;
        let page = self
            .store
            .list_alarms(&filter, &page_request(r.page_size, &r.page_token)?)
            .await?;
        Ok(Response::new(v1::ListAlarmsResponse {
            alarms: page.items.iter().map(alarm_to_proto).collect(),
            next_page_token: page.next_page_token.unwrap_or_default(),
        }))
    }

    async fn watch_alarms(
        &self,
        request: Request<v1::WatchAlarmsRequest>,
    ) -> Result<Response<Self::WatchAlarmsStream>, Status> {
        let caller = Caller::of(&request)?;
        let r = request.into_inner();
        let stream = watch::start(
            WatchContext {
                store: &self.store,
                feed: &self.feed,
                shutdown: &self.shutdown,
                idle: self.stream_idle,
                caller,
            },
            WatchRequest {
                filter: watch_filter(&r)?,
                after_cursor: r.after_cursor,
                stop_when_caught_up: r.stop_when_caught_up,
            },
        )
        .await?;
        Ok(Response::new(stream))
    }

    async fn list_incidents(
        &self,
        request: Request<v1::ListIncidentsRequest>,
    ) -> Result<Response<v1::ListIncidentsResponse>, Status> {
        Ok(Response::new(
            incidents::list(&self.store, request.get_ref()).await?,
        ))
    }

    async fn get_incident(
        &self,
        request: Request<v1::GetIncidentRequest>,
    ) -> Result<Response<v1::Incident>, Status> {
        Ok(Response::new(
            incidents::get(&self.store, request.get_ref()).await?,
        ))
    }

    async fn watch_incidents(
        &self,
        request: Request<v1::WatchIncidentsRequest>,
    ) -> Result<Response<Self::WatchIncidentsStream>, Status> {
        let caller = Caller::of(&request)?;
        let r = request.into_inner();
        let stream = watch::start(
            WatchContext {
                store: &self.store,
                feed: &self.incident_feed,
                shutdown: &self.shutdown,
                idle: self.stream_idle,
                caller,
            },
            WatchRequest {
                filter: None,
                after_cursor: r.after_cursor,
                stop_when_caught_up: r.stop_when_caught_up,
            },
        )
        .await?;
        Ok(Response::new(stream))
    }

    async fn end_incident(
        &self,
        request: Request<v1::EndIncidentRequest>,
    ) -> Result<Response<v1::Incident>, Status> {
        let caller = Caller::of(&request)?;
        let ender = Ender {
            by: &caller.credential.label,
            timeline: self.incident_timeline,
            areas: &self.incident_areas,
            stored: &self.incidents_stored,
        };
        Ok(Response::new(
            incidents::end(&self.store, request.get_ref(), &ender).await?,
        ))
    }
}

#[cfg(test)]
mod tests {
    use std::time::Duration;

    use tokio_stream::StreamExt;

    use tonic::Code;

    use super::*;
    use crate::access::{Access, Sources};
    use crate::alarms::event::Onset;
    use crate::outbox::SessionOutbox;

    /// A WatchAlarms request as the guard of a server without identities passes it on.
    fn watch_request(message: v1::WatchAlarmsRequest) -> Request<v1::WatchAlarmsRequest> {
        let access = Access::load(Sources::default()).expect("no identity files");
        let caller = access
            .admit("/spoofwatch.v1.AlarmService/WatchAlarms", None, None)
            .expect("every caller is an admin");
        let mut request = Request::new(message);
        request.extensions_mut().insert(caller);
        request
    }

    async fn watch(api: &AlarmApi, after_cursor: Option<i64>) -> Vec<(i32, i64)> {
        let request = v1::WatchAlarmsRequest {
            after_cursor,
            stop_when_caught_up: true,
            ..Default::default()
        };
        let stream = api
            .watch_alarms(watch_request(request))
            .await
            .expect("WatchAlarms")
            .into_inner();
        stream
            .map(|reply| reply.expect("an event"))
            .map(|event| (event.kind, event.cursor))
            .collect()
            .await
    }

    /// The feed is a poll behind the log (the events were stored by another replica and not read
    /// yet): a watch with a cursor still replays every stored event after it; one without a
    /// cursor starts at the feed's head and gets the rest live.
    #[tokio::test]
    async fn a_cursor_replays_through_the_log_even_when_the_feed_is_behind() {
        let dir = tempfile::tempdir().expect("temp dir");
        let store = Store::open(&dir.path().join("w.db").to_string_lossy())
            .await
            .expect("open");
        let feed = Arc::new(AlarmFeed::new(&store).await.expect("feed"));
        let other_replica = SessionOutbox::new(&store, 10).await.expect("outbox");
        let stop = CancellationToken::new();
        stop.cancel();
        let alarm = other_replica.onset(&Onset::warning("car-1", "m", 1.0, 1, 0.9));
        other_replica.end(alarm, 3.0, 0.95, 3, Severity::Warning);
        other_replica
            .run(store.clone(), stop, Duration::from_secs(1))
            .await;
        let api = AlarmApi {
            incident_feed: Arc::new(IncidentFeed::new(&store).await.expect("feed")),
            incidents_stored: Arc::new(Notify::new()),
            incident_areas: Arc::new(IncidentAreas::new(true)),
            incident_timeline: IncidentTimeline::Wall,
            store,
            feed,
            shutdown: CancellationToken::new(),
            stream_idle: StreamIdle(Duration::from_secs(60)),
        };

        let (onset, end, caught_up) = (
            v1::AlarmEventKind::Onset as i32,
            v1::AlarmEventKind::End as i32,
            v1::AlarmEventKind::CaughtUp as i32,
        );
        assert_eq!(
            watch(&api, Some(0)).await,
            [(onset, 1), (end, 2), (caught_up, 2)]
        );
        assert_eq!(watch(&api, Some(1)).await, [(end, 2), (caught_up, 2)]);
        assert_eq!(watch(&api, None).await, [(caught_up, 0)]);
        let beyond = api
            .watch_alarms(watch_request(v1::WatchAlarmsRequest {
                after_cursor: Some(3),
                ..Default::default()
            }))
            .await
            .expect_err("a cursor from the future");
        assert_eq!(beyond.code(), Code::InvalidArgument);
    }
}
