//! Session snapshots: the latest detection state of each vehicle's session, written by the session
//! outbox (in the same transactions as the alarm events that preceded it, see `super::outbox`) and
//! read when a stream for the vehicle starts on any server process.
//!
//! It owns the snapshot table; the alarm rows it returns are `super::alarms`'s, and it must not
//! write alarm events.

use super::alarms::AlarmEventRow;
use super::{Store, StoreError};

/// A stored session snapshot. `snapshot` is opaque here (the detection layer encodes it).
#[derive(Debug, Clone, PartialEq, sqlx::FromRow)]
pub struct SnapshotRow {
    /// The vehicle whose session it is.
    pub vehicle_id: String,
    /// The model the session ran.
    pub model_id: String,
    /// The encoding's schema version.
    pub schema_version: i64,
    /// Samples the session had processed.
    pub samples: i64,
    /// The last batch sequence number the session accepted.
    pub last_seq: i64,
    /// The alarm the session holds open, if any.
    pub open_alarm_id: Option<i64>,
    /// How far the session got on that alarm: its latest alarming sample's time, peak probability
    /// and samples. The alarm's end is taken from the copy of the session that got furthest.
    pub open_alarm_last_timestamp_s: Option<f64>,
    pub open_alarm_peak_probability: Option<f64>,
    pub open_alarm_samples: Option<i64>,
    /// The server process that wrote it.
    pub writer: String,
    /// When it was written, unix epoch milliseconds.
    #[sqlx(rename = "updated_at")]
    pub updated_at_ms: i64,
    /// The encoded state.
    pub snapshot: Vec<u8>,
}

#[cfg(test)]
impl SnapshotRow {
    /// A snapshot of `vehicle_id` by writer "1" under model "m1" that holds no alarm open, whose
    /// encoding is the vehicle's name (opaque to the store).
    pub fn opaque(vehicle_id: &str, samples: i64) -> Self {
        Self {
            vehicle_id: vehicle_id.to_string(),
            model_id: "m1".to_string(),
            schema_version: 5,
            samples,
            last_seq: samples,
            open_alarm_id: None,
            open_alarm_last_timestamp_s: None,
            open_alarm_peak_probability: None,
            open_alarm_samples: None,
            writer: "1".to_string(),
            updated_at_ms: 1_000 + samples,
            snapshot: vehicle_id.as_bytes().to_vec(),
        }
    }
}

/// Stores `$row` (a `&SnapshotRow`) as its vehicle's latest snapshot inside the write transaction
/// `$tx` (the joint write of `super::outbox`); evaluates to whether it was stored.
///
/// It is not stored over a snapshot of another session of the vehicle when it holds open an alarm
/// that has ended: it is then a copy of a session that another process replaced (a roll-out),
/// ending that alarm from the copy it read, and the replacement's snapshot must stay. The caller
/// ends the alarm at this copy's progress, which may be further than the copy the other process
/// read (`apply_event!` keeps the furthest end).
macro_rules! upsert_snapshot {
    ($tx:ident, $row:expr) => {{
        let row: &SnapshotRow = $row;
        sqlx::query(
            "INSERT INTO session_snapshots (vehicle_id, model_id, schema_version, samples, \
             last_seq, open_alarm_id, open_alarm_last_timestamp_s, open_alarm_peak_probability, \
             open_alarm_samples, writer, updated_at, snapshot) \
             VALUES ($1, $2, $3, $4, $5, $6, $7, $8, $9, $10, $11, $12) \
             ON CONFLICT (vehicle_id) DO UPDATE SET model_id = excluded.model_id, \
             schema_version = excluded.schema_version, samples = excluded.samples, \
             last_seq = excluded.last_seq, open_alarm_id = excluded.open_alarm_id, \
             open_alarm_last_timestamp_s = excluded.open_alarm_last_timestamp_s, \
             open_alarm_peak_probability = excluded.open_alarm_peak_probability, \
             open_alarm_samples = excluded.open_alarm_samples, \
             writer = excluded.writer, updated_at = excluded.updated_at, \
             snapshot = excluded.snapshot \
             WHERE excluded.open_alarm_id IS NULL \
             OR session_snapshots.open_alarm_id = excluded.open_alarm_id \
             OR NOT EXISTS (SELECT 1 FROM alarm_events a \
                            WHERE a.id = excluded.open_alarm_id AND a.ended_at IS NOT NULL)",
        )
        .bind(&row.vehicle_id)
        .bind(&row.model_id)
        .bind(row.schema_version)
        .bind(row.samples)
        .bind(row.last_seq)
        .bind(row.open_alarm_id)
        .bind(row.open_alarm_last_timestamp_s)
        .bind(row.open_alarm_peak_probability)
        .bind(row.open_alarm_samples)
        .bind(&row.writer)
        .bind(row.updated_at_ms)
        .bind(&row.snapshot)
        .execute(&mut *$tx)
        .await?
        .rows_affected()
            > 0
    }};
}
pub(super) use upsert_snapshot;

impl Store {
    /// The latest snapshot of `vehicle_id`'s session, if one is stored.
    pub async fn load_snapshot(&self, vehicle_id: &str) -> Result<Option<SnapshotRow>, StoreError> {
        Ok(self.load_snapshots(&[vehicle_id]).await?.pop())
    }

    /// The latest snapshots of these vehicles, those that have one, in any order: one query for
    /// many vehicles (a burst of streams failing over at once).
    pub async fn load_snapshots(
        &self,
        vehicle_ids: &[&str],
    ) -> Result<Vec<SnapshotRow>, StoreError> {
        if vehicle_ids.is_empty() {
            return Ok(Vec::new());
        }
        Ok(on_pool!(self, |pool| {
            let mut query = sqlx::QueryBuilder::new(
                "SELECT vehicle_id, model_id, schema_version, samples, last_seq, open_alarm_id, \
                 open_alarm_last_timestamp_s, open_alarm_peak_probability, open_alarm_samples, \
                 writer, updated_at, snapshot FROM session_snapshots WHERE vehicle_id IN (",
            );
            let mut ids = query.separated(", ");
            for id in vehicle_ids {
                ids.push_bind(*id);
            }
            query.push(")");
            query
                .build_query_as::<SnapshotRow>()
                .fetch_all(pool)
                .await?
        }))
    }

    /// Deletes the snapshots of sessions that ran `model_id` (the model was deleted); returns how
    /// many.
    pub async fn delete_snapshots_of_model(&self, model_id: &str) -> Result<u64, StoreError> {
        Ok(on_pool!(self, |pool| {
            sqlx::query("DELETE FROM session_snapshots WHERE model_id = $1")
                .bind(model_id)
                .execute(pool)
                .await?
                .rows_affected()
        }))
    }

    /// The snapshots written before `cutoff_ms` by their writers' clocks, as (vehicle, written
    /// at): candidates for expiry, which the caller confirms by its own clock first.
    pub async fn stale_snapshots(&self, cutoff_ms: i64) -> Result<Vec<(String, i64)>, StoreError> {
        Ok(on_pool!(self, |pool| {
            sqlx::query_as::<_, (String, i64)>(
                "SELECT vehicle_id, updated_at FROM session_snapshots WHERE updated_at < $1",
            )
            .bind(cutoff_ms)
            .fetch_all(pool)
            .await?
        }))
    }

    /// Deletes exactly these snapshot versions, (vehicle, written at): one rewritten since is
    /// kept. Returns the alarms they held open, still open, each with its snapshot (the caller
    /// ends them at their last alarming sample).
    pub async fn expire_snapshots(
        &self,
        versions: &[(String, i64)],
    ) -> Result<Vec<(AlarmEventRow, Vec<u8>)>, StoreError> {
        in_write_tx!(self, |tx| {
            let mut abandoned = Vec::new();
            for (vehicle_id, updated_at) in versions {
                let held = sqlx::query_as::<_, AlarmEventRow>(
                    "SELECT a.id, a.vehicle_id, a.model_id, a.onset_timestamp_s, \
                     a.end_timestamp_s, a.onset_at, a.ended_at, a.peak_probability, a.samples, \
                     a.why_kind, a.why_offset_east_m, a.why_offset_north_m, a.why_drift_east_mps, \
                     a.why_drift_north_mps \
                     FROM session_snapshots s JOIN alarm_events a ON a.id = s.open_alarm_id \
                     WHERE s.vehicle_id = $1 AND s.updated_at = $2 AND a.ended_at IS NULL",
                )
                .bind(vehicle_id)
                .bind(updated_at)
                .fetch_optional(&mut *tx)
                .await?;
                let deleted = sqlx::query_scalar::<_, Vec<u8>>(
                    "DELETE FROM session_snapshots WHERE vehicle_id = $1 AND updated_at = $2 \
                     RETURNING snapshot",
                )
                .bind(vehicle_id)
                .bind(updated_at)
                .fetch_optional(&mut *tx)
                .await?;
                if let (Some(alarm), Some(snapshot)) = (held, deleted) {
                    abandoned.push((alarm, snapshot));
                }
            }
            tx.commit().await?;
            Ok(abandoned)
        })
    }
}
