//! Confirmed-alarm history: one row per alarm episode of a vehicle, written at onset, at its
//! escalation to critical and at end (by the server's session outbox, in batches: see
//! `super::outbox`) so an alarm is never lost even if the in-memory session is. Each onset,
//! escalation and end is also appended to the event log behind WatchAlarms, at a position the
//! database assigns in commit order (see `log_event!`).
//!
//! It owns the alarm tables and their reads; it must not know session snapshots (their table is
//! `super::snapshots`, the joint write `super::outbox`).

use spoofwatch_core::severity::Severity;

use super::error::{require_finite, require_probability};
use super::paging::PagePlan;
use super::{Page, PageRequest, Store, StoreError};

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
    /// Why the alarm was raised (its onset's explanation); all `None` on rows stored before
    /// schema version 6.
    #[sqlx(flatten)]
    pub why: StoredWhy,
    /// Where it started (the onset sample's fix); `None` on rows stored before schema version 8.
    #[sqlx(flatten)]
    pub place: StoredPlace,
    /// The highest severity it reached (warning on rows stored before schema version 10).
    pub severity: StoredSeverity,
    /// When it turned critical, sample time; `None` while it is a warning.
    pub escalated_timestamp_s: Option<f64>,
    /// When it turned critical, wall-clock unix ms; `None` while it is a warning.
    #[sqlx(rename = "escalated_at")]
    pub escalated_at_ms: Option<i64>,
    /// The credential whose call sent the samples that raised it; `None` on rows stored before
    /// schema version 11.
    #[sqlx(flatten)]
    pub credential: StoredCredential,
}

/// The credential behind an alarm as the alarm row stores it. Written with the onset, never changed
/// by its escalation or end (a session continued by another stream keeps its alarm's credential).
#[derive(Debug, Clone, Default, PartialEq, Eq, sqlx::FromRow)]
pub struct StoredCredential {
    /// What the credential is, never its secret: `certificate <name> sha256:<prefix>`,
    /// `token <name> sha256:<prefix>`, `admin token`, or `unauthenticated`.
    pub credential: Option<String>,
    /// Each vehicle of this credential is its own source of evidence (a gateway forwarding
    /// independent receivers, or a server without identities), rather than all of them one.
    pub credential_per_vehicle: bool,
}

/// An alarm's severity as the store keeps it: its name (`warning`, `critical`).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, PartialOrd, Ord)]
pub struct StoredSeverity(pub Severity);

impl StoredSeverity {
    /// The name stored in the database.
    pub fn as_str(self) -> &'static str {
        self.0.name()
    }

    fn from_str_opt(name: &str) -> Option<Self> {
        Severity::from_name(name).map(Self)
    }
}

text_enum!(StoredSeverity);

/// An alarm's onset fix as the alarm row stores it, degrees. Written with the onset, never changed
/// by its end.
#[derive(Debug, Clone, Copy, Default, PartialEq, sqlx::FromRow)]
pub struct StoredPlace {
    pub onset_latitude_deg: Option<f64>,
    pub onset_longitude_deg: Option<f64>,
}

/// The explanation of an alarm's onset as the alarm row stores it: the dominant evidence's
/// snake_case name and the east/north vectors (the store does not interpret them; the alarm API
/// maps them to the wire). Written with the onset, never changed by its end.
#[derive(Debug, Clone, Default, PartialEq, sqlx::FromRow)]
pub struct StoredWhy {
    /// The dominant evidence (`jump`, `held_offset`, …); `None` when the alarm has none stored.
    pub why_kind: Option<String>,
    /// GNSS minus the dead-reckoning anchor, east/north (m).
    pub why_offset_east_m: Option<f64>,
    pub why_offset_north_m: Option<f64>,
    /// The drift rate, east/north (m/s).
    pub why_drift_east_mps: Option<f64>,
    pub why_drift_north_mps: Option<f64>,
}

/// What an alarm event did to its alarm.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum AlarmEventKind {
    /// The alarm started: its row is inserted.
    Onset,
    /// The open alarm, a warning, turned critical: its row is updated.
    Escalated,
    /// The alarm ended: its row is closed.
    End,
}

impl AlarmEventKind {
    /// The lowercase name stored in the database.
    pub fn as_str(self) -> &'static str {
        match self {
            AlarmEventKind::Onset => "onset",
            AlarmEventKind::Escalated => "escalated",
            AlarmEventKind::End => "end",
        }
    }

    fn from_str_opt(name: &str) -> Option<Self> {
        match name {
            "onset" => Some(AlarmEventKind::Onset),
            "escalated" => Some(AlarmEventKind::Escalated),
            "end" => Some(AlarmEventKind::End),
            _ => None,
        }
    }
}

text_enum!(AlarmEventKind);

/// One alarm onset, escalation or end, as the server emits it: stored by the background writer
/// (the alarm row and the event log). Ids and seqs come from the server (never from an insert), so a write can be
/// retried and an end always names its onset.
#[derive(Debug, Clone, PartialEq, sqlx::FromRow)]
pub struct AlarmEvent {
    /// The writer's key of the event: increasing in emission order within one server run, also
    /// across restarts, and unique among the processes sharing the database (a retried write is
    /// skipped by it). Not the WatchAlarms cursor: see [`LoggedAlarmEvent::position`].
    pub seq: i64,
    /// Onset, escalation or end.
    pub kind: AlarmEventKind,
    /// The alarm as this event left it (open with one sample for an onset, critical with its
    /// escalation times for an escalation, closed for an end).
    #[sqlx(flatten)]
    pub alarm: AlarmEventRow,
}

/// An event as the event log holds it: with the position the database gave it when it was stored.
#[derive(Debug, Clone, PartialEq, sqlx::FromRow)]
pub struct LoggedAlarmEvent {
    /// The WatchAlarms cursor: 1, 2, 3, … in commit order across every process writing into the
    /// database (see `Store::write_alarms_and_snapshots`).
    pub position: i64,
    /// The event.
    #[sqlx(flatten)]
    pub event: AlarmEvent,
}

impl AlarmEventRow {
    /// Whether the alarm is still open.
    pub fn is_open(&self) -> bool {
        self.ended_at_ms.is_none()
    }
}

impl AlarmEvent {
    /// [`StoreError::InvalidValue`] for a non-finite timestamp or explanation, a probability
    /// outside [0, 1], an end without an end time, or a critical alarm without its escalation
    /// times (and a warning with them).
    pub fn validate(&self) -> Result<(), StoreError> {
        let alarm = &self.alarm;
        if let Some(escalated) = alarm.escalated_timestamp_s {
            require_finite("escalated_timestamp_s", escalated)?;
        }
        let critical = alarm.severity.0 == Severity::Critical;
        if critical != alarm.escalated_timestamp_s.is_some()
            || critical != alarm.escalated_at_ms.is_some()
            || (self.kind == AlarmEventKind::Escalated && !critical)
        {
            return Err(StoreError::InvalidValue {
                field: "severity",
                reason: "a critical alarm has both escalation times, a warning neither, and an \
                         escalation is critical"
                    .to_string(),
            });
        }
        match self.kind {
            AlarmEventKind::Onset => {
                require_finite("onset_timestamp_s", alarm.onset_timestamp_s)?;
                require_probability("probability", alarm.peak_probability)?;
                let why = &alarm.why;
                for (field, value) in [
                    ("why_offset_east_m", why.why_offset_east_m),
                    ("why_offset_north_m", why.why_offset_north_m),
                    ("why_drift_east_mps", why.why_drift_east_mps),
                    ("why_drift_north_mps", why.why_drift_north_mps),
                    ("onset_latitude_deg", alarm.place.onset_latitude_deg),
                    ("onset_longitude_deg", alarm.place.onset_longitude_deg),
                ] {
                    if let Some(value) = value {
                        require_finite(field, value)?;
                    }
                }
            }
            AlarmEventKind::Escalated => {
                require_probability("peak_probability", alarm.peak_probability)?;
            }
            AlarmEventKind::End => {
                if let Some(end) = alarm.end_timestamp_s {
                    require_finite("end_timestamp_s", end)?;
                }
                require_probability("peak_probability", alarm.peak_probability)?;
                if alarm.ended_at_ms.is_none() {
                    return Err(StoreError::InvalidValue {
                        field: "ended_at",
                        reason: "an alarm end needs its end time".to_string(),
                    });
                }
            }
        }
        Ok(())
    }
}

/// Which alarms `ListAlarms` returns.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub enum AlarmState {
    /// Open and closed.
    #[default]
    Any,
    /// Still on.
    Open,
    /// Ended.
    Closed,
}

/// The filters of [`Store::list_alarms`]; every `None` matches all.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct AlarmFilter {
    /// Exactly this vehicle.
    pub vehicle_id: Option<String>,
    /// Raised by this model (its id).
    pub model_id: Option<String>,
    /// Wall-clock onset at or after this (unix ms).
    pub onset_from_ms: Option<i64>,
    /// Wall-clock onset before this (unix ms).
    pub onset_before_ms: Option<i64>,
    /// Open, closed or both.
    pub state: AlarmState,
    /// The least severity listed: warning lists every alarm, critical those that are critical.
    pub min_severity: Severity,
}

/// `end` as it stands against the stored snapshot copy of its session's progress on the alarm
/// (latest alarming sample's time, peak, samples): taken from that copy when it got further.
pub(super) fn furthest_end(
    end: &AlarmEvent,
    stored_copy: Option<(Option<f64>, Option<f64>, Option<i64>)>,
) -> AlarmEvent {
    let mut end = end.clone();
    if let Some((Some(last), Some(peak), Some(samples))) = stored_copy
        && end.alarm.end_timestamp_s.is_none_or(|ends| last > ends)
    {
        end.alarm.end_timestamp_s = Some(last);
        end.alarm.peak_probability = end.alarm.peak_probability.max(peak);
        end.alarm.samples = end.alarm.samples.max(samples);
    }
    end
}

/// Listing name inside page tokens.
const LISTING: &str = "alarms";

/// Where the alarm ids and event seqs of alarm run `run` start: they are `(run << 32) + n`.
pub fn first_seq_of_run(run: i64) -> i64 {
    run << 32
}

/// `SELECT <the columns of an [`AlarmEventRow`]> FROM alarm_events <rest>`, as a literal (sqlx takes
/// only literal SQL).
macro_rules! select_alarms {
    ($rest:literal) => {
        concat!(
            "SELECT id, vehicle_id, model_id, onset_timestamp_s, end_timestamp_s, onset_at, \
             ended_at, peak_probability, samples, why_kind, why_offset_east_m, \
             why_offset_north_m, why_drift_east_mps, why_drift_north_mps, onset_latitude_deg, \
             onset_longitude_deg, severity, escalated_timestamp_s, escalated_at, credential, \
             credential_per_vehicle FROM alarm_events ",
            $rest
        )
    };
}
pub(super) use select_alarms;

/// Appends `event` to the event log inside the write transaction `tx` (skipped when its seq is
/// already there: a retry), at the next log position. A macro so that it compiles for either
/// backend's transaction.
///
/// The position is `MAX(position) + 1` read inside the write transaction, which holds the
/// database's write lock (SQLite's `BEGIN IMMEDIATE`, PostgreSQL's advisory lock) until it has
/// committed: the next writer gets the lock only once these rows are visible, so positions
/// increase in commit order. A reader that has seen position p therefore never later finds a newly
/// committed row below p, on any replica: the invariant WatchAlarms' cursors rest on.
macro_rules! log_event {
    ($tx:ident, $event:expr) => {{
        let event: &AlarmEvent = $event;
        let alarm = &event.alarm;
        sqlx::query(
            "INSERT INTO alarm_event_log (position, seq, alarm_id, kind, end_timestamp_s, \
             ended_at, peak_probability, samples, severity, escalated_timestamp_s, escalated_at) \
             VALUES ((SELECT COALESCE(MAX(position), 0) + 1 FROM alarm_event_log), \
             $1, $2, $3, $4, $5, $6, $7, $8, $9, $10) ON CONFLICT DO NOTHING",
        )
        .bind(event.seq)
        .bind(alarm.id)
        .bind(event.kind)
        .bind(alarm.end_timestamp_s)
        .bind(alarm.ended_at_ms)
        .bind(alarm.peak_probability)
        .bind(alarm.samples)
        .bind(alarm.severity)
        .bind(alarm.escalated_timestamp_s)
        .bind(alarm.escalated_at_ms)
        .execute(&mut *$tx)
        .await?;
    }};
}
pub(super) use log_event;

/// Applies `event` inside the write transaction `$tx`: an onset inserts its alarm, an escalation
/// makes the open alarm critical, an end closes it, and an event that changed its alarm is appended
/// to the event log, as it left the alarm. A retry of a stored event changes nothing. A macro so that it compiles for either backend's transaction
/// (used by the joint write, `super::outbox`).
///
/// An alarm ends at the latest alarming sample any copy of its session saw. A process that
/// replaces a session (a roll-out) ends its alarm from the copy it read, which may lag the copy
/// another process stored meanwhile, or stores later: so an end takes the stored snapshot's
/// progress on the alarm when that got further, and an end later than the stored one moves it on
/// (an end without a sample time moves nothing that has one). Severity only rises: an end keeps the
/// stored escalation when its copy of the alarm had not seen it, and is logged with it.
macro_rules! apply_event {
    ($tx:ident, $event:expr) => {{
        let event: &AlarmEvent = $event;
        let alarm = &event.alarm;
        match event.kind {
            AlarmEventKind::Onset => {
                let inserted = sqlx::query(
                    "INSERT INTO alarm_events (id, vehicle_id, model_id, \
                     onset_timestamp_s, onset_at, peak_probability, samples, why_kind, \
                     why_offset_east_m, why_offset_north_m, why_drift_east_mps, \
                     why_drift_north_mps, onset_latitude_deg, onset_longitude_deg, severity, \
                     escalated_timestamp_s, escalated_at, credential, credential_per_vehicle) \
                     VALUES ($1, $2, $3, $4, $5, $6, 1, $7, $8, $9, $10, $11, $12, $13, $14, \
                     $15, $16, $17, $18) ON CONFLICT DO NOTHING",
                )
                .bind(alarm.id)
                .bind(&alarm.vehicle_id)
                .bind(&alarm.model_id)
                .bind(alarm.onset_timestamp_s)
                .bind(alarm.onset_at_ms)
                .bind(alarm.peak_probability)
                .bind(alarm.why.why_kind.as_deref())
                .bind(alarm.why.why_offset_east_m)
                .bind(alarm.why.why_offset_north_m)
                .bind(alarm.why.why_drift_east_mps)
                .bind(alarm.why.why_drift_north_mps)
                .bind(alarm.place.onset_latitude_deg)
                .bind(alarm.place.onset_longitude_deg)
                .bind(alarm.severity)
                .bind(alarm.escalated_timestamp_s)
                .bind(alarm.escalated_at_ms)
                .bind(alarm.credential.credential.as_deref())
                .bind(alarm.credential.credential_per_vehicle)
                .execute(&mut *$tx)
                .await?
                .rows_affected();
                if inserted > 0 {
                    $crate::store::alarms::log_event!($tx, event);
                }
            }
            AlarmEventKind::Escalated => {
                // Only an open warning escalates: a retry, or an alarm another process ended
                // meanwhile, changes nothing.
                let escalated = sqlx::query(
                    "UPDATE alarm_events SET severity = $2, escalated_timestamp_s = $3, \
                     escalated_at = $4, peak_probability = $5, samples = $6 \
                     WHERE id = $1 AND ended_at IS NULL AND severity <> $2",
                )
                .bind(alarm.id)
                .bind(alarm.severity)
                .bind(alarm.escalated_timestamp_s)
                .bind(alarm.escalated_at_ms)
                .bind(alarm.peak_probability)
                .bind(alarm.samples)
                .execute(&mut *$tx)
                .await?
                .rows_affected();
                if escalated > 0 {
                    $crate::store::alarms::log_event!($tx, event);
                }
            }
            AlarmEventKind::End => {
                let stored_copy = sqlx::query_as::<_, (Option<f64>, Option<f64>, Option<i64>)>(
                    "SELECT open_alarm_last_timestamp_s, open_alarm_peak_probability, \
                     open_alarm_samples FROM session_snapshots WHERE open_alarm_id = $1",
                )
                .bind(alarm.id)
                .fetch_optional(&mut *$tx)
                .await?;
                let mut event = $crate::store::alarms::furthest_end(event, stored_copy);
                let alarm = &event.alarm;
                let ended = sqlx::query_as::<
                    _,
                    (
                        $crate::store::alarms::StoredSeverity,
                        Option<f64>,
                        Option<i64>,
                    ),
                >(
                    "UPDATE alarm_events SET end_timestamp_s = $2, ended_at = $3, \
                     peak_probability = $4, samples = $5, \
                     severity = CASE WHEN $6 = 'critical' THEN $6 ELSE severity END, \
                     escalated_timestamp_s = COALESCE(escalated_timestamp_s, $7), \
                     escalated_at = COALESCE(escalated_at, $8) WHERE id = $1 AND (ended_at IS NULL \
                     OR end_timestamp_s < $2 OR (end_timestamp_s IS NULL AND $2 IS NOT NULL)) \
                     RETURNING severity, escalated_timestamp_s, escalated_at",
                )
                .bind(alarm.id)
                .bind(alarm.end_timestamp_s)
                .bind(alarm.ended_at_ms)
                .bind(alarm.peak_probability)
                .bind(alarm.samples)
                .bind(alarm.severity)
                .bind(alarm.escalated_timestamp_s)
                .bind(alarm.escalated_at_ms)
                .fetch_optional(&mut *$tx)
                .await?;
                if let Some((severity, escalated_timestamp_s, escalated_at_ms)) = ended {
                    event.alarm.severity = severity;
                    event.alarm.escalated_timestamp_s = escalated_timestamp_s;
                    event.alarm.escalated_at_ms = escalated_at_ms;
                    $crate::store::alarms::log_event!($tx, &event);
                }
            }
        }
    }};
}
pub(super) use apply_event;

impl Store {
    /// The largest alarm id stored (0 when there is none).
    pub async fn max_alarm_id(&self) -> Result<i64, StoreError> {
        Ok(on_pool!(self, |pool| {
            sqlx::query_scalar::<_, i64>("SELECT COALESCE(MAX(id), 0) FROM alarm_events")
                .fetch_one(pool)
                .await?
        }))
    }

    /// Records a server start and returns its run number (never reused, increasing): the run's
    /// alarm ids and event seqs start at [`first_seq_of_run`].
    pub async fn start_alarm_run(&self, started_at_ms: i64) -> Result<i64, StoreError> {
        Ok(on_pool!(self, |pool| {
            sqlx::query_scalar::<_, i64>(
                "INSERT INTO alarm_runs (started_at) VALUES ($1) RETURNING run",
            )
            .bind(started_at_ms)
            .fetch_one(pool)
            .await?
        }))
    }

    /// The most recently opened alarm events first, optionally for one vehicle, at most `limit`.
    pub async fn list_alarm_events(
        &self,
        vehicle_id: Option<&str>,
        limit: u32,
    ) -> Result<Vec<AlarmEventRow>, StoreError> {
        Ok(on_pool!(self, |pool| {
            sqlx::query_as::<_, AlarmEventRow>(select_alarms!(
                "WHERE $1 IS NULL OR vehicle_id = $1 ORDER BY id DESC LIMIT $2"
            ))
            .bind(vehicle_id)
            .bind(i64::from(limit))
            .fetch_all(pool)
            .await?
        }))
    }

    /// One page of the alarms `filter` selects, in id (opening) order.
    ///
    /// [`StoreError::InvalidPageToken`] for a token this listing did not issue.
    pub async fn list_alarms(
        &self,
        filter: &AlarmFilter,
        page: &PageRequest,
    ) -> Result<Page<AlarmEventRow>, StoreError> {
        let sql = select_alarms!(
            "WHERE ($1 IS NULL OR vehicle_id = $1) AND ($2 IS NULL OR model_id = $2) \
             AND ($3 IS NULL OR onset_at >= $3) AND ($4 IS NULL OR onset_at < $4) \
             AND ($5 = 'any' OR ($5 = 'open') = (ended_at IS NULL)) \
             AND ($6 IS NULL OR id > $6) \
             AND ($8 = 'warning' OR severity = $8) \
             ORDER BY id LIMIT $7"
        );
        let state = match filter.state {
            AlarmState::Any => "any",
            AlarmState::Open => "open",
            AlarmState::Closed => "closed",
        };
        let plan = PagePlan::new(LISTING, page)?;
        // Alarms page by id alone: the token's time slot carries the last id; its id slot is unused.
        let rows = on_pool!(self, |pool| {
            sqlx::query_as::<_, AlarmEventRow>(sql)
                .bind(filter.vehicle_id.as_deref())
                .bind(filter.model_id.as_deref())
                .bind(filter.onset_from_ms)
                .bind(filter.onset_before_ms)
                .bind(state)
                .bind(plan.after_created_at())
                .bind(plan.fetch_limit())
                .bind(StoredSeverity(filter.min_severity))
                .fetch_all(pool)
                .await?
        });
        Ok(plan.finish(LISTING, rows, |row| (row.id, "")))
    }

    /// The logged events with `after < position <= through`, optionally of one vehicle, in
    /// position order, at most `limit`.
    pub async fn alarm_events_after(
        &self,
        after: i64,
        through: i64,
        vehicle_id: Option<&str>,
        limit: u32,
    ) -> Result<Vec<LoggedAlarmEvent>, StoreError> {
        self.alarm_events_at_least(after, through, vehicle_id, Severity::Warning, limit)
            .await
    }

    /// [`Store::alarm_events_after`] of at least `min_severity`: with critical, only the events
    /// that left their alarm critical (an onset as critical, an escalation, the end of a critical
    /// alarm).
    pub async fn alarm_events_at_least(
        &self,
        after: i64,
        through: i64,
        vehicle_id: Option<&str>,
        min_severity: Severity,
        limit: u32,
    ) -> Result<Vec<LoggedAlarmEvent>, StoreError> {
        Ok(on_pool!(self, |pool| {
            sqlx::query_as::<_, LoggedAlarmEvent>(
                "SELECT l.position, l.seq, l.kind, a.id, a.vehicle_id, a.model_id, \
                 a.onset_timestamp_s, l.end_timestamp_s, a.onset_at, l.ended_at, \
                 l.peak_probability, l.samples, a.why_kind, a.why_offset_east_m, \
                 a.why_offset_north_m, a.why_drift_east_mps, a.why_drift_north_mps, \
                 a.onset_latitude_deg, a.onset_longitude_deg, l.severity, \
                 l.escalated_timestamp_s, l.escalated_at, a.credential, \
                 a.credential_per_vehicle \
                 FROM alarm_event_log l JOIN alarm_events a ON a.id = l.alarm_id \
                 WHERE l.position > $1 AND l.position <= $2 \
                 AND ($3 IS NULL OR a.vehicle_id = $3) \
                 AND ($5 = 'warning' OR l.severity = $5) \
                 ORDER BY l.position LIMIT $4",
            )
            .bind(after)
            .bind(through)
            .bind(vehicle_id)
            .bind(i64::from(limit))
            .bind(StoredSeverity(min_severity))
            .fetch_all(pool)
            .await?
        }))
    }

    /// The latest event log position (0 when the log is empty).
    pub async fn latest_alarm_position(&self) -> Result<i64, StoreError> {
        self.latest_log_position("alarm_event_log").await
    }

    /// The latest position of the event log table `log` (0 when it is empty); shared by the alarm
    /// and incident logs, whose positions are both a column `position`.
    pub(super) async fn latest_log_position(&self, log: &'static str) -> Result<i64, StoreError> {
        // `log` is one of this module's static table names, never input.
        let sql = format!("SELECT COALESCE(MAX(position), 0) FROM {log}");
        Ok(on_pool!(self, |pool| {
            sqlx::query_scalar::<_, i64>(sqlx::AssertSqlSafe(sql.as_str()))
                .fetch_one(pool)
                .await?
        }))
    }

    /// Start-up recovery: ends every open alarm that no stored session snapshot holds open (left
    /// by a crash, or by a session whose snapshot could not be stored) at wall time
    /// `ended_at_ms`, leaving `end_timestamp_s` NULL ("the session ended while alarming"), and
    /// logs each end with the seqs `first_seq`, `first_seq + 1`, … in id order. Returns the end
    /// events. An alarm a snapshot holds stays open: its session continues it wherever it resumes.
    pub async fn close_open_alarms(
        &self,
        ended_at_ms: i64,
        first_seq: i64,
    ) -> Result<Vec<AlarmEvent>, StoreError> {
        in_write_tx!(self, |tx| {
            let open = sqlx::query_as::<_, AlarmEventRow>(select_alarms!(
                "WHERE ended_at IS NULL AND id NOT IN (SELECT open_alarm_id FROM session_snapshots \
                 WHERE open_alarm_id IS NOT NULL) ORDER BY id"
            ))
            .fetch_all(&mut *tx)
            .await?;
            let mut events = Vec::with_capacity(open.len());
            for (seq, alarm) in (first_seq..).zip(open) {
                sqlx::query("UPDATE alarm_events SET ended_at = $2 WHERE id = $1")
                    .bind(alarm.id)
                    .bind(ended_at_ms)
                    .execute(&mut *tx)
                    .await?;
                let event = AlarmEvent {
                    seq,
                    kind: AlarmEventKind::End,
                    // Ended without a last sample time; its peak and samples as stored.
                    alarm: AlarmEventRow {
                        end_timestamp_s: None,
                        ended_at_ms: Some(ended_at_ms),
                        ..alarm
                    },
                };
                log_event!(tx, &event);
                events.push(event);
            }
            tx.commit().await?;
            Ok(events)
        })
    }
}
