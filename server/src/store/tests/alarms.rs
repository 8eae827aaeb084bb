//! Alarm events: batched onsets and ends with server-assigned ids, retries, list, recovery of open
//! alarms, and the event log's positions (assigned by the database in commit order).

use crate::alarms::event::{Onset, ended, opened};
use crate::store::{
    AlarmEvent, AlarmEventKind, AlarmEventRow, AlarmFilter, AlarmState, LoggedAlarmEvent,
    PageRequest, Store, StoreError, StoredWhy,
};

/// The onset of alarm `id` (seq `id`), opened at wall time `1_000 + id`.
pub(super) fn onset(
    id: i64,
    vehicle_id: &str,
    onset_timestamp_s: f64,
    probability: f64,
) -> AlarmEvent {
    AlarmEvent {
        seq: id,
        kind: AlarmEventKind::Onset,
        alarm: opened(
            id,
            &Onset::warning(vehicle_id, "m1", onset_timestamp_s, 1_000 + id, probability),
        ),
    }
}

/// The end of alarm `id` (seq `1_000 + id`) at wall time `2_000 + id`. The store reads only the
/// id and the end's own values of an end.
pub(super) fn end(
    id: i64,
    end_timestamp_s: f64,
    peak_probability: f64,
    samples: i64,
) -> AlarmEvent {
    AlarmEvent {
        seq: 1_000 + id,
        kind: AlarmEventKind::End,
        alarm: ended(
            &opened(id, &Onset::warning("unread", "unread", 0.0, 0, 0.5)),
            Some(end_timestamp_s),
            2_000 + id,
            peak_probability,
            samples,
        ),
    }
}

fn ids(rows: Vec<AlarmEventRow>) -> Vec<i64> {
    rows.into_iter().map(|r| r.id).collect()
}

async fn an_onset_and_its_end_are_stored_under_the_given_id(store: Store) {
    assert_eq!(store.max_alarm_id().await.unwrap(), 0);
    store
        .write_alarms(&[onset(7, "car-7", 120.5, 0.81)])
        .await
        .unwrap();
    let open = &store.list_alarm_events(Some("car-7"), 10).await.unwrap()[0];
    assert_eq!(open.id, 7);
    assert_eq!(
        (open.vehicle_id.as_str(), open.model_id.as_str()),
        ("car-7", "m1")
    );
    assert_eq!((open.onset_timestamp_s, open.onset_at_ms), (120.5, 1_007));
    assert_eq!((open.end_timestamp_s, open.ended_at_ms), (None, None));
    assert!(open.is_open());
    assert_eq!((open.peak_probability, open.samples), (0.81, 1));
    assert_eq!(store.max_alarm_id().await.unwrap(), 7);

    store
        .write_alarms(&[end(7, 131.0, 0.97, 11)])
        .await
        .unwrap();
    let closed = &store.list_alarm_events(None, 10).await.unwrap()[0];
    assert_eq!(
        (closed.end_timestamp_s, closed.ended_at_ms),
        (Some(131.0), Some(2_007))
    );
    assert_eq!((closed.peak_probability, closed.samples), (0.97, 11));
    assert!(!closed.is_open());
}

/// A jump 300 m east and 400 m north with a slight drift.
fn jump_why() -> StoredWhy {
    StoredWhy {
        why_kind: Some("jump".to_string()),
        why_offset_east_m: Some(300.0),
        why_offset_north_m: Some(400.0),
        why_drift_east_mps: Some(-0.5),
        why_drift_north_mps: Some(0.25),
    }
}

async fn the_onsets_why_is_kept_through_its_end_in_every_read(store: Store) {
    let mut explained = onset(9, "car-9", 50.0, 0.9);
    explained.alarm.why = jump_why();
    store
        .write_alarms(&[explained, onset(10, "car-10", 51.0, 0.9)])
        .await
        .unwrap();
    // The end carries no explanation of its own: the stored one stays.
    store.write_alarms(&[end(9, 60.0, 0.95, 11)]).await.unwrap();
    let listed = store
        .list_alarms(&AlarmFilter::default(), &PageRequest::first(10))
        .await
        .unwrap()
        .items;
    let whys: Vec<_> = listed.iter().map(|a| (a.id, a.why.clone())).collect();
    assert_eq!(whys, [(9, jump_why()), (10, StoredWhy::default())]);
    let logged = store
        .alarm_events_after(0, i64::MAX, Some("car-9"), 10)
        .await
        .unwrap();
    assert_eq!(logged.len(), 2, "the onset and the end");
    assert!(logged.iter().all(|e| e.event.alarm.why == jump_why()));

    let mut not_finite = onset(11, "car-11", 52.0, 0.9);
    not_finite.alarm.why = StoredWhy {
        why_offset_north_m: Some(f64::NAN),
        ..jump_why()
    };
    assert!(matches!(
        not_finite.validate(),
        Err(StoreError::InvalidValue {
            field: "why_offset_north_m",
            ..
        })
    ));
}

async fn a_retried_batch_stores_everything_exactly_once(store: Store) {
    let batch = [
        onset(1, "a", 10.0, 0.9),
        onset(2, "b", 11.0, 0.8),
        end(1, 15.0, 0.95, 6),
    ];
    store.write_alarms(&batch).await.unwrap();
    let first = store.list_alarm_events(None, 10).await.unwrap();
    // The outcome of a batch can be unknown (e.g. a lost commit acknowledgement): writing it again
    // changes nothing, nor does an end at an earlier sample (another copy of the session that got
    // less far; one that got further moves the end on, see the snapshot tests).
    store.write_alarms(&batch).await.unwrap();
    let mut earlier = end(1, 14.0, 0.99, 5);
    earlier.seq += 1;
    store.write_alarms(&[earlier]).await.unwrap();
    assert_eq!(store.list_alarm_events(None, 10).await.unwrap(), first);
    assert_eq!(ids(first), [2, 1]);
}

async fn a_batch_with_an_invalid_value_writes_nothing(store: Store) {
    let cases = [
        (onset(1, "car", f64::NAN, 0.5), "onset_timestamp_s"),
        (onset(1, "car", 1.0, 1.5), "probability"),
        (end(1, f64::INFINITY, 0.5, 1), "end_timestamp_s"),
        (end(1, 2.0, -0.1, 1), "peak_probability"),
    ];
    for (bad, field) in cases {
        let error = store
            .write_alarms(&[onset(1, "car", 1.0, 0.5), bad])
            .await
            .unwrap_err();
        assert!(
            matches!(&error, StoreError::InvalidValue { field: f, .. } if *f == field),
            "{error:?}"
        );
        assert!(store.list_alarm_events(None, 10).await.unwrap().is_empty());
    }
}

async fn list_alarm_events_filters_by_vehicle_newest_first_with_limit(store: Store) {
    store
        .write_alarms(&[
            onset(1, "a", 10.0, 0.9),
            onset(2, "b", 5.0, 0.9),
            onset(3, "a", 20.0, 0.8),
        ])
        .await
        .unwrap();
    assert_eq!(
        ids(store.list_alarm_events(None, 10).await.unwrap()),
        [3, 2, 1]
    );
    assert_eq!(
        ids(store.list_alarm_events(Some("a"), 10).await.unwrap()),
        [3, 1]
    );
    assert_eq!(
        ids(store.list_alarm_events(Some("a"), 1).await.unwrap()),
        [3]
    );
    assert!(
        store
            .list_alarm_events(Some("zzz"), 10)
            .await
            .unwrap()
            .is_empty()
    );
    assert!(store.list_alarm_events(None, 0).await.unwrap().is_empty());
}

async fn close_open_alarms_ends_only_open_ones_without_an_end_timestamp(store: Store) {
    store
        .write_alarms(&[
            onset(1, "a", 1.0, 0.9),
            end(1, 2.0, 0.9, 2),
            onset(2, "b", 3.0, 0.7),
        ])
        .await
        .unwrap();
    let closed_before = store.list_alarm_events(Some("a"), 1).await.unwrap();

    let closed = store.close_open_alarms(4_242, 77).await.unwrap();
    assert_eq!(closed.len(), 1);
    assert_eq!((closed[0].seq, closed[0].kind), (77, AlarmEventKind::End));
    let recovered = &store.list_alarm_events(Some("b"), 1).await.unwrap()[0];
    assert_eq!(recovered.id, 2);
    assert_eq!(recovered.ended_at_ms, Some(4_242));
    assert_eq!(recovered.end_timestamp_s, None);
    assert!(!recovered.is_open());
    assert_eq!(
        store.list_alarm_events(Some("a"), 1).await.unwrap(),
        closed_before
    );
    assert!(store.close_open_alarms(5_000, 78).await.unwrap().is_empty());
    let logged = store
        .alarm_events_after(0, i64::MAX, None, 10)
        .await
        .unwrap();
    let logged: Vec<_> = logged
        .iter()
        .map(|e| (e.position, e.event.seq, e.event.alarm.id))
        .collect();
    assert_eq!(logged, [(1, 1, 1), (2, 1_001, 1), (3, 2, 2), (4, 77, 2)]);
    assert_eq!(
        closed[0].alarm, *recovered,
        "the logged end is the alarm as closed"
    );
}

async fn the_event_log_replays_each_event_as_it_was_emitted_in_position_order(store: Store) {
    let events = [
        onset(1, "a", 10.0, 0.6),
        onset(2, "b", 11.0, 0.7),
        end(1, 15.0, 0.95, 6),
    ];
    store.write_alarms(&events).await.unwrap();
    let replayed = store
        .alarm_events_after(0, i64::MAX, None, 10)
        .await
        .unwrap();
    // The onset of alarm 1 is replayed as it opened, although its row has ended since.
    let logged = |position: i64, event: &AlarmEvent| LoggedAlarmEvent {
        position,
        event: event.clone(),
    };
    assert_eq!(replayed[0], logged(1, &events[0]));
    assert_eq!(replayed[1], logged(2, &events[1]));
    assert_eq!((replayed[2].position, replayed[2].event.seq), (3, 1_001));
    assert_eq!(replayed[2].event.kind, AlarmEventKind::End);
    assert_eq!(
        replayed[2].event.alarm,
        ended(&events[0].alarm, Some(15.0), 2_001, 0.95, 6)
    );
    let positions =
        |events: Vec<LoggedAlarmEvent>| events.iter().map(|e| e.position).collect::<Vec<_>>();
    let between = store.alarm_events_after(1, 2, None, 10).await;
    assert_eq!(
        positions(between.unwrap()),
        [2],
        "after is exclusive, through inclusive"
    );
    let of_a = store.alarm_events_after(0, i64::MAX, Some("a"), 10).await;
    assert_eq!(positions(of_a.unwrap()), [1, 3]);
    let first = store.alarm_events_after(0, i64::MAX, None, 1).await;
    assert_eq!(positions(first.unwrap()), [1]);
    assert_eq!(store.latest_alarm_position().await.unwrap(), 3);
}

async fn log_positions_follow_commit_order_not_seq_order(store: Store) {
    assert_eq!(store.latest_alarm_position().await.unwrap(), 0);
    // Two writers' runs: the later run's events (high seqs) commit first, then the earlier run's.
    let later_run = [onset(1 << 33, "b", 1.0, 0.9)];
    let earlier_run = [onset(1 << 32, "a", 2.0, 0.9), end(1 << 32, 3.0, 0.9, 2)];
    store.write_alarms(&later_run).await.unwrap();
    store.write_alarms(&earlier_run).await.unwrap();
    // A retried batch is skipped by seq and takes no position.
    store.write_alarms(&earlier_run).await.unwrap();
    let logged = store
        .alarm_events_after(0, i64::MAX, None, 10)
        .await
        .unwrap();
    let logged: Vec<_> = logged.iter().map(|e| (e.position, e.event.seq)).collect();
    assert_eq!(
        logged,
        [(1, 1 << 33), (2, 1 << 32), (3, 1_000 + (1 << 32))],
        "a row committed later never gets a position below an earlier commit's"
    );
    assert_eq!(store.latest_alarm_position().await.unwrap(), 3);
}

async fn concurrent_writers_get_distinct_positions_without_gaps(store: Store) {
    // Eight writers (separate pooled connections) racing, five batches of two events each.
    let writers: Vec<_> = (0..8i64)
        .map(|writer| {
            let store = store.clone();
            tokio::spawn(async move {
                for batch in 0..5i64 {
                    let id = 100 * writer + 10 * batch + 1;
                    let events = [onset(id, "car", 1.0, 0.9), onset(id + 1, "car", 1.0, 0.9)];
                    store.write_alarms(&events).await.expect("a racing write");
                }
            })
        })
        .collect();
    for writer in writers {
        writer.await.expect("the writer finishes");
    }
    let logged = store
        .alarm_events_after(0, i64::MAX, None, 500)
        .await
        .unwrap();
    let positions: Vec<_> = logged.iter().map(|e| e.position).collect();
    assert_eq!(positions, (1..=80).collect::<Vec<_>>());
    // Each batch's two events are adjacent: a transaction's rows are never interleaved.
    for pair in logged.chunks(2) {
        assert_eq!(pair[0].event.seq + 1, pair[1].event.seq, "{pair:?}");
    }
}

async fn alarm_runs_increase_and_start_blocks_of_cursors_above_the_previous_ones(store: Store) {
    let first = store.start_alarm_run(1).await.unwrap();
    let second = store.start_alarm_run(2).await.unwrap();
    assert!(second > first);
    assert_eq!(
        crate::store::first_seq_of_run(second) - crate::store::first_seq_of_run(first),
        1 << 32
    );
}

async fn list_alarms_filters_and_pages_in_id_order(store: Store) {
    let mut other_model = onset(4, "a", 40.0, 0.9);
    other_model.alarm.model_id = "m2".to_string();
    store
        .write_alarms(&[
            onset(1, "a", 10.0, 0.9),
            onset(2, "b", 20.0, 0.9),
            onset(3, "a", 30.0, 0.9),
            other_model,
            end(1, 12.0, 0.9, 3),
        ])
        .await
        .unwrap();
    let list = async |filter: AlarmFilter| {
        ids(store
            .list_alarms(&filter, &PageRequest::default())
            .await
            .unwrap()
            .items)
    };
    assert_eq!(list(AlarmFilter::default()).await, [1, 2, 3, 4]);
    let vehicle = |v: &str| AlarmFilter {
        vehicle_id: Some(v.to_string()),
        ..AlarmFilter::default()
    };
    assert_eq!(list(vehicle("a")).await, [1, 3, 4]);
    assert_eq!(list(vehicle("zzz")).await, Vec::<i64>::new());
    let model = AlarmFilter {
        model_id: Some("m2".to_string()),
        ..AlarmFilter::default()
    };
    assert_eq!(list(model).await, [4]);
    // Onsets at wall times 1_001 … 1_004: [1_002, 1_004) holds alarms 2 and 3.
    let window = AlarmFilter {
        onset_from_ms: Some(1_002),
        onset_before_ms: Some(1_004),
        ..AlarmFilter::default()
    };
    assert_eq!(list(window).await, [2, 3]);
    let state = |state| AlarmFilter {
        state,
        ..AlarmFilter::default()
    };
    assert_eq!(list(state(AlarmState::Open)).await, [2, 3, 4]);
    assert_eq!(list(state(AlarmState::Closed)).await, [1]);

    let mut pages = Vec::new();
    let mut request = PageRequest::first(3);
    loop {
        let page = store.list_alarms(&vehicle("a"), &request).await.unwrap();
        pages.push(ids(page.items));
        match page.next_page_token {
            Some(token) => request = PageRequest::after(2, token),
            None => break,
        }
    }
    assert_eq!(pages, [vec![1, 3, 4]]);
    let page = store
        .list_alarms(&AlarmFilter::default(), &PageRequest::first(3))
        .await
        .unwrap();
    assert_eq!(ids(page.items), [1, 2, 3]);
    let token = page.next_page_token.expect("a second page");
    let rest = store
        .list_alarms(&AlarmFilter::default(), &PageRequest::after(3, token))
        .await
        .unwrap();
    assert_eq!((ids(rest.items), rest.next_page_token), (vec![4], None));
    assert!(matches!(
        store
            .list_alarms(&AlarmFilter::default(), &PageRequest::after(3, "zz"))
            .await,
        Err(StoreError::InvalidPageToken)
    ));
}

on_both_backends!(
    an_onset_and_its_end_are_stored_under_the_given_id,
    the_onsets_why_is_kept_through_its_end_in_every_read,
    a_retried_batch_stores_everything_exactly_once,
    a_batch_with_an_invalid_value_writes_nothing,
    list_alarm_events_filters_by_vehicle_newest_first_with_limit,
    close_open_alarms_ends_only_open_ones_without_an_end_timestamp,
    the_event_log_replays_each_event_as_it_was_emitted_in_position_order,
    log_positions_follow_commit_order_not_seq_order,
    concurrent_writers_get_distinct_positions_without_gaps,
    alarm_runs_increase_and_start_blocks_of_cursors_above_the_previous_ones,
    list_alarms_filters_and_pages_in_id_order,
);

/// Migration 0005 on a log written before it: positions 1, 2, 3 in seq order, whatever order the
/// rows were inserted in; the next event stored takes the next position.
mod positions_are_backfilled_in_seq_order {
    use crate::store::Store;

    /// Three events of two runs (inserted out of seq order) and their alarms, as schema version 4
    /// holds them.
    const OLD_LOG: [&str; 3] = [
        "INSERT INTO alarm_events (id, vehicle_id, model_id, onset_timestamp_s, onset_at, \
         ended_at, peak_probability, samples) VALUES (4294967296, 'a', 'm', 1.0, 1, 5, 0.9, 1), \
         (8589934592, 'b', 'm', 2.0, 2, NULL, 0.9, 1)",
        "INSERT INTO alarm_event_log (seq, alarm_id, kind, peak_probability, samples) VALUES \
         (8589934592, 8589934592, 'onset', 0.9, 1), (4294967297, 4294967296, 'end', 0.9, 1)",
        "INSERT INTO alarm_event_log (seq, alarm_id, kind, peak_probability, samples) VALUES \
         (4294967296, 4294967296, 'onset', 0.9, 1)",
    ];

    async fn check(store: Store) {
        let logged = store
            .alarm_events_after(0, i64::MAX, None, 10)
            .await
            .unwrap();
        let logged: Vec<_> = logged.iter().map(|e| (e.position, e.event.seq)).collect();
        assert_eq!(logged, [(1, 4294967296), (2, 4294967297), (3, 8589934592)]);
        store.close_open_alarms(3, 3 << 32).await.unwrap();
        let next = store.alarm_events_after(3, i64::MAX, None, 10).await;
        let next: Vec<_> = next.unwrap().iter().map(|e| e.position).collect();
        assert_eq!(next, [4], "b's alarm ended at the next position");
    }

    from_schema_version!(4, sqlite: OLD_LOG, postgres: OLD_LOG);
}

/// Migration 0006 on alarms stored before it: they read back without an explanation.
mod alarms_before_version_6_have_no_why {
    use crate::store::{AlarmFilter, PageRequest, Store, StoredWhy};

    const OLD_ALARM: &str = "INSERT INTO alarm_events (id, vehicle_id, model_id, \
         onset_timestamp_s, onset_at, ended_at, peak_probability, samples) \
         VALUES (4294967296, 'a', 'm', 1.0, 1, 5, 0.9, 1)";

    async fn check(store: Store) {
        let listed = store
            .list_alarms(&AlarmFilter::default(), &PageRequest::first(10))
            .await
            .unwrap()
            .items;
        assert_eq!(listed.len(), 1);
        assert_eq!(listed[0].why, StoredWhy::default());
    }

    from_schema_version!(5, sqlite: [OLD_ALARM], postgres: [OLD_ALARM]);
}
