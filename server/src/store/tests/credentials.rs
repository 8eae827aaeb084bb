//! The credential behind each alarm in the store: written with the onset, read back by the
//! listings and the event log (which the incident correlator reads), unchanged by the alarm's
//! escalation or end; alarms stored before schema version 11 read without one.

use super::alarms::{end, onset};
use crate::store::{AlarmEvent, AlarmFilter, PageRequest, Store, StoredCredential};

fn gateway() -> StoredCredential {
    StoredCredential {
        credential: Some("token bridge sha256:0123456789abcdef".to_string()),
        credential_per_vehicle: true,
    }
}

/// The onset of alarm `id` for `vehicle`, sent with `credential`.
fn onset_with(id: i64, vehicle: &str, credential: StoredCredential) -> AlarmEvent {
    let mut event = onset(id, vehicle, 100.0, 0.9);
    event.alarm.credential = credential;
    event
}

async fn an_alarm_keeps_the_credential_of_its_onset(store: Store) {
    let admin = StoredCredential {
        credential: Some("admin token".to_string()),
        credential_per_vehicle: false,
    };
    store
        .write_alarms(&[
            onset_with(1, "gw-1", gateway()),
            onset_with(2, "car-2", admin.clone()),
        ])
        .await
        .unwrap();
    // The end is built from a copy that knows no credential: the stored one stays.
    store
        .write_alarms(&[end(1, 130.0, 0.95, 31)])
        .await
        .unwrap();
    let listed = store
        .list_alarms(&AlarmFilter::default(), &PageRequest::first(10))
        .await
        .unwrap()
        .items;
    let credentials: Vec<_> = listed.iter().map(|a| a.credential.clone()).collect();
    assert_eq!(credentials, [gateway(), admin.clone()]);
    let logged = store
        .alarm_events_after(0, i64::MAX, None, 10)
        .await
        .unwrap();
    let logged: Vec<_> = logged
        .iter()
        .map(|e| (e.event.alarm.id, e.event.alarm.credential.clone()))
        .collect();
    assert_eq!(logged, [(1, gateway()), (2, admin), (1, gateway())]);
}

on_both_backends!(an_alarm_keeps_the_credential_of_its_onset);

mod from_version_10 {
    use super::*;

    const OLD: [&str; 2] = [
        "INSERT INTO alarm_events (id, vehicle_id, model_id, onset_timestamp_s, onset_at, \
         ended_at, peak_probability, samples) VALUES (1, 'car-1', 'm', 10.0, 1001, NULL, 0.9, 1)",
        "INSERT INTO alarm_event_log (position, seq, alarm_id, kind, ended_at, peak_probability, \
         samples) VALUES (1, 1, 1, 'onset', NULL, 0.9, 1)",
    ];

    async fn check(store: Store) {
        let logged = store
            .alarm_events_after(0, i64::MAX, None, 10)
            .await
            .unwrap();
        assert_eq!(
            logged[0].event.alarm.credential,
            StoredCredential::default()
        );
        store
            .write_alarms(&[onset_with(2, "gw-2", gateway())])
            .await
            .unwrap();
        let listed = store.list_alarm_events(None, 10).await.unwrap();
        let credentials: Vec<_> = listed
            .iter()
            .map(|a| (a.id, a.credential.clone()))
            .collect();
        assert_eq!(
            credentials,
            [(2, gateway()), (1, StoredCredential::default())]
        );
    }

    from_schema_version!(10, sqlite: OLD, postgres: OLD);
}
