//! Area incidents: the correlator's lease, one step's writes together (fenced on the lease), the
//! incident listing and the event log; the onset place the correlator reads from alarms; and an
//! admin's end of an incident, recorded once and never overwritten by the correlator.

use serde_json::json;

use crate::alarms::event::{Onset, opened};
use crate::store::{
    AlarmEvent, AlarmEventKind, CloseOutcome, Closure, ClosureKind, CorrelationStep,
    CorrelatorPlace, IncidentEventKind, IncidentState, IncidentWrite, PageRequest, Store,
    StoredPlace,
};

const LEASE_MS: i64 = 10_000;

fn write(id: i64, event: Option<IncidentEventKind>, ended: bool, vehicles: u32) -> IncidentWrite {
    IncidentWrite {
        id,
        event,
        ended,
        body: json!({ "id": id, "vehicles": vehicles }),
    }
}

fn step(alarm_position: i64, incidents: Vec<IncidentWrite>) -> CorrelationStep {
    CorrelationStep {
        incidents,
        place: CorrelatorPlace {
            alarm_position,
            state: Some(json!({ "read": alarm_position })),
        },
    }
}

async fn the_lease_has_one_holder_until_it_expires(store: Store) {
    let first = store
        .claim_incident_correlator("a", 1_000, LEASE_MS)
        .await
        .unwrap();
    assert_eq!(
        first,
        Some(CorrelatorPlace {
            alarm_position: 0,
            state: None
        })
    );
    assert_eq!(
        store
            .claim_incident_correlator("b", 5_000, LEASE_MS)
            .await
            .unwrap(),
        None,
        "a holds it"
    );
    assert!(
        store
            .claim_incident_correlator("a", 9_000, LEASE_MS)
            .await
            .unwrap()
            .is_some()
    );
    // a stops renewing: b takes over once the lease has run out since a's last renewal.
    assert_eq!(
        store
            .claim_incident_correlator("b", 19_000, LEASE_MS)
            .await
            .unwrap(),
        None
    );
    assert!(
        store
            .claim_incident_correlator("b", 19_001, LEASE_MS)
            .await
            .unwrap()
            .is_some()
    );
    // a comes back (a stalled process): its step is fenced off and writes nothing.
    let stale = step(7, vec![write(1, Some(IncidentEventKind::Opened), false, 3)]);
    assert!(
        !store
            .write_correlation_step("a", 19_500, &stale)
            .await
            .unwrap()
    );
    assert_eq!(store.latest_incident_position().await.unwrap(), 0);
    assert!(store.get_incident(1).await.unwrap().is_none());
    // Given up, the lease is free at once.
    store.release_incident_correlator("b").await.unwrap();
    assert!(
        store
            .claim_incident_correlator("c", 19_600, LEASE_MS)
            .await
            .unwrap()
            .is_some()
    );
}

async fn a_step_stores_incidents_their_events_and_the_place_together(store: Store) {
    store
        .claim_incident_correlator("a", 1_000, LEASE_MS)
        .await
        .unwrap();
    let first = step(
        4,
        vec![
            write(1, Some(IncidentEventKind::Opened), false, 3),
            write(2, Some(IncidentEventKind::Opened), false, 3),
        ],
    );
    assert!(
        store
            .write_correlation_step("a", 2_000, &first)
            .await
            .unwrap()
    );
    let second = step(
        9,
        vec![
            // A member's alarm ended: the row changes, no event.
            write(1, None, false, 3),
            write(2, Some(IncidentEventKind::Joined), false, 4),
            write(1, Some(IncidentEventKind::Ended), true, 3),
        ],
    );
    assert!(
        store
            .write_correlation_step("a", 3_000, &second)
            .await
            .unwrap()
    );

    let place = store
        .claim_incident_correlator("a", 3_500, LEASE_MS)
        .await
        .unwrap();
    assert_eq!(
        place,
        Some(CorrelatorPlace {
            alarm_position: 9,
            state: Some(json!({ "read": 9 }))
        })
    );
    let one = store.get_incident(1).await.unwrap().expect("stored");
    assert_eq!((one.opened_at_ms, one.ended_at_ms), (2_000, Some(3_000)));
    let two = store.get_incident(2).await.unwrap().expect("stored");
    assert_eq!(
        (two.ended_at_ms, &two.body),
        (None, &json!({ "id": 2, "vehicles": 4 }))
    );

    let ids = |rows: Vec<crate::store::IncidentRow>| rows.iter().map(|r| r.id).collect::<Vec<_>>();
    let first_page = PageRequest::first(1);
    let page = |state| store.list_incidents(state, &first_page);
    let open = page(IncidentState::Open).await.unwrap();
    assert_eq!((ids(open.items), open.next_page_token), (vec![2], None));
    assert_eq!(ids(page(IncidentState::Ended).await.unwrap().items), [1]);
    let all = page(IncidentState::Any).await.unwrap();
    assert_eq!(ids(all.items), [1]);
    let rest = store
        .list_incidents(
            IncidentState::Any,
            &PageRequest::after(1, all.next_page_token.expect("a second page")),
        )
        .await
        .unwrap();
    assert_eq!((ids(rest.items), rest.next_page_token), (vec![2], None));
    assert_eq!(ids(store.open_incidents().await.unwrap()), [2]);

    let events = store.incident_events_after(0, i64::MAX, 10).await.unwrap();
    let summary: Vec<_> = events
        .iter()
        .map(|e| {
            (
                e.position,
                e.incident_id,
                e.kind,
                e.stored_at_ms,
                e.opened_at_ms,
            )
        })
        .collect();
    assert_eq!(
        summary,
        [
            (1, 1, IncidentEventKind::Opened, 2_000, 2_000),
            (2, 2, IncidentEventKind::Opened, 2_000, 2_000),
            (3, 2, IncidentEventKind::Joined, 3_000, 2_000),
            (4, 1, IncidentEventKind::Ended, 3_000, 2_000),
        ]
    );
    assert_eq!(events[2].body, json!({ "id": 2, "vehicles": 4 }));
    assert_eq!(
        store.incident_events_after(1, 3, 10).await.unwrap().len(),
        2
    );
    assert_eq!(store.latest_incident_position().await.unwrap(), 4);
}

async fn an_onset_keeps_where_it_started(store: Store) {
    let mut row = opened(5, &Onset::warning("car-5", "m", 10.0, 1_000, 0.9));
    row.place = StoredPlace {
        onset_latitude_deg: Some(32.25),
        onset_longitude_deg: Some(-110.5),
    };
    let event = AlarmEvent {
        seq: 5,
        kind: AlarmEventKind::Onset,
        alarm: row,
    };
    store.write_alarms(&[event]).await.unwrap();
    let logged = store
        .alarm_events_after(0, i64::MAX, None, 10)
        .await
        .unwrap();
    assert_eq!(logged[0].event.alarm.place.onset_latitude_deg, Some(32.25));
    assert_eq!(
        logged[0].event.alarm.place.onset_longitude_deg,
        Some(-110.5)
    );
}

/// An admin dismisses an open incident: the row records how, why and by whom with its end, one
/// ENDED event carries it, and the correlator (whose state still held it open) writes nothing more
/// to it. A second closure, of it or of one that ended on its own, changes nothing; an unknown id
/// is not found.
async fn an_incident_ended_by_hand_keeps_its_closure(store: Store) {
    store
        .claim_incident_correlator("a", 1_000, LEASE_MS)
        .await
        .unwrap();
    let opened = step(
        3,
        vec![
            write(1, Some(IncidentEventKind::Opened), false, 3),
            write(2, Some(IncidentEventKind::Opened), false, 3),
        ],
    );
    assert!(
        store
            .write_correlation_step("a", 2_000, &opened)
            .await
            .unwrap()
    );
    let closure = Closure {
        kind: ClosureKind::Dismissed,
        reason: "fabricated by two test tokens".into(),
        by: "token ops sha256:0123456789abcdef".into(),
    };
    let ended_body = json!({ "id": 1, "vehicles": 3, "ended": true });
    let outcome = store
        .close_incident(1, &closure, 5_000, |mut body| {
            body["ended"] = json!(true);
            Ok(body)
        })
        .await
        .unwrap();
    let CloseOutcome::Closed(row) = outcome else {
        panic!("the open incident is closed: {outcome:?}");
    };
    assert_eq!((row.ended_at_ms, &row.body), (Some(5_000), &ended_body));
    assert_eq!(row.closure.get(), Some(closure.clone()));
    assert_eq!(store.get_incident(1).await.unwrap(), Some(row.clone()));

    // The correlator's state still held it open: its later changes to it are not written.
    let late = step(
        5,
        vec![
            write(1, Some(IncidentEventKind::Joined), false, 4),
            write(2, Some(IncidentEventKind::Ended), true, 3),
        ],
    );
    assert!(
        store
            .write_correlation_step("a", 6_000, &late)
            .await
            .unwrap()
    );
    assert_eq!(store.get_incident(1).await.unwrap(), Some(row.clone()));
    assert_eq!(store.closed_incidents_among(1, 2).await.unwrap(), [1]);
    assert_eq!(store.closed_incidents_among(2, 9).await.unwrap(), [0i64; 0]);

    let again = Closure {
        kind: ClosureKind::Ended,
        reason: "over".into(),
        by: "admin token".into(),
    };
    let unchanged = |_: serde_json::Value| -> Result<serde_json::Value, crate::store::StoreError> {
        panic!("an ended incident's body is not edited")
    };
    assert_eq!(
        store
            .close_incident(1, &again, 7_000, unchanged)
            .await
            .unwrap(),
        CloseOutcome::AlreadyEnded(row.clone())
    );
    let CloseOutcome::AlreadyEnded(on_its_own) = store
        .close_incident(2, &again, 7_000, unchanged)
        .await
        .unwrap()
    else {
        panic!("incident 2 ended on its own");
    };
    assert_eq!(
        (on_its_own.ended_at_ms, on_its_own.closure.get()),
        (Some(6_000), None)
    );
    assert_eq!(
        store
            .close_incident(9, &again, 7_000, unchanged)
            .await
            .unwrap(),
        CloseOutcome::NotFound
    );

    let events = store.incident_events_after(0, i64::MAX, 10).await.unwrap();
    let summary: Vec<_> = events
        .iter()
        .map(|e| (e.incident_id, e.kind, e.stored_at_ms, e.closure.get()))
        .collect();
    assert_eq!(
        summary,
        [
            (1, IncidentEventKind::Opened, 2_000, Some(closure.clone())),
            (2, IncidentEventKind::Opened, 2_000, None),
            (1, IncidentEventKind::Ended, 5_000, Some(closure.clone())),
            (2, IncidentEventKind::Ended, 6_000, None),
        ],
        "the events read the incident's closure (the wire shows it on ENDED only)"
    );
    assert_eq!(events[2].body, ended_body);
    let open: Vec<i64> = store
        .open_incidents()
        .await
        .unwrap()
        .iter()
        .map(|r| r.id)
        .collect();
    assert!(open.is_empty(), "{open:?}");
    let ended = store
        .list_incidents(IncidentState::Ended, &PageRequest::first(10))
        .await
        .unwrap();
    assert_eq!(ended.items[0].closure.get(), Some(closure));
}

on_both_backends!(
    the_lease_has_one_holder_until_it_expires,
    a_step_stores_incidents_their_events_and_the_place_together,
    an_onset_keeps_where_it_started,
    an_incident_ended_by_hand_keeps_its_closure,
);

/// An incident stored before schema version 12 reads without a closure, and an admin can still
/// end it.
mod from_version_11 {
    use super::*;

    const OLD: [&str; 1] = [
        "INSERT INTO incidents (id, opened_at, ended_at, body_json) \
         VALUES (1, 1000, NULL, '{\"id\": 1}')",
    ];

    async fn check(store: Store) {
        let row = store.get_incident(1).await.unwrap().expect("stored");
        assert_eq!((row.ended_at_ms, row.closure.get()), (None, None));
        let closure = Closure {
            kind: ClosureKind::Ended,
            reason: "over".into(),
            by: "admin token".into(),
        };
        let outcome = store.close_incident(1, &closure, 2_000, Ok).await.unwrap();
        let CloseOutcome::Closed(row) = outcome else {
            panic!("closed: {outcome:?}");
        };
        assert_eq!(
            (row.ended_at_ms, row.closure.get()),
            (Some(2_000), Some(closure))
        );
    }

    from_schema_version!(11, sqlite: OLD, postgres: OLD);
}
