//! Confirmed-alarm history: one row per alarm episode of a vehicle, written at onset and at end so an
//! alarm is never lost even if the in-memory session is.

use sqlx::Sqlite;
use sqlx::query::Query;
use sqlx::sqlite::SqliteArguments;

use super::error::{require_finite, require_probability};
use super::{Store, StoreError, now_unix_ms};

/// A stored alarm episode.
#[derive(Debug, Clone, PartialEq, sqlx::FromRow)]
pub struct AlarmEventRow {
    /// Store-assigned id, increasing in opening order.
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

impl AlarmEventRow {
    /// Whether the alarm is still open.
    pub fn is_open(&self) -> bool {
        self.ended_at_ms.is_none()
    }
}

impl Store {
    /// Records an alarm onset (one sample, peak = `probability`) and returns its id.
    ///
    /// [`StoreError::InvalidValue`] for a non-finite timestamp or a probability outside [0, 1].
    pub async fn open_alarm(
        &self,
        vehicle_id: &str,
        model_id: &str,
        onset_timestamp_s: f64,
        probability: f64,
    ) -> Result<i64, StoreError> {
        require_finite("onset_timestamp_s", onset_timestamp_s)?;
        require_probability("probability", probability)?;
        let id = sqlx::query_scalar::<_, i64>(
            "INSERT INTO alarm_events (vehicle_id, model_id, onset_timestamp_s, onset_at, \
             peak_probability, samples) VALUES (?1, ?2, ?3, ?4, ?5, 1) RETURNING id",
        )
        .bind(vehicle_id)
        .bind(model_id)
        .bind(onset_timestamp_s)
        .bind(now_unix_ms())
        .bind(probability)
        .fetch_one(&self.pool)
        .await?;
        Ok(id)
    }

    /// Updates an open alarm's peak probability and sample count (cheap progress checkpoint).
    ///
    /// [`StoreError::NotFound`] for an unknown id, [`StoreError::InvalidState`] if it is closed.
    pub async fn update_alarm_peak(
        &self,
        id: i64,
        peak_probability: f64,
        samples: u32,
    ) -> Result<(), StoreError> {
        require_probability("peak_probability", peak_probability)?;
        let update = sqlx::query(
            "UPDATE alarm_events SET peak_probability = ?2, samples = ?3 \
             WHERE id = ?1 AND ended_at IS NULL",
        )
        .bind(id)
        .bind(peak_probability)
        .bind(samples);
        self.update_open_alarm(id, "update", update).await
    }

    /// Closes an open alarm at sample time `end_timestamp_s` with its final peak and sample count.
    ///
    /// [`StoreError::NotFound`] for an unknown id, [`StoreError::InvalidState`] if already closed.
    pub async fn close_alarm(
        &self,
        id: i64,
        end_timestamp_s: f64,
        peak_probability: f64,
        samples: u32,
    ) -> Result<(), StoreError> {
        require_finite("end_timestamp_s", end_timestamp_s)?;
        require_probability("peak_probability", peak_probability)?;
        let update = sqlx::query(
            "UPDATE alarm_events SET end_timestamp_s = ?2, ended_at = ?3, peak_probability = ?4, \
             samples = ?5 WHERE id = ?1 AND ended_at IS NULL",
        )
        .bind(id)
        .bind(end_timestamp_s)
        .bind(now_unix_ms())
        .bind(peak_probability)
        .bind(samples);
        self.update_open_alarm(id, "close", update).await
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
        .fetch_all(&self.pool)
        .await?)
    }

    /// Shutdown/crash recovery: marks every open alarm ended at wall time `ended_at_ms`, leaving
    /// `end_timestamp_s` NULL ("the session ended while alarming"). Returns how many were closed.
    pub async fn close_open_alarms(&self, ended_at_ms: i64) -> Result<u64, StoreError> {
        let updated = sqlx::query("UPDATE alarm_events SET ended_at = ?1 WHERE ended_at IS NULL")
            .bind(ended_at_ms)
            .execute(&self.pool)
            .await?;
        Ok(updated.rows_affected())
    }

    /// Runs `update` (restricted to open alarms); if it touched no row, says why.
    async fn update_open_alarm(
        &self,
        id: i64,
        action: &'static str,
        update: Query<'_, Sqlite, SqliteArguments>,
    ) -> Result<(), StoreError> {
        let updated = update.execute(&self.pool).await?;
        if updated.rows_affected() == 0 {
            return Err(self.explain_unchanged_alarm(id, action).await);
        }
        Ok(())
    }

    /// Why an update of an open alarm touched no row: the alarm is unknown or already closed.
    async fn explain_unchanged_alarm(&self, id: i64, action: &'static str) -> StoreError {
        let exists = sqlx::query_scalar::<_, i64>("SELECT id FROM alarm_events WHERE id = ?1")
            .bind(id)
            .fetch_optional(&self.pool)
            .await;
        match exists {
            Ok(Some(_)) => StoreError::InvalidState {
                kind: "alarm event",
                id: id.to_string(),
                action,
                state: "closed",
            },
            Ok(None) => StoreError::NotFound {
                kind: "alarm event",
                id: id.to_string(),
            },
            Err(error) => error.into(),
        }
    }
}
