//! Shadows: the stored configuration of each shadow evaluation (which candidate, which vehicles,
//! who started and stopped it), each server process's counts for it, the vehicles it scored and
//! its would-be alarms.
//!
//! It owns the `shadows`, `shadow_tallies`, `shadow_vehicles` and `shadow_alarms` tables and must
//! not touch the real alarm tables: a shadow's alarms are never real ones.

use sqlx::types::Json;

use super::{Store, StoreError, now_unix_ms};

/// A stored shadow. `scope_json` is opaque here (the shadow subsystem encodes it).
#[derive(Debug, Clone, PartialEq, sqlx::FromRow)]
pub struct ShadowRow {
    pub id: i64,
    pub model_id: String,
    pub scope_json: Json<serde_json::Value>,
    #[sqlx(rename = "started_at")]
    pub started_at_ms: i64,
    pub started_by: String,
    #[sqlx(rename = "stopped_at")]
    pub stopped_at_ms: Option<i64>,
    pub stopped_by: Option<String>,
}

/// What [`Store::start_shadow`] did.
#[derive(Debug, Clone, PartialEq)]
pub enum ShadowStart {
    Started(ShadowRow),
    /// Another shadow runs (at most one per database): nothing was stored.
    AlreadyRunning(ShadowRow),
}

/// A would-be alarm of a shadow.
#[derive(Debug, Clone, PartialEq, sqlx::FromRow)]
pub struct ShadowAlarmRow {
    pub id: i64,
    pub shadow_id: i64,
    pub vehicle_id: String,
    pub model_id: String,
    pub onset_timestamp_s: f64,
    #[sqlx(rename = "onset_at")]
    pub onset_at_ms: i64,
    /// `warning` or `critical`.
    pub severity: String,
    pub escalated_timestamp_s: Option<f64>,
    pub peak_probability: f64,
    pub end_timestamp_s: Option<f64>,
    #[sqlx(rename = "ended_at")]
    pub ended_at_ms: Option<i64>,
    pub end_reason: Option<String>,
    pub live_alarmed: bool,
}

/// A would-be alarm's end.
#[derive(Debug, Clone, PartialEq)]
pub struct ShadowAlarmEnd<'a> {
    pub shadow_id: i64,
    pub vehicle_id: &'a str,
    pub onset_timestamp_s: f64,
    pub end_timestamp_s: f64,
    pub peak_probability: f64,
    pub live_alarmed: bool,
    /// One of the reasons the table allows (`cleared`, `shed`, `idle`, `reset`, `stopped`).
    pub reason: &'static str,
}

/// The columns of a [`ShadowRow`], as a literal for `concat!`.
macro_rules! shadow_columns {
    () => {
        "id, model_id, scope_json, started_at, started_by, stopped_at, stopped_by"
    };
}

/// The columns of a [`ShadowAlarmRow`], as a literal for `concat!`.
macro_rules! alarm_columns {
    () => {
        "id, shadow_id, vehicle_id, model_id, onset_timestamp_s, onset_at, severity, \
         escalated_timestamp_s, peak_probability, end_timestamp_s, ended_at, end_reason, \
         live_alarmed"
    };
}

impl Store {
    /// Stores a new running shadow unless one runs already (checked in the write transaction, so
    /// two replicas cannot both start one).
    pub async fn start_shadow(
        &self,
        model_id: &str,
        scope: &serde_json::Value,
        started_by: &str,
    ) -> Result<ShadowStart, StoreError> {
        let select_running = concat!(
            "SELECT ",
            shadow_columns!(),
            " FROM shadows WHERE stopped_at IS NULL LIMIT 1"
        );
        let insert = concat!(
            "INSERT INTO shadows (model_id, scope_json, started_at, started_by) \
             VALUES ($1, $2, $3, $4) RETURNING ",
            shadow_columns!()
        );
        in_write_tx!(self, |tx| {
            let running: Option<ShadowRow> = sqlx::query_as(select_running)
                .fetch_optional(&mut *tx)
                .await?;
            if let Some(running) = running {
                return Ok(ShadowStart::AlreadyRunning(running));
            }
            let row: ShadowRow = sqlx::query_as(insert)
                .bind(model_id)
                .bind(Json(scope))
                .bind(now_unix_ms())
                .bind(started_by)
                .fetch_one(&mut *tx)
                .await?;
            tx.commit().await?;
            Ok(ShadowStart::Started(row))
        })
    }

    /// The running shadow, if any.
    pub async fn running_shadow(&self) -> Result<Option<ShadowRow>, StoreError> {
        let sql = concat!(
            "SELECT ",
            shadow_columns!(),
            " FROM shadows WHERE stopped_at IS NULL LIMIT 1"
        );
        Ok(on_pool!(self, |pool| sqlx::query_as(sql)
            .fetch_optional(pool)
            .await?))
    }

    /// The shadow `id`, or the newest one (`None`).
    pub async fn get_shadow(&self, id: Option<i64>) -> Result<Option<ShadowRow>, StoreError> {
        let by_id = concat!("SELECT ", shadow_columns!(), " FROM shadows WHERE id = $1");
        let newest = concat!(
            "SELECT ",
            shadow_columns!(),
            " FROM shadows ORDER BY id DESC LIMIT 1"
        );
        Ok(on_pool!(self, |pool| match id {
            Some(id) => sqlx::query_as(by_id).bind(id).fetch_optional(pool).await?,
            None => sqlx::query_as(newest).fetch_optional(pool).await?,
        }))
    }

    /// Marks the shadow `id` stopped (once: a stopped shadow keeps its first stop) and ends its
    /// would-be alarms still open as `stopped`; returns it as stored, `None` if unknown.
    pub async fn stop_shadow(
        &self,
        id: i64,
        stopped_by: &str,
    ) -> Result<Option<ShadowRow>, StoreError> {
        let select = concat!("SELECT ", shadow_columns!(), " FROM shadows WHERE id = $1");
        let now = now_unix_ms();
        in_write_tx!(self, |tx| {
            sqlx::query(
                "UPDATE shadows SET stopped_at = $2, stopped_by = $3 \
                 WHERE id = $1 AND stopped_at IS NULL",
            )
            .bind(id)
            .bind(now)
            .bind(stopped_by)
            .execute(&mut *tx)
            .await?;
            sqlx::query(
                "UPDATE shadow_alarms SET ended_at = $2, end_reason = 'stopped' \
                 WHERE shadow_id = $1 AND ended_at IS NULL",
            )
            .bind(id)
            .bind(now)
            .execute(&mut *tx)
            .await?;
            let row: Option<ShadowRow> = sqlx::query_as(select)
                .bind(id)
                .fetch_optional(&mut *tx)
                .await?;
            tx.commit().await?;
            Ok(row)
        })
    }

    /// Replaces this process's cumulative counts for a shadow.
    pub async fn put_shadow_tally(
        &self,
        shadow_id: i64,
        process: &str,
        tally: &serde_json::Value,
    ) -> Result<(), StoreError> {
        on_pool!(self, |pool| {
            sqlx::query(
                "INSERT INTO shadow_tallies (shadow_id, process, updated_at, tally_json) \
             VALUES ($1, $2, $3, $4) ON CONFLICT (shadow_id, process) DO UPDATE \
             SET updated_at = excluded.updated_at, tally_json = excluded.tally_json",
            )
            .bind(shadow_id)
            .bind(process)
            .bind(now_unix_ms())
            .bind(Json(tally))
            .execute(pool)
            .await?;
        });
        Ok(())
    }

    /// Every process's counts for a shadow.
    pub async fn shadow_tallies(
        &self,
        shadow_id: i64,
    ) -> Result<Vec<serde_json::Value>, StoreError> {
        let rows: Vec<Json<serde_json::Value>> = on_pool!(self, |pool| sqlx::query_scalar(
            "SELECT tally_json FROM shadow_tallies WHERE shadow_id = $1 ORDER BY process"
        )
        .bind(shadow_id)
        .fetch_all(pool)
        .await?);
        Ok(rows.into_iter().map(|Json(value)| value).collect())
    }

    /// Vehicles' shadow states started (afresh after their first start), in one transaction: each
    /// start counted (a vehicle listed twice, twice), and a would-be alarm another copy of a
    /// vehicle's state left open (a restart, a hand-off) ends as `restarted`.
    pub async fn shadow_vehicles_started(
        &self,
        shadow_id: i64,
        vehicle_ids: &[&str],
    ) -> Result<(), StoreError> {
        let now = now_unix_ms();
        in_write_tx!(self, |tx| {
            for vehicle_id in vehicle_ids {
                sqlx::query(
                    "INSERT INTO shadow_vehicles (shadow_id, vehicle_id, starts) VALUES ($1, $2, 1) \
                     ON CONFLICT (shadow_id, vehicle_id) \
                     DO UPDATE SET starts = shadow_vehicles.starts + 1",
                )
                .bind(shadow_id)
                .bind(*vehicle_id)
                .execute(&mut *tx)
                .await?;
                sqlx::query(
                    "UPDATE shadow_alarms SET ended_at = $3, end_reason = 'restarted' \
                     WHERE shadow_id = $1 AND vehicle_id = $2 AND ended_at IS NULL",
                )
                .bind(shadow_id)
                .bind(*vehicle_id)
                .bind(now)
                .execute(&mut *tx)
                .await?;
            }
            tx.commit().await?;
            Ok(())
        })
    }

    /// The vehicles a shadow scored, its would-be alarms, and its vehicle starts in all.
    pub async fn shadow_counts(&self, shadow_id: i64) -> Result<(u64, u64, u64), StoreError> {
        let (vehicles, starts, alarms): (i64, Option<i64>, i64) =
            on_pool!(self, |pool| sqlx::query_as(
                "SELECT (SELECT COUNT(*) FROM shadow_vehicles WHERE shadow_id = $1), \
                 (SELECT CAST(SUM(starts) AS BIGINT) FROM shadow_vehicles WHERE shadow_id = $1), \
                 (SELECT COUNT(*) FROM shadow_alarms WHERE shadow_id = $1)"
            )
            .bind(shadow_id)
            .fetch_one(pool)
            .await?);
        let count = |n: i64| u64::try_from(n).unwrap_or(0);
        Ok((count(vehicles), count(starts.unwrap_or(0)), count(alarms)))
    }

    /// Stores a would-be alarm's onset (once: a repeat of the same onset is ignored).
    pub async fn insert_shadow_alarm(&self, row: &ShadowAlarmRow) -> Result<(), StoreError> {
        on_pool!(self, |pool| {
            sqlx::query(
                "INSERT INTO shadow_alarms (shadow_id, vehicle_id, model_id, onset_timestamp_s, \
             onset_at, severity, escalated_timestamp_s, peak_probability, live_alarmed) \
             VALUES ($1, $2, $3, $4, $5, $6, $7, $8, $9) \
             ON CONFLICT (shadow_id, vehicle_id, onset_timestamp_s) DO NOTHING",
            )
            .bind(row.shadow_id)
            .bind(&row.vehicle_id)
            .bind(&row.model_id)
            .bind(row.onset_timestamp_s)
            .bind(row.onset_at_ms)
            .bind(&row.severity)
            .bind(row.escalated_timestamp_s)
            .bind(row.peak_probability)
            .bind(row.live_alarmed)
            .execute(pool)
            .await?;
        });
        Ok(())
    }

    /// An open would-be alarm turned critical at sample time `timestamp_s`.
    pub async fn escalate_shadow_alarm(
        &self,
        shadow_id: i64,
        vehicle_id: &str,
        onset_timestamp_s: f64,
        timestamp_s: f64,
    ) -> Result<(), StoreError> {
        on_pool!(self, |pool| {
            sqlx::query(
                "UPDATE shadow_alarms SET severity = 'critical', escalated_timestamp_s = $4 \
             WHERE shadow_id = $1 AND vehicle_id = $2 AND onset_timestamp_s = $3 \
             AND ended_at IS NULL AND escalated_timestamp_s IS NULL",
            )
            .bind(shadow_id)
            .bind(vehicle_id)
            .bind(onset_timestamp_s)
            .bind(timestamp_s)
            .execute(pool)
            .await?;
        });
        Ok(())
    }

    /// Ends an open would-be alarm (one already ended keeps its first end).
    pub async fn end_shadow_alarm(&self, end: &ShadowAlarmEnd<'_>) -> Result<(), StoreError> {
        on_pool!(self, |pool| {
            sqlx::query(
                "UPDATE shadow_alarms SET end_timestamp_s = $4, ended_at = $5, end_reason = $6, \
             peak_probability = $7, live_alarmed = $8 \
             WHERE shadow_id = $1 AND vehicle_id = $2 AND onset_timestamp_s = $3 \
             AND ended_at IS NULL",
            )
            .bind(end.shadow_id)
            .bind(end.vehicle_id)
            .bind(end.onset_timestamp_s)
            .bind(end.end_timestamp_s)
            .bind(now_unix_ms())
            .bind(end.reason)
            .bind(end.peak_probability)
            .bind(end.live_alarmed)
            .execute(pool)
            .await?;
        });
        Ok(())
    }

    /// Up to `limit` would-be alarms of a shadow (of one vehicle, if given) with ids below
    /// `before` (`None`: from the newest), newest first.
    pub async fn list_shadow_alarms(
        &self,
        shadow_id: i64,
        vehicle_id: Option<&str>,
        before: Option<i64>,
        limit: u32,
    ) -> Result<Vec<ShadowAlarmRow>, StoreError> {
        let sql = concat!(
            "SELECT ",
            alarm_columns!(),
            " FROM shadow_alarms WHERE shadow_id = $1 \
             AND ($2 IS NULL OR vehicle_id = $2) AND id < $3 ORDER BY id DESC LIMIT $4"
        );
        Ok(on_pool!(self, |pool| sqlx::query_as(sql)
            .bind(shadow_id)
            .bind(vehicle_id)
            .bind(before.unwrap_or(i64::MAX))
            .bind(i64::from(limit))
            .fetch_all(pool)
            .await?))
    }
}
