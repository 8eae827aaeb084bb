//! The live feed behind WatchAlarms: one follower task per server reads the alarm event log after
//! the last position it has broadcast and broadcasts each new row to this server's watchers.
//!
//! Live events come from the shared log, not from this server's queue, so a watcher on any replica
//! follows every replica's events, in position (commit) order. The follower reads as soon as the
//! local alarm writer has committed (so local events stay near-instant) and otherwise every
//! [`POLL`] (other replicas' events). A read that fails is retried on the next tick; watchers keep
//! their streams meanwhile and get the events once the database answers again.

use std::sync::{Arc, Mutex, MutexGuard};
use std::time::Duration;

use tokio::sync::{Notify, broadcast};
use tokio::time::MissedTickBehavior;
use tokio_util::sync::CancellationToken;

use crate::store::{LoggedAlarmEvent, Store, StoreError};

/// How often the follower looks for events other processes stored.
pub const POLL: Duration = Duration::from_millis(200);
/// Events a watcher may fall behind before it is told it lagged (it then replays from the log).
const LIVE_BUFFER: usize = 4_096;
/// Rows read per query of the follower.
const PAGE: u32 = 500;

/// Where a watcher joins the feed (see [`AlarmFeed::subscribe`]).
#[derive(Debug)]
pub struct FeedSubscription {
    /// Every event broadcast after `head`.
    pub live: broadcast::Receiver<Arc<LoggedAlarmEvent>>,
    /// The last position broadcast when the receiver was created: every event up to it is in the
    /// log, every later one reaches `live`.
    pub head: i64,
}

/// The follower's state: the last position broadcast and the channel to the watchers.
#[derive(Debug)]
pub struct AlarmFeed {
    /// Held while broadcasting, so that a subscription's receiver and head fit together.
    head: Mutex<i64>,
    live: broadcast::Sender<Arc<LoggedAlarmEvent>>,
}

impl AlarmFeed {
    /// A feed starting after the latest event stored now.
    pub async fn new(store: &Store) -> Result<Self, StoreError> {
        Ok(Self::starting_after(store.latest_alarm_position().await?))
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
    pub fn subscribe(&self) -> FeedSubscription {
        let head = self.head();
        FeedSubscription {
            live: self.live.subscribe(),
            head: *head,
        }
    }

    /// Broadcasts every stored event after the head, page by page.
    async fn read_new(&self, store: &Store) -> Result<(), StoreError> {
        loop {
            let after = *self.head();
            let page = store
                .alarm_events_after(after, i64::MAX, None, PAGE)
                .await?;
            let complete = page.len() < PAGE as usize;
            let mut head = self.head();
            for event in page {
                // Only this task moves the head; the check keeps a position from being sent twice.
                if event.position > *head {
                    *head = event.position;
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

    /// The follower: reads new events when `stored` is told (the local writer committed) and every
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
                    tracing::info!("alarm feed recovered: watchers get new alarm events again");
                }
                Ok(()) => {}
                Err(error) if !failing => {
                    failing = true;
                    tracing::warn!(
                        %error,
                        head = *self.head(),
                        "could not read new alarm events for watchers; retrying every {} ms",
                        POLL.as_millis()
                    );
                }
                Err(_) => {}
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::outbox::SessionOutbox;
    use crate::store::AlarmEventKind;

    /// Two outboxes on one database (two replicas) and one feed: the feed broadcasts both one's
    /// and the other's stored events, once each, in position order, and a subscription's head
    /// covers everything broadcast before it.
    #[tokio::test]
    async fn the_feed_broadcasts_every_writer_s_stored_events_in_position_order() {
        let dir = tempfile::tempdir().expect("temp dir");
        let store = Store::open(&dir.path().join("f.db").to_string_lossy())
            .await
            .expect("open");
        let (here, there) = (
            SessionOutbox::new(&store, 10).await.unwrap(),
            SessionOutbox::new(&store, 10).await.unwrap(),
        );
        let feed = AlarmFeed::new(&store).await.unwrap();
        let mut subscription = feed.subscribe();
        assert_eq!(subscription.head, 0);

        let stop = CancellationToken::new();
        stop.cancel();
        let first = here.onset("car-1", "m", 1.0, 1, 0.9, None);
        here.run(store.clone(), stop.clone(), Duration::from_secs(1))
            .await;
        let second = there.onset("car-2", "m", 2.0, 1, 0.8, None);
        there
            .run(store.clone(), stop.clone(), Duration::from_secs(1))
            .await;
        here.end(first, 3.0, 0.95, 3);
        here.run(store.clone(), stop, Duration::from_secs(1)).await;
        feed.read_new(&store).await.unwrap();

        let mut received = Vec::new();
        while let Ok(event) = subscription.live.try_recv() {
            received.push((event.position, event.event.kind, event.event.alarm.id));
        }
        assert_eq!(
            received,
            [
                (1, AlarmEventKind::Onset, first),
                (2, AlarmEventKind::Onset, second),
                (3, AlarmEventKind::End, first)
            ]
        );
        feed.read_new(&store).await.unwrap();
        assert!(subscription.live.try_recv().is_err(), "nothing twice");
        assert_eq!(feed.subscribe().head, 3);
    }
}
