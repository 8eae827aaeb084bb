//! Area incidents: one row per incident (as its latest change left it), the event log behind
//! WatchIncidents, and the correlator's lease, read position and state.
//!
//! Exactly one process computes incidents at a time: the holder of the correlator's lease
//! ([`Store::claim_incident_correlator`]), which it renews while it works and another process takes
//! over once it expires. Each correlation step is one write transaction, fenced on the lease: the
//! changed incidents, their events, how far the alarm event log has been read and the correlator's
//! state commit together or not at all, so a holder killed at any point leaves a state the next
//! one continues exactly.
//!
//! An admin may end an open incident by hand ([`Store::close_incident`]): the row records how,
//! why and by whom (schema version 12), and from then on no correlation step writes to it (the
//! correlator drops it from its state on its next step, [`Store::closed_incidents_among`]).
//!
//! The store does not interpret the incident and state JSON (the correlator's own types, written by
//! `crate::incidents`). It owns these tables and their reads; it must not know alarms (it reads
//! none of their tables).

use sqlx::types::Json;

use super::paging::PagePlan;
use super::{Page, PageRequest, Store, StoreError};

/// A stored incident.
#[derive(Debug, Clone, PartialEq, sqlx::FromRow)]
pub struct IncidentRow {
    /// The correlator's id.
    pub id: i64,
    /// Wall-clock time it was stored as opened (unix ms).
    #[sqlx(rename = "opened_at")]
    pub opened_at_ms: i64,
    /// Wall-clock time it was stored as ended; `None` while open.
    #[sqlx(rename = "ended_at")]
    pub ended_at_ms: Option<i64>,
    /// The incident as its latest change left it.
    #[sqlx(json, rename = "body_json")]
    pub body: serde_json::Value,
    /// How an admin ended it; `None` while open and when it ended on its own.
    #[sqlx(flatten)]
    pub closure: StoredClosure,
}

/// How an admin ended an incident by hand.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ClosureKind {
    /// The threat is over.
    Ended,
    /// It was never real.
    Dismissed,
}

impl ClosureKind {
    /// The lowercase name stored in the database.
    pub fn as_str(self) -> &'static str {
        match self {
            ClosureKind::Ended => "ended",
            ClosureKind::Dismissed => "dismissed",
        }
    }

    fn from_str_opt(name: &str) -> Option<Self> {
        match name {
            "ended" => Some(ClosureKind::Ended),
            "dismissed" => Some(ClosureKind::Dismissed),
            _ => None,
        }
    }
}

text_enum!(ClosureKind);

/// The closure columns of an incident row: all `None` unless an admin ended it.
#[derive(Debug, Clone, Default, PartialEq, Eq, sqlx::FromRow)]
pub struct StoredClosure {
    pub closed_as: Option<ClosureKind>,
    pub closed_reason: Option<String>,
    /// The credential label of the call (never a secret).
    pub closed_by: Option<String>,
}

/// An admin's closure of an incident, as [`Store::close_incident`] records it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Closure {
    pub kind: ClosureKind,
    pub reason: String,
    pub by: String,
}

impl StoredClosure {
    /// The closure, when one is recorded.
    pub fn get(&self) -> Option<Closure> {
        Some(Closure {
            kind: self.closed_as?,
            reason: self.closed_reason.clone().unwrap_or_default(),
            by: self.closed_by.clone().unwrap_or_default(),
        })
    }
}

/// What [`Store::close_incident`] found.
#[derive(Debug, Clone, PartialEq)]
pub enum CloseOutcome {
    /// It was open and is now ended, as the row shows.
    Closed(IncidentRow),
    /// There is no incident with that id.
    NotFound,
    /// It had already ended (on its own or by hand); nothing changed.
    AlreadyEnded(IncidentRow),
}

/// What an incident event did.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum IncidentEventKind {
    Opened,
    Joined,
    Ended,
}

impl IncidentEventKind {
    /// The lowercase name stored in the database.
    pub fn as_str(self) -> &'static str {
        match self {
            IncidentEventKind::Opened => "opened",
            IncidentEventKind::Joined => "joined",
            IncidentEventKind::Ended => "ended",
        }
    }

    fn from_str_opt(name: &str) -> Option<Self> {
        match name {
            "opened" => Some(IncidentEventKind::Opened),
            "joined" => Some(IncidentEventKind::Joined),
            "ended" => Some(IncidentEventKind::Ended),
            _ => None,
        }
    }
}

text_enum!(IncidentEventKind);

/// An incident event as the log holds it.
#[derive(Debug, Clone, PartialEq, sqlx::FromRow)]
pub struct LoggedIncidentEvent {
    /// The WatchIncidents cursor: 1, 2, 3, … in commit order.
    pub position: i64,
    pub incident_id: i64,
    pub kind: IncidentEventKind,
    #[sqlx(rename = "stored_at")]
    pub stored_at_ms: i64,
    /// When the incident was stored as opened.
    #[sqlx(rename = "opened_at")]
    pub opened_at_ms: i64,
    /// The incident as this event left it.
    #[sqlx(json, rename = "body_json")]
    pub body: serde_json::Value,
    /// The incident's closure by hand, if any (an ENDED event of such an incident is the closure's).
    #[sqlx(flatten)]
    pub closure: StoredClosure,
}

/// The columns of an incident row, in [`IncidentRow`]'s order.
macro_rules! incident_columns {
    () => {
        "id, opened_at, ended_at, body_json, closed_as, closed_reason, closed_by"
    };
}

/// The correlator's place, as the lease holder continues from it.
#[derive(Debug, Clone, PartialEq, sqlx::FromRow)]
pub struct CorrelatorPlace {
    /// The last alarm event log position correlated.
    pub alarm_position: i64,
    /// The correlator's state; `None` before the first step.
    #[sqlx(json(nullable), rename = "state_json")]
    pub state: Option<serde_json::Value>,
}

/// One incident as a correlation step changed it.
#[derive(Debug, Clone, PartialEq)]
pub struct IncidentWrite {
    pub id: i64,
    /// The event to log; `None` for a change the row keeps but watchers are not sent (a member's
    /// alarm opening again or ending).
    pub event: Option<IncidentEventKind>,
    /// The incident has ended.
    pub ended: bool,
    pub body: serde_json::Value,
}

/// One correlation step: what it changed and where it leaves the correlator.
#[derive(Debug, Clone, PartialEq)]
pub struct CorrelationStep {
    /// In the order they happened.
    pub incidents: Vec<IncidentWrite>,
    pub place: CorrelatorPlace,
}

/// Which incidents ListIncidents returns.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub enum IncidentState {
    #[default]
    Any,
    Open,
    Ended,
}

/// Listing name inside page tokens.
const LISTING: &str = "incidents";

impl Store {
    /// Takes the correlator's lease for `owner` if it is free, expired (no heartbeat for
    /// `lease_ms`) or already `owner`'s, renewing it; returns where the correlator stands, or
    /// `None` when another process holds the lease.
    pub async fn claim_incident_correlator(
        &self,
        owner: &str,
        now_ms: i64,
        lease_ms: i64,
    ) -> Result<Option<CorrelatorPlace>, StoreError> {
        in_write_tx!(self, |tx| {
            let place = sqlx::query_as::<_, CorrelatorPlace>(
                "UPDATE incident_correlator SET owner = $1, heartbeat_at = $2 \
                 WHERE id = 1 AND (owner IS NULL OR heartbeat_at IS NULL OR owner = $1 \
                 OR heartbeat_at < $3) RETURNING alarm_position, state_json",
            )
            .bind(owner)
            .bind(now_ms)
            .bind(now_ms.saturating_sub(lease_ms))
            .fetch_optional(&mut *tx)
            .await?;
            tx.commit().await?;
            Ok(place)
        })
    }

    /// Gives the lease up (at shutdown), so that another process takes over at once.
    pub async fn release_incident_correlator(&self, owner: &str) -> Result<(), StoreError> {
        on_pool!(self, |pool| {
            sqlx::query(
                "UPDATE incident_correlator SET owner = NULL, heartbeat_at = NULL \
                 WHERE id = 1 AND owner = $1",
            )
            .bind(owner)
            .execute(pool)
            .await?;
        });
        Ok(())
    }

    /// Stores `step` if `owner` still holds the lease (renewing it); returns whether it did. The
    /// incidents, their events at the next log positions, the read position and the state commit
    /// together.
    pub async fn write_correlation_step(
        &self,
        owner: &str,
        now_ms: i64,
        step: &CorrelationStep,
    ) -> Result<bool, StoreError> {
        in_write_tx!(self, |tx| {
            let held = sqlx::query(
                "UPDATE incident_correlator SET heartbeat_at = $2, alarm_position = $3, \
                 state_json = $4 WHERE id = 1 AND owner = $1",
            )
            .bind(owner)
            .bind(now_ms)
            .bind(step.place.alarm_position)
            .bind(step.place.state.as_ref().map(Json))
            .execute(&mut *tx)
            .await?
            .rows_affected();
            if held == 0 {
                return Ok(false);
            }
            for write in &step.incidents {
                // An incident an admin ended is never written again: the correlator's state still
                // held it open, and drops it on its next step.
                let written = sqlx::query(
                    "INSERT INTO incidents (id, opened_at, ended_at, body_json) \
                     VALUES ($1, $2, $3, $4) ON CONFLICT (id) DO UPDATE \
                     SET ended_at = excluded.ended_at, body_json = excluded.body_json \
                     WHERE incidents.closed_as IS NULL",
                )
                .bind(write.id)
                .bind(now_ms)
                .bind(write.ended.then_some(now_ms))
                .bind(Json(&write.body))
                .execute(&mut *tx)
                .await?
                .rows_affected();
                if written == 0 {
                    continue;
                }
                if let Some(kind) = write.event {
                    sqlx::query(
                        "INSERT INTO incident_event_log (position, incident_id, kind, stored_at, \
                         body_json) VALUES \
                         ((SELECT COALESCE(MAX(position), 0) + 1 FROM incident_event_log), \
                         $1, $2, $3, $4)",
                    )
                    .bind(write.id)
                    .bind(kind)
                    .bind(now_ms)
                    .bind(Json(&write.body))
                    .execute(&mut *tx)
                    .await?;
                }
            }
            tx.commit().await?;
            Ok(true)
        })
    }

    /// One page of the incidents in `state`, in id order.
    ///
    /// [`StoreError::InvalidPageToken`] for a token this listing did not issue.
    pub async fn list_incidents(
        &self,
        state: IncidentState,
        page: &PageRequest,
    ) -> Result<Page<IncidentRow>, StoreError> {
        let state = match state {
            IncidentState::Any => "any",
            IncidentState::Open => "open",
            IncidentState::Ended => "ended",
        };
        let plan = PagePlan::new(LISTING, page)?;
        // Incidents page by id alone, as alarms do: the token's time slot carries the last id.
        let rows = on_pool!(self, |pool| {
            sqlx::query_as::<_, IncidentRow>(concat!(
                "SELECT ",
                incident_columns!(),
                " FROM incidents WHERE ($1 = 'any' OR ($1 = 'open') = (ended_at IS NULL)) \
                 AND ($2 IS NULL OR id > $2) ORDER BY id LIMIT $3"
            ))
            .bind(state)
            .bind(plan.after_created_at())
            .bind(plan.fetch_limit())
            .fetch_all(pool)
            .await?
        });
        Ok(plan.finish(LISTING, rows, |row| (row.id, "")))
    }

    /// One incident.
    pub async fn get_incident(&self, id: i64) -> Result<Option<IncidentRow>, StoreError> {
        Ok(on_pool!(self, |pool| {
            sqlx::query_as::<_, IncidentRow>(concat!(
                "SELECT ",
                incident_columns!(),
                " FROM incidents WHERE id = $1"
            ))
            .bind(id)
            .fetch_optional(pool)
            .await?
        }))
    }

    /// The open incidents, in id order.
    pub async fn open_incidents(&self) -> Result<Vec<IncidentRow>, StoreError> {
        Ok(on_pool!(self, |pool| {
            sqlx::query_as::<_, IncidentRow>(concat!(
                "SELECT ",
                incident_columns!(),
                " FROM incidents WHERE ended_at IS NULL ORDER BY id"
            ))
            .fetch_all(pool)
            .await?
        }))
    }

    /// The logged incident events with `after < position <= through`, in position order, at most
    /// `limit`.
    pub async fn incident_events_after(
        &self,
        after: i64,
        through: i64,
        limit: u32,
    ) -> Result<Vec<LoggedIncidentEvent>, StoreError> {
        Ok(on_pool!(self, |pool| {
            sqlx::query_as::<_, LoggedIncidentEvent>(
                "SELECT l.position, l.incident_id, l.kind, l.stored_at, i.opened_at, l.body_json, \
                 i.closed_as, i.closed_reason, i.closed_by FROM incident_event_log l JOIN incidents i ON i.id = l.incident_id \
                 WHERE l.position > $1 AND l.position <= $2 ORDER BY l.position LIMIT $3",
            )
            .bind(after)
            .bind(through)
            .bind(i64::from(limit))
            .fetch_all(pool)
            .await?
        }))
    }

    /// Ends the open incident `id` by hand, at `now_ms`: records `closure` with it, stores the
    /// body `edit` makes of its current one (the caller's incident JSON, as it ended) and logs its
    /// ENDED event, in one write transaction. An incident that is not there, or has already ended,
    /// is left as it is.
    pub async fn close_incident(
        &self,
        id: i64,
        closure: &Closure,
        now_ms: i64,
        edit: impl FnOnce(serde_json::Value) -> Result<serde_json::Value, StoreError>,
    ) -> Result<CloseOutcome, StoreError> {
        in_write_tx!(self, |tx| {
            let row = sqlx::query_as::<_, IncidentRow>(concat!(
                "SELECT ",
                incident_columns!(),
                " FROM incidents WHERE id = $1"
            ))
            .bind(id)
            .fetch_optional(&mut *tx)
            .await?;
            let Some(mut row) = row else {
                return Ok(CloseOutcome::NotFound);
            };
            if row.ended_at_ms.is_some() {
                return Ok(CloseOutcome::AlreadyEnded(row));
            }
            row.body = edit(row.body)?;
            row.ended_at_ms = Some(now_ms);
            row.closure = StoredClosure {
                closed_as: Some(closure.kind),
                closed_reason: Some(closure.reason.clone()),
                closed_by: Some(closure.by.clone()),
            };
            sqlx::query(
                "UPDATE incidents SET ended_at = $2, body_json = $3, closed_as = $4, \
                 closed_reason = $5, closed_by = $6 WHERE id = $1",
            )
            .bind(id)
            .bind(now_ms)
            .bind(Json(&row.body))
            .bind(closure.kind)
            .bind(&closure.reason)
            .bind(&closure.by)
            .execute(&mut *tx)
            .await?;
            sqlx::query(
                "INSERT INTO incident_event_log (position, incident_id, kind, stored_at, \
                 body_json) VALUES \
                 ((SELECT COALESCE(MAX(position), 0) + 1 FROM incident_event_log), \
                 $1, $2, $3, $4)",
            )
            .bind(id)
            .bind(IncidentEventKind::Ended)
            .bind(now_ms)
            .bind(Json(&row.body))
            .execute(&mut *tx)
            .await?;
            tx.commit().await?;
            Ok(CloseOutcome::Closed(row))
        })
    }

    /// Of the incidents with ids in `from..=through`, those an admin ended by hand, in id order
    /// (the correlator drops them from the incidents its state holds open).
    pub async fn closed_incidents_among(
        &self,
        from: i64,
        through: i64,
    ) -> Result<Vec<i64>, StoreError> {
        Ok(on_pool!(self, |pool| {
            sqlx::query_scalar::<_, i64>(
                "SELECT id FROM incidents WHERE closed_as IS NOT NULL AND id >= $1 AND id <= $2 \
                 ORDER BY id",
            )
            .bind(from)
            .bind(through)
            .fetch_all(pool)
            .await?
        }))
    }

    /// The latest incident event log position (0 when the log is empty).
    pub async fn latest_incident_position(&self) -> Result<i64, StoreError> {
        self.latest_log_position("incident_event_log").await
    }
}
