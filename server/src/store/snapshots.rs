//! Session snapshots: the latest detection state of each vehicle's session, written by the session
//! outbox (in the same transactions as the alarm events that preceded it, see `super::outbox`) and
//! read when a stream for the vehicle starts on any server process.
//!
//! It owns the snapshot table; the alarm rows it returns are `super::alarms`'s, and it must not
//! write alarm events.

use sqlx::Acquire;

use super::alarms::{AlarmEventRow, select_alarms};
use super::error::is_row_error;
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
    /// ends them at their last alarming sample), and the versions whose rows could not be read.
    ///
    /// Each version is expired in a savepoint of its own, so a row that cannot be decoded is left
    /// in place and reported while the others go; a database fault still fails the whole call
    /// (nothing is deleted, and the caller retries later).
    pub async fn expire_snapshots(
        &self,
        versions: &[(String, i64)],
    ) -> Result<ExpiredSnapshots, StoreError> {
        in_write_tx!(self, |tx| {
            let mut expired = ExpiredSnapshots::default();
            for version in versions {
                let (vehicle_id, updated_at) = version;
                // A savepoint: a version that cannot be read is rolled back alone.
                let mut one = Acquire::begin(&mut tx).await?;
                let attempt: Result<_, sqlx::Error> = async {
                    let open_alarm_id: Option<Option<i64>> = sqlx::query_scalar(
                        "SELECT open_alarm_id FROM session_snapshots \
                         WHERE vehicle_id = $1 AND updated_at = $2",
                    )
                    .bind(vehicle_id)
                    .bind(updated_at)
                    .fetch_optional(&mut *one)
                    .await?;
                    let held = match open_alarm_id.flatten() {
                        Some(id) => {
                            sqlx::query_as::<_, AlarmEventRow>(select_alarms!(
                                "WHERE id = $1 AND ended_at IS NULL"
                            ))
                            .bind(id)
                            .fetch_optional(&mut *one)
                            .await?
                        }
                        None => None,
                    };
                    let deleted = sqlx::query_scalar::<_, Vec<u8>>(
                        "DELETE FROM session_snapshots WHERE vehicle_id = $1 AND updated_at = $2 \
                         RETURNING snapshot",
                    )
                    .bind(vehicle_id)
                    .bind(updated_at)
                    .fetch_optional(&mut *one)
                    .await?;
                    Ok(held.zip(deleted))
                }
                .await;
                match attempt {
                    Ok(abandoned) => {
                        one.commit().await?;
                        expired.abandoned.extend(abandoned);
                    }
                    Err(error) if is_row_error(&error) => {
                        one.rollback().await?;
                        expired
                            .unreadable
                            .push((version.clone(), error.to_string()));
                    }
                    Err(error) => return Err(error.into()),
                }
            }
            tx.commit().await?;
            Ok(expired)
        })
    }
}

/// What [`Store::expire_snapshots`] did.
#[derive(Debug, Default)]
pub struct ExpiredSnapshots {
    /// The alarms the deleted snapshots held open, still open, each with its snapshot.
    pub abandoned: Vec<(AlarmEventRow, Vec<u8>)>,
    /// Versions left in place because a row of theirs cannot be decoded, each with the reason.
    pub unreadable: Vec<((String, i64), String)>,
}
