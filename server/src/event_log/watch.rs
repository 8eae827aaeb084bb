//! A resumable watch of an event log (WatchAlarms, WatchIncidents).
//!
//! The cursor is the event log position the database assigned when the event was stored (commit
//! order across every replica writing into the database), so a cursor from any replica resumes on
//! any other. A watch replays what the caller missed, then follows live events:
//! 1. it subscribes to the feed (the live receiver and the feed's head are taken together);
//! 2. it sends the stored events after its position (paged from the log), then CAUGHT_UP: with a
//!    cursor, through the latest event in the log when the call started (the feed may be a poll
//!    behind events other replicas stored); without one, from the feed's head;
//! 3. it follows the live receiver, skipping any position it has already passed (de-duplication).
//!
//! A watcher that falls more than the live buffer behind (`Lagged`) goes back to step 1 from its
//! position: the missed events are in the log, so a slow dashboard is slowed down, never given a
//! gap. A watch sends only stored events. If a replay cannot read the log, or the server drains,
//! the stream ends with UNAVAILABLE naming the cursor to resume from. Each call runs in its own
//! task writing into a small bounded channel (as DetectionService streams do), and a watcher that
//! leaves an event unread for the stream idle limit is let go.
//!
//! A watch ends as soon as a change of the identity files no longer admits its caller
//! ([`Caller::until_revoked`]: UNAUTHENTICATED, or PERMISSION_DENIED for a caller that may no
//! longer read), and nothing is queued for it once that change is in force: every event is sent
//! only after the caller's standing is checked ([`Caller::check_standing`]).

use std::collections::HashMap;
use std::sync::Arc;
use std::time::Duration;

use tokio::sync::broadcast::error::RecvError;
use tokio::sync::mpsc;
use tokio_stream::wrappers::ReceiverStream;
use tokio_util::sync::CancellationToken;
use tonic::{Code, Status};
use tonic_types::{ErrorDetails, StatusExt};

use super::EventLog;
use super::feed::{Feed, FeedSubscription};
use crate::access::Caller;
use crate::idle::StreamIdle;
use crate::status::{invalid_field, shutting_down};
use crate::store::Store;

/// Events buffered per watch before its task waits for the client.
const OUTBOUND_BUFFER: usize = 16;
/// Stored events read per query of a replay.
const REPLAY_PAGE: u32 = 500;

/// A watch's reply stream.
pub type WatchStream<L> = ReceiverStream<Result<<L as EventLog>::Message, Status>>;

/// What a watch needs of its server.
pub struct WatchContext<'a, L: EventLog> {
    pub store: &'a Store,
    pub feed: &'a Arc<Feed<L>>,
    /// Cancelled when the server starts draining.
    pub shutdown: &'a CancellationToken,
    /// How long a watcher may leave a pending event unread.
    pub idle: StreamIdle,
    /// Who watches: the watch ends when the identities in force no longer admit it.
    pub caller: Caller,
}

/// What the caller asked for.
#[derive(Debug)]
pub struct WatchRequest<F> {
    pub filter: Option<F>,
    /// Replay every event after this position first; `None`: only events from now on.
    pub after_cursor: Option<i64>,
    /// End the call (OK) right after CAUGHT_UP.
    pub stop_when_caught_up: bool,
}

/// Starts a watch: checks the cursor, subscribes, and runs the watch in its own task.
pub async fn start<L: EventLog>(
    context: WatchContext<'_, L>,
    request: WatchRequest<L::Filter>,
) -> Result<WatchStream<L>, Status> {
    if context.shutdown.is_cancelled() {
        return Err(shutting_down());
    }
    if let Some(after) = request.after_cursor
        && after < 0
    {
        return Err(invalid_field("after_cursor", "must not be negative"));
    }
    let subscription = context.feed.subscribe();
    let (position, replay_through) = match request.after_cursor {
        // A replay runs through the log's latest event, not the feed's head: the feed may be a
        // poll behind the log (an event another replica just stored), and a cursor seen on one
        // replica must resume on another with every stored event after it. Only the log itself
        // tells that a cursor is from the future.
        Some(after) => {
            let latest = L::latest(context.store).await?;
            if after > latest {
                return Err(invalid_field(
                    "after_cursor",
                    format!(
                        "{after} is beyond the latest event ({latest}); resume with a cursor \
                         the watch sent, or without one ({} lists what is stored)",
                        L::LISTING_RPC
                    ),
                ));
            }
            (after, latest.max(subscription.head))
        }
        None => (subscription.head, subscription.head),
    };
    let (tx, rx) = mpsc::channel(OUTBOUND_BUFFER);
    let watch = Watch::<L> {
        store: context.store.clone(),
        feed: Arc::clone(context.feed),
        shutdown: context.shutdown.clone(),
        filter: request.filter,
        stop_when_caught_up: request.stop_when_caught_up,
        tx: tx.clone(),
        idle: context.idle,
        caller: context.caller,
        position,
    };
    let idle = context.idle;
    tokio::spawn(async move {
        if let Err(Stop::Fail(status)) = watch.run(subscription, replay_through).await {
            idle.send(&tx, Err(status)).await;
        }
    });
    Ok(ReceiverStream::new(rx))
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

/// One watch call.
struct Watch<L: EventLog> {
    store: Store,
    feed: Arc<Feed<L>>,
    shutdown: CancellationToken,
    filter: Option<L::Filter>,
    /// End the call after CAUGHT_UP.
    stop_when_caught_up: bool,
    tx: mpsc::Sender<Result<L::Message, Status>>,
    /// A watcher that reads no event for this long is let go (it resumes with its cursor).
    idle: StreamIdle,
    /// Who watches: judged again at every change of the identities.
    caller: Caller,
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

impl<L: EventLog> Watch<L> {
    /// Sends `event` if it is past the position and wanted; advances the position.
    async fn offer(&mut self, event: &L::Event) -> Result<(), Stop> {
        let position = L::position(event);
        if position <= self.position {
            return Ok(());
        }
        self.position = position;
        if L::wanted(self.filter.as_ref(), event) {
            self.send(L::message(event)).await?;
        }
        Ok(())
    }

    /// Sends `message` if the identities in force still admit the caller.
    async fn send(&mut self, message: L::Message) -> Result<(), Stop> {
        self.caller.check_standing(None).map_err(Stop::Fail)?;
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
            let page = L::read(
                &self.store,
                self.position,
                through,
                self.filter.as_ref(),
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
            for event in &page {
                self.offer(event).await?;
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
        mut subscription: FeedSubscription<L>,
        replay_through: i64,
    ) -> Result<(), Stop> {
        self.replay_stored(replay_through).await?;
        self.send(L::caught_up(self.position)).await?;
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
                    status = self.caller.until_revoked(None) => return Err(Stop::Fail(status)),
                    received = subscription.live.recv() => received,
                };
                match received {
                    Ok(event) => self.offer(&event).await?,
                    Err(RecvError::Lagged(missed)) => {
                        tracing::debug!(
                            missed,
                            position = self.position,
                            "{} watcher fell behind; replaying what it missed",
                            L::NAME
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
