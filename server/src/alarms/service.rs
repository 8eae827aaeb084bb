//! The AlarmService RPCs: ListAlarms reads the store; WatchAlarms reads the event log and follows
//! the live feed.
//!
//! The cursor is the event log position the database assigned when the event was stored (commit
//! order across every replica writing into the database; see `store::alarms`), so a cursor from
//! any replica resumes on any other. A watch replays what the caller missed, then follows live
//! events:
//! 1. it subscribes to the feed (the live receiver and the feed's head are taken together);
//! 2. it sends the stored events after its position (paged from the log), then CAUGHT_UP: with a
//!    cursor, through the latest event in the log when the call started (the feed may be a poll
//!    behind events other replicas stored); without one, from the feed's head;
//! 3. it follows the live receiver, skipping any position it has already passed (de-duplication).
//!
//! A watcher that falls more than the live buffer behind (`Lagged`) goes back to step 1 from its
//! position: the missed events are in the log, so a slow dashboard is slowed down, never given a
//! gap. A watch sends only stored events: while the database is down, watchers see nothing new
//! (the detection stream still carries each alarm at once) and get the events once it is back. If
//! a replay cannot read the log, or the server drains, the stream ends with UNAVAILABLE naming the
//! cursor to resume from. Each call runs in its own task writing into a small bounded channel (as
//! DetectionService streams do).

use std::collections::HashMap;
use std::sync::Arc;
use std::time::Duration;

use spoofwatch_proto::v1;
use spoofwatch_proto::v1::alarm_service_server::AlarmService;
use spoofwatch_proto::wire::convert::timestamp_from_ms;
use spoofwatch_proto::wire::{ModelName, VehicleId};
use tokio::sync::broadcast::error::RecvError;
use tokio::sync::mpsc;
use tokio_stream::wrappers::ReceiverStream;
use tokio_util::sync::CancellationToken;
use tonic::{Code, Request, Response, Status};
use tonic_types::{ErrorDetails, StatusExt};

use super::feed::{AlarmFeed, FeedSubscription};
use crate::edge::{optional_model_name, optional_vehicle_id, page_request};
use crate::idle::StreamIdle;
use crate::status::{invalid_field, shutting_down};
use crate::store::{
    AlarmEventKind, AlarmEventRow, AlarmFilter, AlarmState, LoggedAlarmEvent, Store,
};

/// Events buffered per watch before its task waits for the client.
const OUTBOUND_BUFFER: usize = 16;
/// Stored events read per query of a replay.
const REPLAY_PAGE: u32 = 500;

type WatchReply = Result<v1::AlarmEvent, Status>;

/// The AlarmService implementation.
#[derive(Debug, Clone)]
pub struct AlarmApi {
    pub store: Store,
    pub feed: Arc<AlarmFeed>,
    /// Cancelled when the server starts draining.
    pub shutdown: CancellationToken,
    /// How long a watcher may leave a pending event unread.
    pub stream_idle: StreamIdle,
}

/// A stored or emitted alarm on the wire.
fn alarm_to_proto(alarm: &AlarmEventRow) -> v1::Alarm {
    v1::Alarm {
        id: alarm.id,
        vehicle_id: alarm.vehicle_id.clone(),
        model: ModelName::from_id(&alarm.model_id).to_string(),
        onset_timestamp_s: alarm.onset_timestamp_s,
        end_timestamp_s: alarm.end_timestamp_s,
        onset_time: Some(timestamp_from_ms(alarm.onset_at_ms)),
        end_time: alarm.ended_at_ms.map(timestamp_from_ms),
        peak_probability: alarm.peak_probability,
        samples: u64::try_from(alarm.samples).unwrap_or(0),
        open: alarm.is_open(),
        why: super::why::to_proto(&alarm.why),
    }
}

fn event_to_proto(logged: &LoggedAlarmEvent) -> v1::AlarmEvent {
    let kind = match logged.event.kind {
        AlarmEventKind::Onset => v1::AlarmEventKind::Onset,
        AlarmEventKind::End => v1::AlarmEventKind::End,
    };
    v1::AlarmEvent {
        cursor: logged.position,
        kind: kind as i32,
        alarm: Some(alarm_to_proto(&logged.event.alarm)),
    }
}

fn caught_up(cursor: i64) -> v1::AlarmEvent {
    v1::AlarmEvent {
        cursor,
        kind: v1::AlarmEventKind::CaughtUp as i32,
        alarm: None,
    }
}

/// A `vehicle_id` filter: empty = every vehicle.
fn vehicle_filter(vehicle_id: &str) -> Result<Option<String>, Status> {
    Ok(optional_vehicle_id("vehicle_id", vehicle_id)?.map(VehicleId::into_string))
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
    })
}

/// UNAVAILABLE ending a watch, telling the client where to resume (in the message for people, in
/// ErrorInfo metadata `resume_after_cursor` for programs) and when (RetryInfo).
fn resume_status(reason: &str, message: &str, cursor: i64, retry_after: Duration) -> Status {
    let mut details = ErrorDetails::new();
    details.set_retry_info(Some(retry_after)).set_error_info(
        reason,
        "spoofwatch",
        HashMap::from([("resume_after_cursor".to_string(), cursor.to_string())]),
    );
    Status::with_error_details(
        Code::Unavailable,
        format!("{message}; resume with after_cursor = {cursor}"),
        details,
    )
}

fn draining(cursor: i64) -> Status {
    resume_status(
        "SHUTTING_DOWN",
        "server is shutting down",
        cursor,
        Duration::from_secs(1),
    )
}

/// One WatchAlarms call.
struct Watch {
    store: Store,
    feed: Arc<AlarmFeed>,
    shutdown: CancellationToken,
    vehicle_id: Option<String>,
    /// End the call after CAUGHT_UP.
    stop_when_caught_up: bool,
    tx: mpsc::Sender<WatchReply>,
    /// A watcher that reads no event for this long is let go (it resumes with its cursor).
    idle: StreamIdle,
    /// Every event up to this log position has been sent or filtered out.
    position: i64,
}

/// Why a watch stops early.
enum Stop {
    /// The client went away.
    Gone,
    /// The call ends with this status.
    Fail(Status),
}

impl Watch {
    fn wanted(&self, logged: &LoggedAlarmEvent) -> bool {
        self.vehicle_id
            .as_deref()
            .is_none_or(|v| v == logged.event.alarm.vehicle_id)
    }

    /// Sends `logged` if it is past the position and wanted; advances the position.
    async fn offer(&mut self, logged: &LoggedAlarmEvent) -> Result<(), Stop> {
        if logged.position <= self.position {
            return Ok(());
        }
        self.position = logged.position;
        if self.wanted(logged) {
            self.send(event_to_proto(logged)).await?;
        }
        Ok(())
    }

    async fn send(&self, message: v1::AlarmEvent) -> Result<(), Stop> {
        if self.idle.send(&self.tx, Ok(message)).await {
            Ok(())
        } else {
            Err(Stop::Gone)
        }
    }

    /// Sends the stored events after the position, up to `through`.
    async fn replay_stored(&mut self, through: i64) -> Result<(), Stop> {
        while self.position < through {
            if self.shutdown.is_cancelled() {
                return Err(Stop::Fail(draining(self.position)));
            }
            let page = self
                .store
                .alarm_events_after(
                    self.position,
                    through,
                    self.vehicle_id.as_deref(),
                    REPLAY_PAGE,
                )
                .await
                .map_err(|error| {
                    let status = Status::from(error);
                    let message = format!(
                        "{}; resume with after_cursor = {}",
                        status.message(),
                        self.position
                    );
                    Stop::Fail(Status::with_details(
                        status.code(),
                        message,
                        status.details().to_vec().into(),
                    ))
                })?;
            let complete = page.len() < REPLAY_PAGE as usize;
            for logged in &page {
                self.offer(logged).await?;
            }
            if complete {
                self.position = through;
            }
        }
        Ok(())
    }

    /// Replays through `replay_through` (at least the subscription's head), sends CAUGHT_UP, then
    /// follows live events until the client goes away or the call must end.
    async fn run(
        mut self,
        mut subscription: FeedSubscription,
        replay_through: i64,
    ) -> Result<(), Stop> {
        self.replay_stored(replay_through).await?;
        self.send(caught_up(self.position)).await?;
        if self.stop_when_caught_up {
            return Ok(());
        }
        loop {
            // Live events up to the position are skipped by `offer`.
            self.replay_stored(subscription.head).await?;
            loop {
                let received = tokio::select! {
                    biased;
                    _ = self.shutdown.cancelled() => return Err(Stop::Fail(draining(self.position))),
                    _ = self.tx.closed() => return Err(Stop::Gone),
                    received = subscription.live.recv() => received,
                };
                match received {
                    Ok(logged) => self.offer(&logged).await?,
                    Err(RecvError::Lagged(missed)) => {
                        tracing::debug!(
                            missed,
                            position = self.position,
                            "an alarm watcher fell behind; replaying what it missed"
                        );
                        break;
                    }
                    // The feed lives as long as the server: it is going away.
                    Err(RecvError::Closed) => return Err(Stop::Fail(draining(self.position))),
                }
            }
            subscription = self.feed.subscribe();
        }
    }
}

#[tonic::async_trait]
impl AlarmService for AlarmApi {
    type WatchAlarmsStream = ReceiverStream<WatchReply>;

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
        if self.shutdown.is_cancelled() {
            return Err(shutting_down());
        }
        let r = request.into_inner();
        let vehicle_id = vehicle_filter(&r.vehicle_id)?;
        if let Some(after) = r.after_cursor
            && after < 0
        {
            return Err(invalid_field("after_cursor", "must not be negative"));
        }
        let subscription = self.feed.subscribe();
        let (position, replay_through) = match r.after_cursor {
            // A replay runs through the log's latest event, not the feed's head: the feed may be a
            // poll behind the log (an event another replica just stored), and a cursor seen on
            // one replica must resume on another with every stored event after it. Only the log
            // itself tells that a cursor is from the future.
            Some(after) => {
                let latest = self.store.latest_alarm_position().await?;
                if after > latest {
                    return Err(invalid_field(
                        "after_cursor",
                        format!(
                            "{after} is beyond the latest event ({latest}); resume with a cursor \
                             WatchAlarms sent, or without one (ListAlarms lists what is stored)"
                        ),
                    ));
                }
                (after, latest.max(subscription.head))
            }
            None => (subscription.head, subscription.head),
        };
        let (tx, rx) = mpsc::channel(OUTBOUND_BUFFER);
        let watch = Watch {
            store: self.store.clone(),
            feed: Arc::clone(&self.feed),
            shutdown: self.shutdown.clone(),
            vehicle_id,
            stop_when_caught_up: r.stop_when_caught_up,
            tx: tx.clone(),
            idle: self.stream_idle,
            position,
        };
        let idle = self.stream_idle;
        tokio::spawn(async move {
            if let Err(Stop::Fail(status)) = watch.run(subscription, replay_through).await {
                idle.send(&tx, Err(status)).await;
            }
        });
        Ok(Response::new(ReceiverStream::new(rx)))
    }
}

#[cfg(test)]
mod tests {
    use std::time::Duration;

    use tokio_stream::StreamExt;

    use super::*;
    use crate::outbox::SessionOutbox;

    async fn watch(api: &AlarmApi, after_cursor: Option<i64>) -> Vec<(i32, i64)> {
        let request = v1::WatchAlarmsRequest {
            after_cursor,
            stop_when_caught_up: true,
            ..Default::default()
        };
        let stream = api
            .watch_alarms(Request::new(request))
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
        let alarm = other_replica.onset("car-1", "m", 1.0, 1, 0.9, None);
        other_replica.end(alarm, 3.0, 0.95, 3);
        other_replica
            .run(store.clone(), stop, Duration::from_secs(1))
            .await;
        let api = AlarmApi {
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
            .watch_alarms(Request::new(v1::WatchAlarmsRequest {
                after_cursor: Some(3),
                ..Default::default()
            }))
            .await
            .expect_err("a cursor from the future");
        assert_eq!(beyond.code(), Code::InvalidArgument);
    }
}
