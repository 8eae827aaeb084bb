//! Confirmed-alarm history: one row per alarm episode of a vehicle, written at onset and at end (by
//! the server's background alarm writer, in batches) so an alarm is never lost even if the
//! in-memory session is.

use super::error::{require_finite, require_probability};
use super::{Store, StoreError};

/// A stored alarm episode.
#[derive(Debug, Clone, PartialEq, sqlx::FromRow)]
pub struct AlarmEventRow {
    /// Server-assigned id, increasing in opening order.
    pub id: i64,
    /// The vehicle that alarmed.
    pub vehicle_id: String,
    /// The model that raised it.
    pub model_id: String,
    /// Sample timestamp (seconds, the vehicle's clock) of the onset.
    pub onset_timestamp_s: f64,
    /// Sample timestamp of the last alarming sample; `None` while open, or when the session ended
    /// while still alarming (then `ended_at_ms` is set).
    pub end_timestamp_s: Option<f64>,
    /// Wall-clock onset, unix epoch milliseconds.
    #[sqlx(rename = "onset_at")]
    pub onset_at_ms: i64,
    /// Wall-clock end, unix epoch milliseconds; `None` while the alarm is open.
    #[sqlx(rename = "ended_at")]
    pub ended_at_ms: Option<i64>,
    /// Highest spoofing probability seen during the episode.
    pub peak_probability: f64,
    /// Number of samples in the episode so far.
    pub samples: i64,
}

/// One alarm write of the background writer: ids come from the server (never from an insert), so
/// a write can be retried and an end always names its own onset.
#[derive(Debug, Clone, PartialEq)]
pub enum AlarmWrite {
    /// An alarm onset (one sample, peak = `probability`).
    Onset {
        id: i64,
        vehicle_id: String,
        model_id: String,
        onset_timestamp_s: f64,
        onset_at_ms: i64,
        probability: f64,
    },
    /// The end of alarm `id` at its last alarming sample.
    End {
        id: i64,
        end_timestamp_s: f64,
        ended_at_ms: i64,
        peak_probability: f64,
        samples: u32,
    },
}

impl AlarmWrite {
    /// [`StoreError::InvalidValue`] for a non-finite timestamp or a probability outside [0, 1].
    pub fn validate(&self) -> Result<(), StoreError> {
        match self {
            Self::Onset {
                onset_timestamp_s,
                probability,
                ..
            } => {
                require_finite("onset_timestamp_s", *onset_timestamp_s)?;
                require_probability("probability", *probability)?;
            }
            Self::End {
                end_timestamp_s,
                peak_probability,
                ..
            } => {
                require_finite("end_timestamp_s", *end_timestamp_s)?;
                require_probability("peak_probability", *peak_probability)?;
            }
        }
        Ok(())
    }
}

impl AlarmEventRow {
    /// Whether the alarm is still open.
    pub fn is_open(&self) -> bool {
        self.ended_at_ms.is_none()
    }
}

impl Store {
    /// The largest alarm id stored (0 when there is none): where server-assigned ids continue.
    pub async fn max_alarm_id(&self) -> Result<i64, StoreError> {
        Ok(
            sqlx::query_scalar::<_, i64>("SELECT COALESCE(MAX(id), 0) FROM alarm_events")
                .fetch_one(self.pool()?)
                .await?,
        )
    }

    /// Applies `writes` in order in one transaction, all or nothing. Idempotent, so a batch whose
    /// outcome is unknown can be retried: an onset already stored is skipped and an end only
    /// touches its alarm while it is open.
    ///
    /// [`StoreError::InvalidValue`] (before anything is written) for a non-finite timestamp or a
    /// probability outside [0, 1].
    pub async fn write_alarms(&self, writes: &[AlarmWrite]) -> Result<(), StoreError> {
        for write in writes {
            write.validate()?;
        }
        let mut tx = self.begin_write().await?;
        for write in writes {
            match write {
                AlarmWrite::Onset {
                    id,
                    vehicle_id,
                    model_id,
                    onset_timestamp_s,
                    onset_at_ms,
                    probability,
                } => {
                    sqlx::query(
                        "INSERT OR IGNORE INTO alarm_events (id, vehicle_id, model_id, \
                         onset_timestamp_s, onset_at, peak_probability, samples) \
                         VALUES (?1, ?2, ?3, ?4, ?5, ?6, 1)",
                    )
                    .bind(id)
                    .bind(vehicle_id)
                    .bind(model_id)
                    .bind(onset_timestamp_s)
                    .bind(onset_at_ms)
                    .bind(probability)
                    .execute(&mut *tx)
                    .await?;
                }
                AlarmWrite::End {
                    id,
                    end_timestamp_s,
                    ended_at_ms,
                    peak_probability,
                    samples,
                } => {
                    sqlx::query(
                        "UPDATE alarm_events SET end_timestamp_s = ?2, ended_at = ?3, \
                         peak_probability = ?4, samples = ?5 WHERE id = ?1 AND ended_at IS NULL",
                    )
                    .bind(id)
                    .bind(end_timestamp_s)
                    .bind(ended_at_ms)
                    .bind(peak_probability)
                    .bind(samples)
                    .execute(&mut *tx)
                    .await?;
                }
            }
        }
        tx.commit().await?;
        Ok(())
    }

    /// The most recently opened alarm events first, optionally for one vehicle, at most `limit`.
    pub async fn list_alarm_events(
        &self,
        vehicle_id: Option<&str>,
        limit: u32,
    ) -> Result<Vec<AlarmEventRow>, StoreError> {
        Ok(sqlx::query_as::<_, AlarmEventRow>(
            "SELECT id, vehicle_id, model_id, onset_timestamp_s, end_timestamp_s, onset_at, \
             ended_at, peak_probability, samples FROM alarm_events \
             WHERE ?1 IS NULL OR vehicle_id = ?1 ORDER BY id DESC LIMIT ?2",
        )
        .bind(vehicle_id)
        .bind(limit)
        .fetch_all(self.pool()?)
        .await?)
    }

    /// Shutdown/crash recovery: marks every open alarm ended at wall time `ended_at_ms`, leaving
    /// `end_timestamp_s` NULL ("the session ended while alarming"). Returns how many were closed.
    pub async fn close_open_alarms(&self, ended_at_ms: i64) -> Result<u64, StoreError> {
        let updated = sqlx::query("UPDATE alarm_events SET ended_at = ?1 WHERE ended_at IS NULL")
            .bind(ended_at_ms)
            .execute(self.pool()?)
            .await?;
        Ok(updated.rows_affected())
    }
}
