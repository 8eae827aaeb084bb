//! Alarm severities in the store: an escalation turns the open alarm critical in its row and in
//! the event log, an end keeps the highest severity, ListAlarms and the log read filter by the
//! least severity, and alarms stored before schema version 10 read as warnings.

use spoofwatch_core::severity::Severity;

use super::alarms::{end, onset};
use crate::alarms::event::escalated;
use crate::store::{
    AlarmEvent, AlarmEventKind, AlarmFilter, PageRequest, Store, StoreError, StoredSeverity,
};

/// The escalation of alarm `id` (seq `500 + id`, stored as opened by [`onset`]) at sample time
/// `timestamp_s`, wall time `3_000 + id`, with 5 samples and peak 0.99 by then.
fn escalation(id: i64, vehicle_id: &str, onset_timestamp_s: f64, timestamp_s: f64) -> AlarmEvent {
    let open = onset(id, vehicle_id, onset_timestamp_s, 0.8).alarm;
    AlarmEvent {
        seq: 500 + id,
        kind: AlarmEventKind::Escalated,
        alarm: escalated(&open, timestamp_s, 3_000 + id, 0.99, 5),
    }
}

/// An onset that is critical at once (decisive evidence): escalated at its onset.
fn critical_onset(id: i64, vehicle_id: &str, onset_timestamp_s: f64) -> AlarmEvent {
    let mut event = onset(id, vehicle_id, onset_timestamp_s, 0.99);
    event.alarm.severity = StoredSeverity(Severity::Critical);
    event.alarm.escalated_timestamp_s = Some(onset_timestamp_s);
    event.alarm.escalated_at_ms = Some(event.alarm.onset_at_ms);
    event
}

/// (kind, severity, escalated sample time) of every logged event of `vehicle`.
async fn logged(store: &Store, vehicle: &str) -> Vec<(AlarmEventKind, Severity, Option<f64>)> {
    let events = store.alarm_events_after(0, i64::MAX, Some(vehicle), 10);
    events
        .await
        .unwrap()
        .iter()
        .map(|e| {
            let alarm = &e.event.alarm;
            (e.event.kind, alarm.severity.0, alarm.escalated_timestamp_s)
        })
        .collect()
}

async fn an_escalation_turns_the_open_alarm_critical_once_and_its_end_stays_critical(store: Store) {
    store
        .write_alarms(&[onset(1, "car-1", 100.0, 0.8)])
        .await
        .unwrap();
    let listed = &store.list_alarm_events(Some("car-1"), 1).await.unwrap()[0];
    assert_eq!(listed.severity, StoredSeverity(Severity::Warning));

    store
        .write_alarms(&[escalation(1, "car-1", 100.0, 104.0)])
        .await
        .unwrap();
    let row = &store.list_alarm_events(Some("car-1"), 1).await.unwrap()[0];
    assert_eq!(row.severity, StoredSeverity(Severity::Critical));
    assert_eq!(
        (row.escalated_timestamp_s, row.escalated_at_ms),
        (Some(104.0), Some(3_001))
    );
    assert_eq!((row.peak_probability, row.samples), (0.99, 5));
    assert!(row.is_open());

    // A retried escalation changes and logs nothing; the end, from a copy of the alarm that had
    // not seen the escalation, ends it critical.
    store
        .write_alarms(&[escalation(1, "car-1", 100.0, 104.0)])
        .await
        .unwrap();
    store
        .write_alarms(&[end(1, 120.0, 0.99, 21)])
        .await
        .unwrap();
    let row = &store.list_alarm_events(Some("car-1"), 1).await.unwrap()[0];
    assert_eq!(
        (
            row.severity.0,
            row.escalated_timestamp_s,
            row.end_timestamp_s
        ),
        (Severity::Critical, Some(104.0), Some(120.0))
    );
    assert_eq!(
        logged(&store, "car-1").await,
        [
            (AlarmEventKind::Onset, Severity::Warning, None),
            (AlarmEventKind::Escalated, Severity::Critical, Some(104.0)),
            (AlarmEventKind::End, Severity::Critical, Some(104.0)),
        ]
    );

    // An escalation of an alarm that ended (another process ended it first) changes nothing.
    store
        .write_alarms(&[onset(2, "car-2", 200.0, 0.8)])
        .await
        .unwrap();
    store.write_alarms(&[end(2, 210.0, 0.9, 11)]).await.unwrap();
    store
        .write_alarms(&[escalation(2, "car-2", 200.0, 205.0)])
        .await
        .unwrap();
    let row = &store.list_alarm_events(Some("car-2"), 1).await.unwrap()[0];
    assert_eq!(row.severity, StoredSeverity(Severity::Warning));
    assert_eq!(logged(&store, "car-2").await.len(), 2);
}

async fn lists_and_the_log_filter_by_the_least_severity(store: Store) {
    store
        .write_alarms(&[
            onset(1, "car-1", 10.0, 0.8),
            onset(2, "car-2", 20.0, 0.8),
            critical_onset(3, "car-3", 30.0),
        ])
        .await
        .unwrap();
    store
        .write_alarms(&[
            end(1, 15.0, 0.9, 6),
            escalation(2, "car-2", 20.0, 24.0),
            end(2, 29.0, 0.99, 10),
        ])
        .await
        .unwrap();
    let ids = async |min_severity| {
        let filter = AlarmFilter {
            min_severity,
            ..AlarmFilter::default()
        };
        let page = store.list_alarms(&filter, &PageRequest::first(10)).await;
        page.unwrap().items.iter().map(|a| a.id).collect::<Vec<_>>()
    };
    assert_eq!(ids(Severity::Warning).await, [1, 2, 3]);
    assert_eq!(ids(Severity::Critical).await, [2, 3]);

    let critical = store
        .alarm_events_at_least(0, i64::MAX, None, Severity::Critical, 10)
        .await
        .unwrap();
    let critical: Vec<_> = critical
        .iter()
        .map(|e| (e.event.alarm.id, e.event.kind))
        .collect();
    assert_eq!(
        critical,
        [
            (3, AlarmEventKind::Onset),
            (2, AlarmEventKind::Escalated),
            (2, AlarmEventKind::End)
        ],
        "in log order: the critical onset, the escalation and the critical alarm's end"
    );
    let of_car_2 = store
        .alarm_events_at_least(0, i64::MAX, Some("car-2"), Severity::Critical, 10)
        .await
        .unwrap();
    assert_eq!(of_car_2.len(), 2);
}

async fn a_severity_without_its_escalation_times_is_refused(store: Store) {
    let mut bare = escalation(1, "car-1", 10.0, 12.0);
    bare.alarm.escalated_at_ms = None;
    let mut warning_escalation = escalation(2, "car-2", 10.0, 12.0);
    warning_escalation.alarm.severity = StoredSeverity(Severity::Warning);
    warning_escalation.alarm.escalated_timestamp_s = None;
    warning_escalation.alarm.escalated_at_ms = None;
    let mut not_finite = critical_onset(3, "car-3", 10.0);
    not_finite.alarm.escalated_timestamp_s = Some(f64::INFINITY);
    for (event, field) in [
        (bare, "severity"),
        (warning_escalation, "severity"),
        (not_finite, "escalated_timestamp_s"),
    ] {
        let refused = store.write_alarms(&[event]).await;
        assert!(
            matches!(&refused, Err(StoreError::InvalidValue { field: f, .. }) if *f == field),
            "{refused:?}"
        );
    }
}

on_both_backends!(
    an_escalation_turns_the_open_alarm_critical_once_and_its_end_stays_critical,
    lists_and_the_log_filter_by_the_least_severity,
    a_severity_without_its_escalation_times_is_refused,
);

/// Migration 0010 on alarms and events stored before it: they read back as warnings, in the same
/// log positions, and an escalation can follow.
mod alarms_before_version_10_are_warnings {
    use spoofwatch_core::severity::Severity;

    use super::escalation;
    use crate::store::{AlarmEventKind, AlarmFilter, PageRequest, Store};

    const OLD: [&str; 2] = [
        "INSERT INTO alarm_events (id, vehicle_id, model_id, onset_timestamp_s, onset_at, \
         ended_at, peak_probability, samples) VALUES (1, 'car-1', 'm', 10.0, 1001, 5, 0.9, 1), \
         (2, 'car-2', 'm1', 20.0, 1002, NULL, 0.8, 1)",
        "INSERT INTO alarm_event_log (position, seq, alarm_id, kind, ended_at, peak_probability, \
         samples) VALUES (1, 1, 1, 'onset', NULL, 0.9, 1), (2, 2, 2, 'onset', NULL, 0.8, 1), \
         (3, 3, 1, 'end', 5, 0.9, 1)",
    ];

    async fn check(store: Store) {
        let listed = store
            .list_alarms(&AlarmFilter::default(), &PageRequest::first(10))
            .await
            .unwrap()
            .items;
        let levels: Vec<_> = listed
            .iter()
            .map(|a| (a.id, a.severity.0, a.escalated_timestamp_s))
            .collect();
        assert_eq!(
            levels,
            [(1, Severity::Warning, None), (2, Severity::Warning, None)]
        );
        store
            .write_alarms(&[escalation(2, "car-2", 20.0, 25.0)])
            .await
            .unwrap();
        let logged = store
            .alarm_events_after(0, i64::MAX, None, 10)
            .await
            .unwrap();
        let logged: Vec<_> = logged
            .iter()
            .map(|e| (e.position, e.event.kind, e.event.alarm.severity.0))
            .collect();
        assert_eq!(
            logged,
            [
                (1, AlarmEventKind::Onset, Severity::Warning),
                (2, AlarmEventKind::Onset, Severity::Warning),
                (3, AlarmEventKind::End, Severity::Warning),
                (4, AlarmEventKind::Escalated, Severity::Critical),
            ]
        );
    }

    from_schema_version!(9, sqlite: OLD, postgres: OLD);
}
