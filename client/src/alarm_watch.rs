//! A resumable `WatchAlarms` feed: the client side of the fleet's alarm events.
//!
//! [`AlarmWatch`] remembers the cursor of the last event it returned (a CAUGHT_UP event included)
//! and, when the call ends with UNAVAILABLE (a server draining, restarting or briefly unreachable),
//! opens a new call after that cursor, so its caller sees every event exactly once across
//! reconnects. It must not know how events are printed: `spoofwatch alarms watch` does that.

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

/// What to watch.
#[derive(Clone, Debug, Default)]
pub struct WatchOptions {
    /// One vehicle's events only (empty: the whole fleet).
    pub vehicle_id: String,
    /// Start after this cursor (`Some(0)`: every stored event); `None`: only events from now on.
    pub after_cursor: Option<i64>,
    /// Keep trying to reconnect for this long after the call ended with UNAVAILABLE (zero: never
    /// reconnect).
    pub reconnect_for: Duration,
}

/// Called before each reconnection attempt with the status that ended the call and the cursor
/// the watch will resume after.
pub type ReconnectNotice = Box<dyn FnMut(&tonic::Status, Option<i64>) + Send + Sync>;

/// One `WatchAlarms` feed that survives reconnects.
pub struct AlarmWatch {
    connection: Connection,
    options: WatchOptions,
    cursor: Option<i64>,
    stream: Option<Streaming<v1::AlarmEvent>>,
    reconnects: u64,
    notice: Option<ReconnectNotice>,
}

impl AlarmWatch {
    /// A watch over `connection`; the call is opened by the first [`AlarmWatch::next`].
    pub fn new(connection: Connection, options: WatchOptions) -> Self {
        Self {
            connection,
            cursor: options.after_cursor,
            options,
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

    /// Ends the current call (the next [`AlarmWatch::next`] opens a new one after the cursor), as a
    /// dropped connection would.
    pub fn disconnect(&mut self) {
        self.stream = None;
    }

    async fn open(&self) -> Result<Streaming<v1::AlarmEvent>, tonic::Status> {
        let request = v1::WatchAlarmsRequest {
            vehicle_id: self.options.vehicle_id.clone(),
            after_cursor: self.cursor,
            stop_when_caught_up: false,
        };
        Ok(self
            .connection
            .alarms()
            .watch_alarms(request)
            .await?
            .into_inner())
    }

    /// The next event. A call that ends with UNAVAILABLE (or ends without a status, which a
    /// server never does on its own) is reopened after the cursor, waiting between attempts, for
    /// at most `reconnect_for` without an event; any other failure is returned.
    pub async fn next(&mut self) -> Result<v1::AlarmEvent, ClientError> {
        let mut failing_since: Option<Instant> = None;
        let mut backoff = FIRST_BACKOFF;
        loop {
            let ended = match self.stream.as_mut() {
                None => match self.open().await {
                    Ok(stream) => {
                        self.stream = Some(stream);
                        continue;
                    }
                    Err(status) => status,
                },
                Some(stream) => match stream.message().await {
                    Ok(Some(event)) => {
                        self.cursor = Some(event.cursor);
                        return Ok(event);
                    }
                    Ok(None) => tonic::Status::unavailable("the server ended the watch"),
                    Err(status) => status,
                },
            };
            self.stream = None;
            let since = *failing_since.get_or_insert_with(Instant::now);
            if ended.code() != Code::Unavailable || since.elapsed() >= self.options.reconnect_for {
                return Err(rpc("watching alarms")(ended));
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
