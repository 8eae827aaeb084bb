//! The live feed of an event log: one follower task per server and log reads the log after the
//! last position it has broadcast and broadcasts each new event to this server's watchers.
//!
//! Live events come from the shared log, not from this server's queues, so a watcher on any
//! replica follows every replica's events, in position (commit) order. The follower reads as soon
//! as a local writer has committed (so local events stay near-instant) and otherwise every
//! [`POLL`] (other replicas' events). A read that fails is retried on the next tick; watchers keep
//! their streams meanwhile and get the events once the database answers again.

use std::sync::{Arc, Mutex, MutexGuard};
use std::time::Duration;

use tokio::sync::{Notify, broadcast};
use tokio::time::MissedTickBehavior;
use tokio_util::sync::CancellationToken;

use super::EventLog;
use crate::store::{Store, StoreError};

/// How often the follower looks for events other processes stored.
pub const POLL: Duration = Duration::from_millis(200);
/// Events a watcher may fall behind before it is told it lagged (it then replays from the log).
const LIVE_BUFFER: usize = 4_096;
/// Rows read per query of the follower.
const PAGE: u32 = 500;

/// Where a watcher joins the feed (see [`Feed::subscribe`]).
#[derive(Debug)]
pub struct FeedSubscription<L: EventLog> {
    /// Every event broadcast after `head`.
    pub live: broadcast::Receiver<Arc<L::Event>>,
    /// The last position broadcast when the receiver was created: every event up to it is in the
    /// log, every later one reaches `live`.
    pub head: i64,
}

/// The follower's state: the last position broadcast and the channel to the watchers.
#[derive(Debug)]
pub struct Feed<L: EventLog> {
    /// Held while broadcasting, so that a subscription's receiver and head fit together.
    head: Mutex<i64>,
    live: broadcast::Sender<Arc<L::Event>>,
}

impl<L: EventLog> Feed<L> {
    /// A feed starting after the latest event stored now.
    pub async fn new(store: &Store) -> Result<Self, StoreError> {
        Ok(Self::starting_after(L::latest(store).await?))
    }

    fn starting_after(head: i64) -> Self {
        Self {
            head: Mutex::new(head),
            live: broadcast::channel(LIVE_BUFFER).0,
        }
    }

    fn head(&self) -> MutexGuard<'_, i64> {
        // A plain integer: a poisoned lock still holds a valid one.
        self.head.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Joins the feed: the receiver and the head are taken together.
    pub fn subscribe(&self) -> FeedSubscription<L> {
        let head = self.head();
        FeedSubscription {
            live: self.live.subscribe(),
            head: *head,
        }
    }

    /// Broadcasts every stored event after the head, page by page.
    pub(crate) async fn read_new(&self, store: &Store) -> Result<(), StoreError> {
        loop {
            let after = *self.head();
            let page = L::read(store, after, i64::MAX, None, PAGE).await?;
            let complete = page.len() < PAGE as usize;
            let mut head = self.head();
            for event in page {
                // Only this task moves the head; the check keeps a position from being sent twice.
                let position = L::position(&event);
                if position > *head {
                    *head = position;
                    // No watcher is not an error.
                    let _ = self.live.send(Arc::new(event));
                }
            }
            drop(head);
            if complete {
                return Ok(());
            }
        }
    }

    /// The follower: reads new events when `stored` is told (a local writer committed) and every
    /// [`POLL`], until `stop` is cancelled. A failed read is logged once per outage.
    pub async fn follow(&self, store: Store, stored: &Notify, stop: CancellationToken) {
        let mut tick = tokio::time::interval(POLL);
        tick.set_missed_tick_behavior(MissedTickBehavior::Delay);
        let mut failing = false;
        loop {
            tokio::select! {
                biased;
                _ = stop.cancelled() => return,
                _ = stored.notified() => {}
                _ = tick.tick() => {}
            }
            match self.read_new(&store).await {
                Ok(()) if failing => {
                    failing = false;
                    tracing::info!(
                        "{} feed recovered: watchers get new {} events again",
                        L::NAME,
                        L::NAME
                    );
                }
                Ok(()) => {}
                Err(error) if !failing => {
                    failing = true;
                    tracing::warn!(
                        %error,
                        head = *self.head(),
                        "could not read new {} events for watchers; retrying every {} ms",
                        L::NAME,
                        POLL.as_millis()
                    );
                }
                Err(_) => {}
            }
        }
    }
}
