//! Stores what the shadow's worker decided, in its order: vehicle starts, would-be alarm onsets,
//! escalations and ends. A write the store refuses is logged and dropped (the counts say how many
//! alarms were stored; the vehicle's next start ends an alarm whose end was lost). It never blocks
//! the live path: the worker waits for it, and the queue sheds meanwhile.

use tokio::sync::mpsc;

use super::worker::Write;
use crate::store::{ShadowAlarmEnd, ShadowAlarmRow, Store, StoreError, now_unix_ms};

/// Stores every write until the worker is gone.
pub async fn store_writes(store: Store, mut pending: mpsc::Receiver<Write>) {
    while let Some(write) = pending.recv().await {
        if let Err(error) = apply(&store, &write).await {
            tracing::warn!(%error, ?write, "a shadow write was not stored");
        }
    }
}

async fn apply(store: &Store, write: &Write) -> Result<(), StoreError> {
    match write {
        Write::VehicleStarted {
            shadow_id,
            vehicle_id,
        } => store.shadow_vehicle_started(*shadow_id, vehicle_id).await,
        Write::Onset {
            shadow_id,
            model_id,
            vehicle_id,
            episode,
        } => {
            store
                .insert_shadow_alarm(&ShadowAlarmRow {
                    id: 0,
                    shadow_id: *shadow_id,
                    vehicle_id: vehicle_id.clone(),
                    model_id: model_id.clone(),
                    onset_timestamp_s: episode.onset_timestamp_s,
                    onset_at_ms: now_unix_ms(),
                    severity: if episode.critical {
                        "critical"
                    } else {
                        "warning"
                    }
                    .to_string(),
                    escalated_timestamp_s: episode.critical.then_some(episode.onset_timestamp_s),
                    peak_probability: episode.peak,
                    end_timestamp_s: None,
                    ended_at_ms: None,
                    end_reason: None,
                    live_alarmed: episode.live_alarmed,
                })
                .await
        }
        Write::Escalated {
            shadow_id,
            vehicle_id,
            onset_timestamp_s,
            timestamp_s,
        } => {
            store
                .escalate_shadow_alarm(*shadow_id, vehicle_id, *onset_timestamp_s, *timestamp_s)
                .await
        }
        Write::Ended {
            shadow_id,
            vehicle_id,
            episode,
            reason,
        } => {
            store
                .end_shadow_alarm(&ShadowAlarmEnd {
                    shadow_id: *shadow_id,
                    vehicle_id,
                    onset_timestamp_s: episode.onset_timestamp_s,
                    end_timestamp_s: episode.last_timestamp_s,
                    peak_probability: episode.peak,
                    live_alarmed: episode.live_alarmed,
                    reason,
                })
                .await
        }
    }
}
