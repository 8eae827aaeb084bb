//! The alarm event log as an [`EventLog`]: what WatchAlarms follows (the live feed of newly stored
//! events is `crate::event_log::feed`).

use spoofwatch_core::severity::Severity;
use spoofwatch_proto::v1;

use super::wire::{caught_up, event_to_proto};
use crate::event_log::EventLog;
use crate::event_log::feed::Feed;
use crate::store::{LoggedAlarmEvent, Store, StoreError};

/// The alarm event log (filtered by vehicle and by severity).
#[derive(Debug)]
pub struct AlarmLog;

/// What a WatchAlarms caller asks for beyond the whole fleet's events.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct AlarmWatchFilter {
    /// Only this vehicle's events.
    pub vehicle_id: Option<String>,
    /// Only events that left their alarm at least this severe (warning: every event; critical:
    /// onsets as critical, escalations, ends of critical alarms).
    pub min_severity: Severity,
}

/// The live feed of stored alarm events.
pub type AlarmFeed = Feed<AlarmLog>;

impl EventLog for AlarmLog {
    type Event = LoggedAlarmEvent;
    type Filter = AlarmWatchFilter;
    type Message = v1::AlarmEvent;
    const NAME: &'static str = "alarm";
    const LISTING_RPC: &'static str = "ListAlarms";

    fn position(event: &LoggedAlarmEvent) -> i64 {
        event.position
    }

    async fn read(
        store: &Store,
        after: i64,
        through: i64,
        filter: Option<&AlarmWatchFilter>,
        limit: u32,
    ) -> Result<Vec<LoggedAlarmEvent>, StoreError> {
        let filter = filter.cloned().unwrap_or_default();
        store
            .alarm_events_at_least(
                after,
                through,
                filter.vehicle_id.as_deref(),
                filter.min_severity,
                limit,
            )
            .await
    }

    async fn latest(store: &Store) -> Result<i64, StoreError> {
        store.latest_alarm_position().await
    }

    fn wanted(filter: Option<&AlarmWatchFilter>, event: &LoggedAlarmEvent) -> bool {
        let alarm = &event.event.alarm;
        filter.is_none_or(|f| {
            f.vehicle_id.as_ref().is_none_or(|v| *v == alarm.vehicle_id)
                && alarm.severity.0 >= f.min_severity
        })
    }

    fn message(event: &LoggedAlarmEvent) -> v1::AlarmEvent {
        event_to_proto(event)
    }

    fn caught_up(cursor: i64) -> v1::AlarmEvent {
        caught_up(cursor)
    }
}

#[cfg(test)]
mod tests {
    use std::time::Duration;

    use tokio_util::sync::CancellationToken;

    use super::*;
    use crate::alarms::event::Onset;
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
        let first = here.onset(&Onset::warning("car-1", "m", 1.0, 1, 0.9));
        here.run(store.clone(), stop.clone(), Duration::from_secs(1))
            .await;
        let second = there.onset(&Onset::warning("car-2", "m", 2.0, 1, 0.8));
        there
            .run(store.clone(), stop.clone(), Duration::from_secs(1))
            .await;
        here.end(first, 3.0, 0.95, 3, Severity::Warning);
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
