//! Stores what the shadow's worker decided, in its order: vehicle starts, would-be alarm onsets,
//! escalations and ends. A write the store refuses is logged and dropped (the counts say how many
//! alarms were stored; the vehicle's next start ends an alarm whose end was lost). It never blocks
//! the live path: the worker waits for it, and the queue sheds meanwhile.
//!
//! The vehicle starts waiting together are stored in one transaction: a shadow started on a large
//! fleet starts every vehicle within its first second, and one write transaction each would hold
//! the database's write lock against the live path's writers (alarms, session snapshots) for that
//! long.

use tokio::sync::mpsc;

use super::worker::Write;
use crate::store::{ShadowAlarmEnd, ShadowAlarmRow, Store, StoreError, now_unix_ms};

/// Most writes taken from the worker at once (their vehicle starts share one transaction).
const BATCH: usize = 512;

/// Stores every write until the worker is gone.
pub async fn store_writes(store: Store, mut pending: mpsc::Receiver<Write>) {
    let mut batch = Vec::with_capacity(BATCH);
    while pending.recv_many(&mut batch, BATCH).await > 0 {
        for run in runs(&batch) {
            if let Err(error) = run.apply(&store).await {
                tracing::warn!(%error, write = ?run, "a shadow write was not stored");
            }
        }
        batch.clear();
    }
}

/// Writes as they are stored: consecutive vehicle starts of one shadow together, the others one
/// by one, in the worker's order.
#[derive(Debug)]
enum Run<'a> {
    Started {
        shadow_id: i64,
        vehicle_ids: Vec<&'a str>,
    },
    One(&'a Write),
}

fn runs(writes: &[Write]) -> Vec<Run<'_>> {
    let mut runs: Vec<Run<'_>> = Vec::new();
    for write in writes {
        match (write, runs.last_mut()) {
            (
                Write::VehicleStarted {
                    shadow_id,
                    vehicle_id,
                },
                Some(Run::Started {
                    shadow_id: last,
                    vehicle_ids,
                }),
            ) if shadow_id == last => vehicle_ids.push(vehicle_id),
            (
                Write::VehicleStarted {
                    shadow_id,
                    vehicle_id,
                },
                _,
            ) => runs.push(Run::Started {
                shadow_id: *shadow_id,
                vehicle_ids: vec![vehicle_id],
            }),
            (other, _) => runs.push(Run::One(other)),
        }
    }
    runs
}

impl Run<'_> {
    async fn apply(&self, store: &Store) -> Result<(), StoreError> {
        match self {
            Run::Started {
                shadow_id,
                vehicle_ids,
            } => store.shadow_vehicles_started(*shadow_id, vehicle_ids).await,
            Run::One(write) => apply(store, write).await,
        }
    }
}

async fn apply(store: &Store, write: &Write) -> Result<(), StoreError> {
    match write {
        Write::VehicleStarted {
            shadow_id,
            vehicle_id,
        } => {
            store
                .shadow_vehicles_started(*shadow_id, &[vehicle_id.as_str()])
                .await
        }
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

#[cfg(test)]
mod tests {
    use super::*;

    fn started(shadow_id: i64, vehicle_id: &str) -> Write {
        Write::VehicleStarted {
            shadow_id,
            vehicle_id: vehicle_id.to_string(),
        }
    }

    fn shape(runs: &[Run<'_>]) -> Vec<String> {
        runs.iter()
            .map(|run| match run {
                Run::Started {
                    shadow_id,
                    vehicle_ids,
                } => format!("{shadow_id}:{}", vehicle_ids.join(",")),
                Run::One(_) => "one".to_string(),
            })
            .collect()
    }

    #[test]
    fn consecutive_starts_of_one_shadow_are_stored_together_and_the_order_is_kept() {
        let escalated = Write::Escalated {
            shadow_id: 1,
            vehicle_id: "b".to_string(),
            onset_timestamp_s: 1.0,
            timestamp_s: 2.0,
        };
        let writes = [
            started(1, "a"),
            started(1, "b"),
            started(1, "a"),
            escalated,
            started(1, "c"),
            started(2, "c"),
        ];
        assert_eq!(
            shape(&runs(&writes)),
            ["1:a,b,a", "one", "1:c", "2:c"],
            "a start after another write is not moved before it; another shadow's starts apart"
        );
        assert!(runs(&[]).is_empty());
    }
}
