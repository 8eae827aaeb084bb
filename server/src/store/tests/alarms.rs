//! Alarm events: open, update, close, list, recovery of open alarms.

use super::temp_store;
use crate::store::{StoreError, now_unix_ms};

#[tokio::test]
async fn alarm_opens_updates_and_closes() {
    let (_dir, store) = temp_store().await;
    let before = now_unix_ms();
    let id = store.open_alarm("car-7", "m1", 120.5, 0.81).await.unwrap();

    let open = store.list_alarm_events(Some("car-7"), 10).await.unwrap();
    assert_eq!(open.len(), 1);
    let row = &open[0];
    assert_eq!(row.id, id);
    assert_eq!(
        (row.vehicle_id.as_str(), row.model_id.as_str()),
        ("car-7", "m1")
    );
    assert_eq!(row.onset_timestamp_s, 120.5);
    assert_eq!(row.end_timestamp_s, None);
    assert!(row.onset_at_ms >= before);
    assert_eq!(row.ended_at_ms, None);
    assert!(row.is_open());
    assert_eq!((row.peak_probability, row.samples), (0.81, 1));

    store.update_alarm_peak(id, 0.93, 4).await.unwrap();
    let updated = &store.list_alarm_events(None, 10).await.unwrap()[0];
    assert_eq!((updated.peak_probability, updated.samples), (0.93, 4));
    assert!(updated.is_open());

    store.close_alarm(id, 131.0, 0.97, 11).await.unwrap();
    let closed = &store.list_alarm_events(None, 10).await.unwrap()[0];
    assert_eq!(closed.end_timestamp_s, Some(131.0));
    assert!(closed.ended_at_ms.expect("ended") >= closed.onset_at_ms);
    assert_eq!((closed.peak_probability, closed.samples), (0.97, 11));
    assert!(!closed.is_open());
}

#[tokio::test]
async fn closed_or_unknown_alarms_cannot_be_changed() {
    let (_dir, store) = temp_store().await;
    let id = store.open_alarm("car-7", "m1", 1.0, 0.9).await.unwrap();
    store.close_alarm(id, 2.0, 0.9, 2).await.unwrap();

    let error = store.close_alarm(id, 3.0, 0.99, 3).await.unwrap_err();
    assert!(
        matches!(
            &error,
            StoreError::InvalidState {
                kind: "alarm event",
                action: "close",
                state: "closed",
                ..
            }
        ),
        "{error:?}"
    );
    assert!(matches!(
        store.update_alarm_peak(id, 0.99, 3).await,
        Err(StoreError::InvalidState {
            action: "update",
            ..
        })
    ));
    let kept = &store.list_alarm_events(None, 1).await.unwrap()[0];
    assert_eq!(
        (kept.end_timestamp_s, kept.peak_probability, kept.samples),
        (Some(2.0), 0.9, 2)
    );

    let missing = id + 100;
    let error = store.close_alarm(missing, 3.0, 0.9, 1).await.unwrap_err();
    assert!(
        matches!(&error, StoreError::NotFound { kind: "alarm event", id } if *id == missing.to_string()),
        "{error:?}"
    );
    assert!(matches!(
        store.update_alarm_peak(missing, 0.9, 1).await,
        Err(StoreError::NotFound { .. })
    ));
}

#[tokio::test]
async fn invalid_alarm_values_are_refused() {
    let (_dir, store) = temp_store().await;
    assert!(matches!(
        store.open_alarm("car", "m", f64::NAN, 0.5).await,
        Err(StoreError::InvalidValue {
            field: "onset_timestamp_s",
            ..
        })
    ));
    assert!(matches!(
        store.open_alarm("car", "m", 1.0, 1.5).await,
        Err(StoreError::InvalidValue {
            field: "probability",
            ..
        })
    ));
    let id = store.open_alarm("car", "m", 1.0, 0.5).await.unwrap();
    assert!(matches!(
        store.close_alarm(id, f64::INFINITY, 0.5, 1).await,
        Err(StoreError::InvalidValue {
            field: "end_timestamp_s",
            ..
        })
    ));
    assert!(matches!(
        store.update_alarm_peak(id, -0.1, 1).await,
        Err(StoreError::InvalidValue {
            field: "peak_probability",
            ..
        })
    ));
    assert_eq!(store.list_alarm_events(None, 10).await.unwrap().len(), 1);
}

#[tokio::test]
async fn list_alarm_events_filters_by_vehicle_newest_first_with_limit() {
    let (_dir, store) = temp_store().await;
    let a1 = store.open_alarm("a", "m1", 10.0, 0.9).await.unwrap();
    let b1 = store.open_alarm("b", "m1", 5.0, 0.9).await.unwrap();
    let a2 = store.open_alarm("a", "m2", 20.0, 0.8).await.unwrap();
    assert!(a1 < b1 && b1 < a2, "ids increase in opening order");

    let ids =
        |rows: Vec<crate::store::AlarmEventRow>| rows.into_iter().map(|r| r.id).collect::<Vec<_>>();
    assert_eq!(
        ids(store.list_alarm_events(None, 10).await.unwrap()),
        [a2, b1, a1]
    );
    assert_eq!(
        ids(store.list_alarm_events(Some("a"), 10).await.unwrap()),
        [a2, a1]
    );
    assert_eq!(
        ids(store.list_alarm_events(Some("a"), 1).await.unwrap()),
        [a2]
    );
    assert_eq!(
        ids(store.list_alarm_events(Some("zzz"), 10).await.unwrap()),
        Vec::<i64>::new()
    );
    assert_eq!(
        ids(store.list_alarm_events(None, 0).await.unwrap()),
        Vec::<i64>::new()
    );
}

#[tokio::test]
async fn close_open_alarms_ends_only_open_ones_without_an_end_timestamp() {
    let (_dir, store) = temp_store().await;
    let closed = store.open_alarm("a", "m1", 1.0, 0.9).await.unwrap();
    store.close_alarm(closed, 2.0, 0.9, 2).await.unwrap();
    let left_open = store.open_alarm("b", "m1", 3.0, 0.7).await.unwrap();
    let closed_before = store.list_alarm_events(Some("a"), 1).await.unwrap();

    assert_eq!(store.close_open_alarms(4_242).await.unwrap(), 1);
    let recovered = &store.list_alarm_events(Some("b"), 1).await.unwrap()[0];
    assert_eq!(recovered.id, left_open);
    assert_eq!(recovered.ended_at_ms, Some(4_242));
    assert_eq!(recovered.end_timestamp_s, None);
    assert!(!recovered.is_open());
    assert_eq!(
        store.list_alarm_events(Some("a"), 1).await.unwrap(),
        closed_before
    );
    assert_eq!(store.close_open_alarms(5_000).await.unwrap(), 0);
}
