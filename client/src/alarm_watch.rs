//! Resumable `WatchAlarms` and `WatchIncidents` feeds: the client side of the fleet's alarm and
//! incident events.
//!
//! A [`ResumableWatch`] remembers the cursor of the last event it returned (a CAUGHT_UP event
//! included) and, when the call ends with UNAVAILABLE (a server draining, restarting or briefly
//! unreachable), opens a new call after that cursor, so its caller sees every event exactly once
//! across reconnects. [`AlarmWatch`] and [`IncidentWatch`] are its two calls. It must not know how
//! events are printed: `spoofwatch alarms watch` and `spoofwatch incidents watch` do that.

use std::future::Future;
use std::time::{Duration, Instant};

use spoofwatch_proto::v1;
use tonic::{Code, Streaming};
use tonic_types::StatusExt;

use crate::connection::Connection;
use crate::error::{ClientError, rpc};

/// First wait before reopening a call; doubled per failed attempt up to [`MAX_BACKOFF`].
const FIRST_BACKOFF: Duration = Duration::from_millis(100);
/// Longest wait between attempts (a server's RetryInfo may ask for longer: it is honoured).
const MAX_BACKOFF: Duration = Duration::from_secs(5);

/// A watch call that can be reopened after a cursor.
pub trait WatchCall: Send + Sync {
    /// One event (or CAUGHT_UP) of the call.
    type Event: Send;
    /// What the call does, for errors ("watching alarms").
    const WHAT: &'static str;

    fn open(
        &self,
        connection: &Connection,
        after_cursor: Option<i64>,
    ) -> impl Future<Output = Result<Streaming<Self::Event>, tonic::Status>> + Send;

    fn cursor(event: &Self::Event) -> i64;
}

/// WatchAlarms, for one vehicle or (empty) the whole fleet, of at least a severity.
#[derive(Clone, Debug, Default)]
pub struct AlarmCall {
    pub vehicle_id: String,
    pub min_severity: v1::AlarmSeverity,
}

impl WatchCall for AlarmCall {
    type Event = v1::AlarmEvent;
    const WHAT: &'static str = "watching alarms";

    async fn open(
        &self,
        connection: &Connection,
        after_cursor: Option<i64>,
    ) -> Result<Streaming<v1::AlarmEvent>, tonic::Status> {
        let request = v1::WatchAlarmsRequest {
            vehicle_id: self.vehicle_id.clone(),
            after_cursor,
            stop_when_caught_up: false,
            severity: self.min_severity as i32,
        };
        Ok(connection
            .alarms()
            .watch_alarms(request)
            .await?
            .into_inner())
    }

    fn cursor(event: &v1::AlarmEvent) -> i64 {
        event.cursor
    }
}

/// WatchIncidents.
#[derive(Clone, Copy, Debug, Default)]
pub struct IncidentCall;

impl WatchCall for IncidentCall {
    type Event = v1::IncidentEvent;
    const WHAT: &'static str = "watching incidents";

    async fn open(
        &self,
        connection: &Connection,
        after_cursor: Option<i64>,
    ) -> Result<Streaming<v1::IncidentEvent>, tonic::Status> {
        let request = v1::WatchIncidentsRequest {
            after_cursor,
            stop_when_caught_up: false,
        };
        Ok(connection
            .alarms()
            .watch_incidents(request)
            .await?
            .into_inner())
    }

    fn cursor(event: &v1::IncidentEvent) -> i64 {
        event.cursor
    }
}

/// What to watch.
#[derive(Clone, Debug, Default)]
pub struct WatchOptions {
    /// One vehicle's alarm events only (empty: the whole fleet; incidents are not filtered).
    pub vehicle_id: String,
    /// Alarm events at least this severe only (UNSPECIFIED or WARNING: every event; CRITICAL:
    /// critical onsets, escalations and ends of critical alarms; incidents are not filtered).
    pub min_severity: v1::AlarmSeverity,
    /// Start after this cursor (`Some(0)`: every stored event); `None`: only events from now on.
    pub after_cursor: Option<i64>,
    /// Keep trying to reconnect for this long after the call ended with UNAVAILABLE (zero: never
    /// reconnect).
    pub reconnect_for: Duration,
}

/// Called before each reconnection attempt with the status that ended the call and the cursor
/// the watch will resume after.
pub type ReconnectNotice = Box<dyn FnMut(&tonic::Status, Option<i64>) + Send + Sync>;

/// One watch that survives reconnects.
pub struct ResumableWatch<C: WatchCall> {
    connection: Connection,
    call: C,
    reconnect_for: Duration,
    cursor: Option<i64>,
    stream: Option<Streaming<C::Event>>,
    reconnects: u64,
    notice: Option<ReconnectNotice>,
}

/// A resumable WatchAlarms feed.
pub type AlarmWatch = ResumableWatch<AlarmCall>;
/// A resumable WatchIncidents feed.
pub type IncidentWatch = ResumableWatch<IncidentCall>;

impl AlarmWatch {
    /// An alarm watch over `connection`; the call is opened by the first [`ResumableWatch::next`].
    pub fn new(connection: Connection, options: WatchOptions) -> Self {
        let call = AlarmCall {
            vehicle_id: options.vehicle_id.clone(),
            min_severity: options.min_severity,
        };
        ResumableWatch::of(connection, call, &options)
    }
}

impl IncidentWatch {
    /// An incident watch over `connection` (`options.vehicle_id` does not apply).
    pub fn incidents(connection: Connection, options: &WatchOptions) -> Self {
        ResumableWatch::of(connection, IncidentCall, options)
    }
}

impl<C: WatchCall> ResumableWatch<C> {
    fn of(connection: Connection, call: C, options: &WatchOptions) -> Self {
        Self {
            connection,
            call,
            reconnect_for: options.reconnect_for,
            cursor: options.after_cursor,
            stream: None,
            reconnects: 0,
            notice: None,
        }
    }

    /// Calls `notice` before each reconnection attempt.
    pub fn with_reconnect_notice(mut self, notice: ReconnectNotice) -> Self {
        self.notice = Some(notice);
        self
    }

    /// The cursor a new watch would resume after: the last event returned, else the starting one.
    pub fn cursor(&self) -> Option<i64> {
        self.cursor
    }

    /// Calls opened again after the first.
    pub fn reconnects(&self) -> u64 {
        self.reconnects
    }

    /// Ends the current call (the next [`ResumableWatch::next`] opens a new one after the cursor), as a
    /// dropped connection would.
    pub fn disconnect(&mut self) {
        self.stream = None;
    }

    /// The next event. A call that ends with UNAVAILABLE (or ends without a status, which a
    /// server never does on its own) is reopened after the cursor, waiting between attempts, for
    /// at most `reconnect_for` without an event; any other failure is returned.
    pub async fn next(&mut self) -> Result<C::Event, ClientError> {
        let mut failing_since: Option<Instant> = None;
        let mut backoff = FIRST_BACKOFF;
        loop {
            let ended = match self.stream.as_mut() {
                None => match self.call.open(&self.connection, self.cursor).await {
                    Ok(stream) => {
                        self.stream = Some(stream);
                        continue;
                    }
                    Err(status) => status,
                },
                Some(stream) => match stream.message().await {
                    Ok(Some(event)) => {
                        self.cursor = Some(C::cursor(&event));
                        return Ok(event);
                    }
                    Ok(None) => tonic::Status::unavailable("the server ended the watch"),
                    Err(status) => status,
                },
            };
            self.stream = None;
            let since = *failing_since.get_or_insert_with(Instant::now);
            if ended.code() != Code::Unavailable || since.elapsed() >= self.reconnect_for {
                return Err(rpc(C::WHAT)(ended));
            }
            if let Some(notice) = self.notice.as_mut() {
                notice(&ended, self.cursor);
            }
            let asked = ended
                .get_details_retry_info()
                .and_then(|retry| retry.retry_delay)
                .unwrap_or_default();
            tokio::time::sleep(backoff.max(asked)).await;
            backoff = (backoff * 2).min(MAX_BACKOFF);
            self.reconnects += 1;
        }
    }
}
