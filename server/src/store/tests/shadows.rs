//! Shadows in the store: one runs at a time, a stop is kept once and ends the open would-be
//! alarms, each process's counts are replaced whole, a vehicle's later starts are counted and end
//! what an earlier copy of its state left open, and would-be alarms list newest first by page.

use serde_json::json;

use crate::store::{ShadowAlarmEnd, ShadowAlarmRow, ShadowStart, Store};

fn alarm(shadow_id: i64, vehicle: &str, onset_timestamp_s: f64) -> ShadowAlarmRow {
    ShadowAlarmRow {
        id: 0,
        shadow_id,
        vehicle_id: vehicle.to_string(),
        model_id: "cand".to_string(),
        onset_timestamp_s,
        onset_at_ms: 1_000,
        severity: "warning".to_string(),
        escalated_timestamp_s: None,
        peak_probability: 0.8,
        end_timestamp_s: None,
        ended_at_ms: None,
        end_reason: None,
        live_alarmed: false,
    }
}

async fn started(store: &Store, model: &str) -> ShadowStart {
    store
        .start_shadow(model, &json!({"kind": "all"}), "admin token")
        .await
        .unwrap()
}

async fn one_shadow_runs_at_a_time_and_a_stop_is_kept_once(store: Store) {
    assert_eq!(store.running_shadow().await.unwrap(), None);
    assert_eq!(store.get_shadow(None).await.unwrap(), None);
    let ShadowStart::Started(first) = started(&store, "cand").await else {
        panic!("the first shadow starts");
    };
    assert_eq!(first.scope_json.0, json!({"kind": "all"}));
    let ShadowStart::AlreadyRunning(running) = started(&store, "other").await else {
        panic!("a second shadow is refused while one runs");
    };
    assert_eq!(running.id, first.id);
    assert_eq!(store.running_shadow().await.unwrap(), Some(first.clone()));

    store
        .insert_shadow_alarm(&alarm(first.id, "car", 10.0))
        .await
        .unwrap();
    let stopped = store.stop_shadow(first.id, "ops").await.unwrap().unwrap();
    assert_eq!(stopped.stopped_by.as_deref(), Some("ops"));
    let again = store
        .stop_shadow(first.id, "someone else")
        .await
        .unwrap()
        .unwrap();
    assert_eq!(again, stopped, "the first stop is kept");
    let listed = store
        .list_shadow_alarms(first.id, None, None, 10)
        .await
        .unwrap();
    assert_eq!(listed[0].end_reason.as_deref(), Some("stopped"));
    assert_eq!(
        store.stop_shadow(first.id + 100, "ops").await.unwrap(),
        None
    );

    let ShadowStart::Started(second) = started(&store, "other").await else {
        panic!("a new shadow starts once the first stopped");
    };
    assert!(second.id > first.id);
    assert_eq!(store.get_shadow(None).await.unwrap(), Some(second.clone()));
    assert_eq!(
        store.get_shadow(Some(first.id)).await.unwrap(),
        Some(stopped)
    );
}

async fn counts_vehicles_and_would_be_alarms_are_kept_per_shadow(store: Store) {
    let ShadowStart::Started(shadow) = started(&store, "cand").await else {
        panic!("starts");
    };
    let id = shadow.id;
    store
        .put_shadow_tally(id, "a/1", &json!({"samples_scored": 5}))
        .await
        .unwrap();
    store
        .put_shadow_tally(id, "a/1", &json!({"samples_scored": 7}))
        .await
        .unwrap();
    store
        .put_shadow_tally(id, "b/1", &json!({"samples_scored": 1}))
        .await
        .unwrap();
    assert_eq!(
        store.shadow_tallies(id).await.unwrap(),
        vec![json!({"samples_scored": 7}), json!({"samples_scored": 1})]
    );

    // The vehicle's state starts, raises a would-be alarm, and starts again elsewhere: the alarm
    // the lost state held open ends as `restarted`.
    store.shadow_vehicles_started(id, &["car"]).await.unwrap();
    store
        .insert_shadow_alarm(&alarm(id, "car", 10.0))
        .await
        .unwrap();
    store
        .insert_shadow_alarm(&alarm(id, "car", 10.0))
        .await
        .unwrap();
    store
        .escalate_shadow_alarm(id, "car", 10.0, 12.0)
        .await
        .unwrap();
    store
        .shadow_vehicles_started(id, &["car", "van"])
        .await
        .unwrap();
    assert_eq!(store.shadow_counts(id).await.unwrap(), (2, 3, 1));
    let row = &store
        .list_shadow_alarms(id, Some("car"), None, 10)
        .await
        .unwrap()[0];
    assert_eq!(row.severity, "critical");
    assert_eq!(row.escalated_timestamp_s, Some(12.0));
    assert_eq!(row.end_reason.as_deref(), Some("restarted"));

    // A later end keeps the first.
    let end = |reason| ShadowAlarmEnd {
        shadow_id: id,
        vehicle_id: "van",
        onset_timestamp_s: 20.0,
        end_timestamp_s: 25.0,
        peak_probability: 0.95,
        live_alarmed: true,
        reason,
    };
    store
        .insert_shadow_alarm(&alarm(id, "van", 20.0))
        .await
        .unwrap();
    store.end_shadow_alarm(&end("cleared")).await.unwrap();
    store.end_shadow_alarm(&end("idle")).await.unwrap();
    let van = &store
        .list_shadow_alarms(id, Some("van"), None, 10)
        .await
        .unwrap()[0];
    assert_eq!(
        (
            van.end_timestamp_s,
            van.end_reason.as_deref(),
            van.live_alarmed,
            van.peak_probability
        ),
        (Some(25.0), Some("cleared"), true, 0.95)
    );

    // Pages, newest first.
    for t in 0..3 {
        store
            .insert_shadow_alarm(&alarm(id, "bus", f64::from(t)))
            .await
            .unwrap();
    }
    let page = store.list_shadow_alarms(id, None, None, 2).await.unwrap();
    assert_eq!(page.len(), 2);
    assert!(page[0].id > page[1].id);
    let rest = store
        .list_shadow_alarms(id, None, Some(page[1].id), 10)
        .await
        .unwrap();
    assert_eq!(rest.len(), 3);
    assert!(rest.iter().all(|r| r.id < page[1].id));
    assert!(
        store
            .list_shadow_alarms(id + 1, None, None, 10)
            .await
            .unwrap()
            .is_empty()
    );
}

on_both_backends!(
    one_shadow_runs_at_a_time_and_a_stop_is_kept_once,
    counts_vehicles_and_would_be_alarms_are_kept_per_shadow,
);
