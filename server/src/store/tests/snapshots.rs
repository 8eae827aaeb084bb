//! Session snapshots: one vehicle's read and many vehicles' in one query agree.

use crate::store::{AlarmEvent, SnapshotRow, Store};

/// A snapshot of `vehicle_id` whose encoding is its name (opaque to the store).
fn snapshot(vehicle_id: &str, samples: i64) -> SnapshotRow {
    SnapshotRow {
        vehicle_id: vehicle_id.to_string(),
        model_id: "m1".to_string(),
        schema_version: 5,
        samples,
        last_seq: samples,
        open_alarm_id: None,
        writer: "1".to_string(),
        updated_at_ms: 1_000 + samples,
        snapshot: vehicle_id.as_bytes().to_vec(),
    }
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

on_both_backends!(
    many_vehicles_are_read_in_one_query,
    a_burst_sized_batch_is_read_whole
);
