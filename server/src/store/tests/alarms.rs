//! Alarm events: batched onsets and ends with server-assigned ids, retries, list, recovery of open
//! alarms.

use super::temp_store;
use crate::store::{AlarmEventRow, AlarmWrite, StoreError};

fn onset(id: i64, vehicle_id: &str, onset_timestamp_s: f64, probability: f64) -> AlarmWrite {
    AlarmWrite::Onset {
        id,
        vehicle_id: vehicle_id.to_string(),
        model_id: "m1".to_string(),
        onset_timestamp_s,
        onset_at_ms: 1_000 + id,
        probability,
    }
}

fn end(id: i64, end_timestamp_s: f64, peak_probability: f64, samples: u32) -> AlarmWrite {
    AlarmWrite::End {
        id,
        end_timestamp_s,
        ended_at_ms: 2_000 + id,
        peak_probability,
        samples,
    }
}

fn ids(rows: Vec<AlarmEventRow>) -> Vec<i64> {
    rows.into_iter().map(|r| r.id).collect()
}

#[tokio::test]
async fn an_onset_and_its_end_are_stored_under_the_given_id() {
    let (_dir, store) = temp_store().await;
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

#[tokio::test]
async fn a_retried_batch_stores_everything_exactly_once() {
    let (_dir, store) = temp_store().await;
    let batch = [
        onset(1, "a", 10.0, 0.9),
        onset(2, "b", 11.0, 0.8),
        end(1, 15.0, 0.95, 6),
    ];
    store.write_alarms(&batch).await.unwrap();
    let first = store.list_alarm_events(None, 10).await.unwrap();
    // The outcome of a batch can be unknown (e.g. a lost commit acknowledgement): writing it again
    // changes nothing, and a later end of a closed alarm keeps the first end.
    store.write_alarms(&batch).await.unwrap();
    store.write_alarms(&[end(1, 99.0, 0.99, 99)]).await.unwrap();
    assert_eq!(store.list_alarm_events(None, 10).await.unwrap(), first);
    assert_eq!(ids(first), [2, 1]);
}

#[tokio::test]
async fn a_batch_with_an_invalid_value_writes_nothing() {
    let (_dir, store) = temp_store().await;
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

#[tokio::test]
async fn list_alarm_events_filters_by_vehicle_newest_first_with_limit() {
    let (_dir, store) = temp_store().await;
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

#[tokio::test]
async fn close_open_alarms_ends_only_open_ones_without_an_end_timestamp() {
    let (_dir, store) = temp_store().await;
    store
        .write_alarms(&[
            onset(1, "a", 1.0, 0.9),
            end(1, 2.0, 0.9, 2),
            onset(2, "b", 3.0, 0.7),
        ])
        .await
        .unwrap();
    let closed_before = store.list_alarm_events(Some("a"), 1).await.unwrap();

    assert_eq!(store.close_open_alarms(4_242).await.unwrap(), 1);
    let recovered = &store.list_alarm_events(Some("b"), 1).await.unwrap()[0];
    assert_eq!(recovered.id, 2);
    assert_eq!(recovered.ended_at_ms, Some(4_242));
    assert_eq!(recovered.end_timestamp_s, None);
    assert!(!recovered.is_open());
    assert_eq!(
        store.list_alarm_events(Some("a"), 1).await.unwrap(),
        closed_before
    );
    assert_eq!(store.close_open_alarms(5_000).await.unwrap(), 0);
}
