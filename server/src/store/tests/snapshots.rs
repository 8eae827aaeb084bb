//! Session snapshots: one vehicle's read and many vehicles' in one query agree; two copies of a
//! session that another process replaced, stored in either order, end its alarm at the copy that
//! got furthest, and the replacement's snapshot stays; an expired snapshot gives back the alarm it
//! held open, whole, and one whose alarm cannot be read blocks no other.

use super::alarms::{end, onset};
use crate::store::{AlarmEvent, AlarmEventRow, SnapshotRow, Store, StoredPlace, StoredWhy};

fn snapshot(vehicle_id: &str, samples: i64) -> SnapshotRow {
    SnapshotRow::opaque(vehicle_id, samples)
}

async fn many_vehicles_are_read_in_one_query(store: Store) {
    let stored = [
        snapshot("car-1", 10),
        snapshot("car-2", 20),
        snapshot("car-3", 30),
    ];
    store
        .write_alarms_and_snapshots::<AlarmEvent>(&[], &stored)
        .await
        .unwrap();
    let mut read = store
        .load_snapshots(&["car-3", "car-1", "car-9"])
        .await
        .unwrap();
    read.sort_by(|a, b| a.vehicle_id.cmp(&b.vehicle_id));
    assert_eq!(read, vec![stored[0].clone(), stored[2].clone()]);
    for row in &stored {
        let one = store.load_snapshot(&row.vehicle_id).await.unwrap();
        assert_eq!(one.as_ref(), Some(row));
    }
    assert_eq!(store.load_snapshots(&[]).await.unwrap(), vec![]);
    assert_eq!(store.load_snapshots(&["car-9"]).await.unwrap(), vec![]);
}

/// Hundreds of vehicles in one query (a burst of failovers) are all found.
async fn a_burst_sized_batch_is_read_whole(store: Store) {
    let stored: Vec<SnapshotRow> = (0..600).map(|i| snapshot(&format!("car-{i}"), i)).collect();
    store
        .write_alarms_and_snapshots::<AlarmEvent>(&[], &stored)
        .await
        .unwrap();
    let ids: Vec<&str> = stored.iter().map(|row| row.vehicle_id.as_str()).collect();
    let read = store.load_snapshots(&ids).await.unwrap();
    assert_eq!(read.len(), 600);
}

/// Writer `writer`'s copy of car-7's session under model m1, holding alarm 7 open, its latest
/// alarming sample at `last` s (peak and samples grow with it).
fn copy_holding_alarm_7(writer: &str, last: f64) -> SnapshotRow {
    SnapshotRow {
        open_alarm_id: Some(7),
        open_alarm_last_timestamp_s: Some(last),
        open_alarm_peak_probability: Some(last / 200.0),
        open_alarm_samples: Some(last as i64 - 99),
        writer: writer.to_string(),
        ..snapshot("car-7", last as i64)
    }
}

/// The session that replaced it on writer "1": another model, no alarm.
fn replacement() -> SnapshotRow {
    SnapshotRow {
        model_id: "m2".to_string(),
        writer: "1".to_string(),
        ..snapshot("car-7", 0)
    }
}

/// Alarm 7 as stored: (end time, peak, samples).
async fn alarm_7(store: &Store) -> (Option<f64>, f64, i64) {
    let rows: Vec<AlarmEventRow> = store.list_alarm_events(Some("car-7"), 1).await.unwrap();
    (
        rows[0].end_timestamp_s,
        rows[0].peak_probability,
        rows[0].samples,
    )
}

/// The end times the event log holds for alarm 7, in log order.
async fn logged_ends_of_alarm_7(store: &Store) -> Vec<Option<f64>> {
    let logged = store
        .alarm_events_after(0, i64::MAX, Some("car-7"), 10)
        .await
        .unwrap();
    logged
        .iter()
        .skip(1)
        .map(|e| e.event.alarm.end_timestamp_s)
        .collect()
}

/// Alarm 7's onset, and process "2"'s copy of the session at 150 s.
async fn alarm_7_opened_and_its_copy_stored_at_150(store: &Store) {
    store
        .write_alarms_and_snapshots(
            &[onset(7, "car-7", 100.0, 0.5)],
            &[copy_holding_alarm_7("2", 150.0)],
        )
        .await
        .unwrap();
}

/// Process "1" replaces the session from the copy at 150 s: it ends alarm 7 there and stores its
/// own session; both are taken.
async fn replaced_from_the_copy_at_150(store: &Store) {
    let refused = store
        .write_alarms_and_snapshots(&[end(7, 150.0, 0.75, 51)], &[replacement()])
        .await
        .unwrap();
    assert_eq!(refused, Vec::<usize>::new());
}

/// Process "1" replaces car-7's session (a roll-out) from the copy stored at 150 s and ends its
/// alarm there; process "2", which held the session, stores its copy at 170 s afterwards.
async fn a_later_copy_of_a_replaced_session_moves_its_alarms_end_on(store: Store) {
    alarm_7_opened_and_its_copy_stored_at_150(&store).await;
    replaced_from_the_copy_at_150(&store).await;
    assert_eq!(alarm_7(&store).await, (Some(150.0), 0.75, 51));

    // The later copy is not stored over the replacement, and is reported.
    let later = copy_holding_alarm_7("2", 170.0);
    let refused = store
        .write_alarms_and_snapshots::<AlarmEvent>(&[], &[later])
        .await
        .unwrap();
    assert_eq!(refused, vec![0]);
    assert_eq!(
        store.load_snapshot("car-7").await.unwrap(),
        Some(replacement())
    );

    // Its writer ends the alarm at the copy's progress: the end moves on, and is logged.
    let mut its_end = end(7, 170.0, 0.85, 71);
    its_end.seq += 1;
    store.write_alarms(&[its_end.clone()]).await.unwrap();
    assert_eq!(alarm_7(&store).await, (Some(170.0), 0.85, 71));
    // A retry, an earlier end, or one without a sample time changes nothing.
    let mut earlier = end(7, 160.0, 0.8, 61);
    earlier.seq += 2;
    let mut untimed = end(7, 0.0, 0.5, 1);
    untimed.seq += 3;
    untimed.alarm.end_timestamp_s = None;
    store
        .write_alarms(&[its_end, earlier, untimed])
        .await
        .unwrap();
    assert_eq!(alarm_7(&store).await, (Some(170.0), 0.85, 71));
    assert_eq!(
        logged_ends_of_alarm_7(&store).await,
        [Some(150.0), Some(170.0)]
    );
}

/// Process "2" stores its copy at 170 s before process "1", which read the copy at 150 s, ends the
/// alarm and replaces the session: the end is the stored copy's.
async fn an_end_from_a_lagging_copy_takes_the_stored_copys_progress(store: Store) {
    alarm_7_opened_and_its_copy_stored_at_150(&store).await;
    store
        .write_alarms_and_snapshots::<AlarmEvent>(&[], &[copy_holding_alarm_7("2", 170.0)])
        .await
        .unwrap();
    replaced_from_the_copy_at_150(&store).await;
    assert_eq!(alarm_7(&store).await, (Some(170.0), 0.85, 71));
    assert_eq!(logged_ends_of_alarm_7(&store).await, [Some(170.0)]);
    assert_eq!(
        store.load_snapshot("car-7").await.unwrap(),
        Some(replacement())
    );
}

/// A session's own copy holding its alarm open is stored even after that alarm ended (a snapshot
/// taken before the end, stored in a later batch): it replaces nothing of another session.
async fn a_sessions_own_older_copy_is_stored_after_its_alarm_ended(store: Store) {
    alarm_7_opened_and_its_copy_stored_at_150(&store).await;
    store.write_alarms(&[end(7, 180.0, 0.9, 81)]).await.unwrap();
    let own = copy_holding_alarm_7("2", 170.0);
    let refused = store
        .write_alarms_and_snapshots::<AlarmEvent>(&[], std::slice::from_ref(&own))
        .await
        .unwrap();
    assert_eq!(refused, Vec::<usize>::new());
    assert_eq!(store.load_snapshot("car-7").await.unwrap(), Some(own));
    assert_eq!(alarm_7(&store).await, (Some(180.0), 0.9, 81));
}

/// Alarm 7's onset as the server stores it (with its explanation and place), and car-7's copy
/// holding it open; car-8's snapshot holds no alarm.
async fn alarm_7_held_by_an_abandoned_snapshot(store: &Store) -> AlarmEventRow {
    let mut opened = onset(7, "car-7", 100.0, 0.5);
    opened.alarm.why = StoredWhy {
        why_kind: Some("jump".to_string()),
        why_offset_east_m: Some(120.0),
        why_offset_north_m: Some(-35.0),
        why_drift_east_mps: Some(0.0),
        why_drift_north_mps: Some(0.0),
    };
    opened.alarm.place = StoredPlace {
        onset_latitude_deg: Some(32.23),
        onset_longitude_deg: Some(-110.91),
    };
    store
        .write_alarms_and_snapshots(
            std::slice::from_ref(&opened),
            &[copy_holding_alarm_7("2", 150.0), snapshot("car-8", 5)],
        )
        .await
        .unwrap();
    opened.alarm
}

/// The TTL passed for every stored snapshot: each version as stored, by vehicle.
async fn every_snapshot_is_stale(store: &Store) -> Vec<(String, i64)> {
    let mut stale = store.stale_snapshots(i64::MAX).await.unwrap();
    stale.sort();
    stale
}

async fn an_expired_snapshot_gives_back_the_alarm_it_held_open_and_goes(store: Store) {
    let opened = alarm_7_held_by_an_abandoned_snapshot(&store).await;
    let stale = every_snapshot_is_stale(&store).await;
    assert_eq!(stale.len(), 2);
    // car-8's snapshot was rewritten since it was found stale: that version is gone, the new
    // one stays.
    let rewritten = (stale[1].0.clone(), stale[1].1 - 1);
    let expired = store
        .expire_snapshots(&[stale[0].clone(), rewritten])
        .await
        .unwrap();
    assert_eq!(expired.unreadable, vec![]);
    assert_eq!(expired.abandoned, vec![(opened, b"car-7".to_vec())]);
    assert_eq!(store.load_snapshot("car-7").await.unwrap(), None);
    assert_eq!(
        store.load_snapshot("car-8").await.unwrap(),
        Some(snapshot("car-8", 5))
    );
}

on_both_backends!(
    an_expired_snapshot_gives_back_the_alarm_it_held_open_and_goes,
    many_vehicles_are_read_in_one_query,
    a_burst_sized_batch_is_read_whole,
    a_later_copy_of_a_replaced_session_moves_its_alarms_end_on,
    an_end_from_a_lagging_copy_takes_the_stored_copys_progress,
    a_sessions_own_older_copy_is_stored_after_its_alarm_ended
);

/// A snapshot whose alarm row cannot be decoded (a value of the wrong type, which only SQLite can
/// hold) stays, reported, and the others in its batch expire.
#[tokio::test]
async fn an_unreadable_alarm_blocks_no_other_expiry() {
    let (_dir, store) = super::temp_store().await;
    let opened = alarm_7_held_by_an_abandoned_snapshot(&store).await;
    let broken = SnapshotRow {
        open_alarm_id: Some(9),
        ..snapshot("car-9", 9)
    };
    store
        .write_alarms_and_snapshots(
            &[onset(9, "car-9", 10.0, 0.5)],
            std::slice::from_ref(&broken),
        )
        .await
        .unwrap();
    store
        .execute_for_test("UPDATE alarm_events SET peak_probability = 'high' WHERE id = 9")
        .await;
    let stale = every_snapshot_is_stale(&store).await;
    let expired = store.expire_snapshots(&stale).await.unwrap();
    assert_eq!(expired.abandoned, vec![(opened, b"car-7".to_vec())]);
    let [(version, reason)] = expired.unreadable.as_slice() else {
        panic!("one unreadable version: {:?}", expired.unreadable);
    };
    assert_eq!(version, &("car-9".to_string(), broken.updated_at_ms));
    assert!(reason.contains("peak_probability"), "{reason}");
    assert_eq!(store.load_snapshot("car-8").await.unwrap(), None);
    assert_eq!(store.load_snapshot("car-9").await.unwrap(), Some(broken));
}
