//! Where a session's state goes between processes: its snapshots, read and written through the
//! session outbox, when they are due, and the expiry of the stored snapshots of vehicles that did
//! not come back; and the alarm events a session's state changes emit on the same queue, so that
//! a snapshot is stored with (or after) every event it includes.
//!
//! Owns the outbox handle, snapshot reads and writes, the snapshot policy, expiry and the building
//! of [`SnapshotRow`]s. Must not hold the session table (the caller hands in a session's state, and
//! to expiry whether the table holds a vehicle) or decide when an alarm starts or ends
//! (`super::episodes`).

use std::collections::HashMap;
use std::sync::{Arc, Mutex, PoisonError};
use std::time::{Duration, Instant};

use spoofwatch_core::explain::Explanation;
use spoofwatch_core::geo::LatLon;
use spoofwatch_core::sample::Sample;
use spoofwatch_core::severity::Severity;
use spoofwatch_proto::wire::{ModelName, VehicleId};
use tokio::sync::oneshot;

use super::handoff::{OpenAlarm, SNAPSHOT_SCHEMA, SessionSnapshot, SnapshotRefused, reads_schema};
use super::resume::Progress;
use super::snapshot_reads::{SnapshotReads, Unread, UnreadSince};
use super::state::SessionState;
use crate::access::Credential;
use crate::alarms::event::{Onset, OnsetWhy};
use crate::fault_log::FaultLog;
use crate::models::LoadedModel;
use crate::outbox::SessionOutbox;
use crate::store::{AlarmEventRow, SnapshotRow, Store, StoredCredential, now_unix_ms};

/// When sessions are snapshotted besides their stream's end, eviction, shutdown and alarm changes.
#[derive(Clone, Copy, Debug)]
pub struct SnapshotPolicy {
    /// After this many samples since the last snapshot (0: never by count).
    pub every_samples: u64,
    /// At the first batch this long after the last snapshot.
    pub every: Duration,
    /// A stored snapshot not rewritten for this long is deleted, and the alarm it held ends.
    pub ttl: Duration,
}

/// Most a stream's end waits for its session's snapshot to be stored before the call ends (longer
/// only while the database refuses; the snapshot stays queued).
pub const SNAPSHOT_WAIT: Duration = Duration::from_secs(2);

/// Snapshot versions expired per database transaction.
const EXPIRY_BATCH: usize = 500;

/// How often a stored reset reads a snapshot that was rewritten while it was deleted.
const RESET_ATTEMPTS: usize = 3;

/// Why the stored session of a vehicle this process does not hold could not be reset.
#[derive(Debug, thiserror::Error)]
pub enum StoredReset {
    #[error("the vehicle's last snapshot is still waiting to be stored; retry")]
    NotStoredYet,
    #[error("the vehicle's stored session cannot be read: {0}")]
    Unreadable(String),
    #[error(
        "the vehicle's stored session was rewritten while it was reset: another server process \
         streams it; reset it there (route the call with the x-vehicle-id header)"
    )]
    Rewritten,
    #[error(transparent)]
    Store(#[from] crate::store::StoreError),
}

/// A stored snapshot with how far its session got (read from its encoding, so that which copy is
/// newer never depends on the servers' clocks); one that cannot be read is refused.
pub(super) fn with_progress(row: SnapshotRow) -> Result<(SnapshotRow, Progress), SnapshotRefused> {
    if !reads_schema(row.schema_version) {
        return Err(SnapshotRefused::Schema {
            found: row.schema_version,
        });
    }
    let snapshot = SessionSnapshot::decode(&row.snapshot)?;
    let progress = Progress {
        last_timestamp_s: snapshot.last_timestamp_s,
        last_seq: snapshot.last_seq,
        samples: snapshot.samples,
    };
    Ok((row, progress))
}

/// The sessions' snapshots and alarm events, on their way to the store and back.
#[derive(Debug)]
pub(super) struct SessionKeeper {
    outbox: Arc<SessionOutbox>,
    /// Where snapshots are deleted and expired (they are written through the outbox).
    store: Store,
    /// Where snapshots are read, many vehicles' in one query.
    reads: SnapshotReads,
    /// How long vehicles have waited for a store that could not be read.
    unread_since: UnreadSince,
    policy: SnapshotPolicy,
    /// How long this process must see a snapshot unchanged, by its own clock, before it expires.
    confirmation: Duration,
    /// Stored snapshot versions (vehicle, written at) past the TTL, and when this process first
    /// saw each: they expire once seen unchanged long enough ([`Self::expire_snapshots`]).
    stale_seen: Mutex<HashMap<(String, i64), Instant>>,
    /// Whether expiring snapshots meets a store fault (logged when it starts and when it clears).
    expiry_fault: FaultLog,
}

impl SessionKeeper {
    /// A keeper whose sessions, held without a stream, are evicted after `idle`.
    pub(super) fn new(
        outbox: Arc<SessionOutbox>,
        store: Store,
        policy: SnapshotPolicy,
        idle: Duration,
    ) -> Self {
        Self {
            outbox,
            reads: SnapshotReads::start(store.clone()),
            unread_since: UnreadSince::default(),
            store,
            policy,
            // Longer than a held session goes without rewriting its snapshot (at least every
            // snapshot period while batches come; a session held without batches, up to the idle
            // limit, keeps its last copy).
            confirmation: idle + policy.every,
            stale_seen: Mutex::new(HashMap::new()),
            expiry_fault: FaultLog::default(),
        }
    }

    /// The process id written with snapshots (this start's alarm run: unique per process).
    pub(super) fn writer(&self) -> String {
        self.outbox.run_id().to_string()
    }

    /// Queues a snapshot of the session (see [`SessionOutbox::save_snapshot`]).
    pub(super) fn save(
        &self,
        vehicle_id: &VehicleId,
        state: &mut SessionState,
    ) -> oneshot::Receiver<()> {
        state.since_snapshot = 0;
        state.snapshot_taken = Instant::now();
        self.outbox
            .save_snapshot(self.snapshot_row(vehicle_id, state))
    }

    /// The stored form of a session's snapshot.
    fn snapshot_row(&self, vehicle_id: &VehicleId, state: &SessionState) -> SnapshotRow {
        let now_ms = now_unix_ms();
        let snapshot = state.snapshot();
        let open = snapshot.open_alarm.as_ref();
        SnapshotRow {
            vehicle_id: vehicle_id.to_string(),
            model_id: snapshot.model_id.clone(),
            schema_version: i64::from(SNAPSHOT_SCHEMA),
            samples: i64::try_from(state.samples).unwrap_or(i64::MAX),
            last_seq: i64::try_from(state.seqs.last()).unwrap_or(i64::MAX),
            open_alarm_id: open.map(|open| open.id),
            open_alarm_last_timestamp_s: open.map(|open| open.last_timestamp_s),
            open_alarm_peak_probability: open.map(|open| open.peak),
            open_alarm_samples: open.map(|open| i64::from(open.samples)),
            writer: self.writer(),
            updated_at_ms: now_ms,
            snapshot: snapshot.encode(),
        }
    }

    /// Snapshots a session that leaves this process (evicted, or at shutdown) unless nothing
    /// changed since its last snapshot: that copy is stored or queued already, and by now the
    /// vehicle may have moved on to another process, whose newer snapshot must not be overwritten
    /// by this stale one.
    pub(super) fn save_if_changed(&self, vehicle_id: &VehicleId, state: &mut SessionState) {
        if state.since_snapshot > 0 {
            self.save(vehicle_id, state);
        }
    }

    /// Whether the policy wants a snapshot now (checked after each batch).
    pub(super) fn snapshot_due(&self, state: &SessionState) -> bool {
        let policy = &self.policy;
        (policy.every_samples > 0 && state.since_snapshot >= policy.every_samples)
            || state.snapshot_taken.elapsed() >= policy.every
    }

    /// Replaces a session's state: the alarm the old state held ends (unless the new state holds
    /// it: a restore), and the new state is snapshotted at once, so that no process continues the
    /// old one.
    pub(super) fn replace_state(
        &self,
        vehicle_id: &VehicleId,
        state: &mut SessionState,
        new: SessionState,
    ) {
        if state.alarm.ends_when_replaced_by(&new.alarm) {
            self.close_alarm(state);
        }
        *state = new;
        if let Some(row) = state
            .alarm
            .open_row(vehicle_id.as_str(), state.model.name.id())
        {
            self.outbox.adopt(row);
        }
        self.save(vehicle_id, state);
    }

    /// The vehicle's latest snapshot: queued here and not stored yet, else stored.
    pub(super) async fn stored_snapshot(
        &self,
        vehicle_id: &VehicleId,
    ) -> Result<Option<SnapshotRow>, SnapshotRefused> {
        if let Some(queued) = self.outbox.queued_snapshot(vehicle_id.as_str()) {
            return Ok(Some(queued));
        }
        let read = self.reads.read(vehicle_id.as_str());
        let unread = match tokio::time::timeout(SNAPSHOT_WAIT, read).await {
            Ok(Ok(row)) => {
                self.unread_since.read(vehicle_id.as_str());
                return Ok(row);
            }
            Ok(Err(unread)) => unread,
            Err(_) => Unread::no_answer_within(SNAPSHOT_WAIT),
        };
        let retry = unread.may_pass && self.unread_since.may_wait(vehicle_id.as_str());
        Err(SnapshotRefused::Unreadable {
            why: unread.why,
            retry,
        })
    }

    /// The session a stored snapshot continues under `model`.
    pub(super) fn restore(
        &self,
        row: &SnapshotRow,
        model: &LoadedModel,
    ) -> Result<SessionState, SnapshotRefused> {
        if !reads_schema(row.schema_version) {
            return Err(SnapshotRefused::Schema {
                found: row.schema_version,
            });
        }
        let snapshot = SessionSnapshot::decode(&row.snapshot)?;
        SessionState::restore(model.clone(), snapshot)
    }

    /// Queues an alarm onset of `severity` (with `why`, the onset sample's explanation) and opens
    /// its episode under the id the outbox gave it.
    pub(super) fn record_onset(
        &self,
        state: &mut SessionState,
        vehicle: &VehicleId,
        sample: &Sample,
        (p, severity): (f64, Severity),
        why: &Explanation,
        credential: &Credential,
    ) {
        let onset_at_ms = now_unix_ms();
        let timestamp_s = sample.timestamp_s;
        let credential = StoredCredential {
            credential: Some(credential.label.to_string()),
            credential_per_vehicle: credential.per_vehicle,
        };
        let id = self.outbox.onset(&Onset {
            vehicle_id: vehicle.as_str(),
            model_id: state.model.name.id(),
            timestamp_s,
            at_ms: onset_at_ms,
            probability: p,
            severity,
            why: Some(OnsetWhy {
                explanation: why,
                fix: LatLon::new(sample.latitude_deg, sample.longitude_deg),
            }),
            credential: &credential,
        });
        state
            .alarm
            .open(id, (timestamp_s, onset_at_ms), p, severity, &credential);
    }

    /// Makes the session's open episode critical from the sample at `timestamp_s` and queues the
    /// escalation.
    pub(super) fn record_escalation(&self, state: &mut SessionState, timestamp_s: f64) {
        let at_ms = now_unix_ms();
        if let Some(open) = state.alarm.escalate(timestamp_s, at_ms) {
            self.outbox
                .escalate(open.id, timestamp_s, at_ms, open.peak, open.samples);
        }
    }

    /// Queues the end of an episode at its last alarming sample.
    pub(super) fn record_end(&self, episode: OpenAlarm) {
        self.outbox.end(
            episode.id,
            episode.last_timestamp_s,
            episode.peak,
            episode.samples,
            episode.severity(),
        );
    }

    /// Ends the alarm a stored session of another model held open: that session is replaced by a
    /// fresh one under the model now asked for (a roll-out), so no process will continue it. (A
    /// session replaced in this process's memory ends its alarm in [`Self::replace_state`].)
    pub(super) fn end_alarm_of_replaced(&self, vehicle_id: &VehicleId, row: &SnapshotRow) {
        let Some(open) = SessionSnapshot::decode(&row.snapshot)
            .ok()
            .and_then(|snapshot| snapshot.open_alarm)
        else {
            return;
        };
        self.outbox
            .adopt(open.row(vehicle_id.as_str(), &row.model_id));
        self.record_end(open);
    }

    /// Ends the session's open episode, if any (when the session ends, resets or changes model
    /// while alarming).
    pub(super) fn close_alarm(&self, state: &mut SessionState) {
        if let Some(episode) = state.alarm.close() {
            self.record_end(episode);
        }
    }

    /// Deletes the stored snapshots of a deleted model (they would be refused anyway; a failure
    /// only leaves them so).
    pub(super) async fn delete_snapshots_of_model(&self, name: &ModelName) {
        if let Err(error) = self.store.delete_snapshots_of_model(name.id()).await {
            tracing::warn!(%error, model = %name, "could not delete the deleted model's session snapshots");
        }
    }

    /// Deletes the stored snapshots whose vehicles did not come back and ends the alarms they held
    /// open, at their last alarming sample; returns how many alarms ended.
    ///
    /// A snapshot expires when it is older than the policy's TTL by its writer's clock, and this
    /// process has also seen it unchanged for the confirmation period (longer than a held session
    /// goes without rewriting it) by its own monotonic clock, and `held` says this process does not
    /// hold the vehicle's session. So a wall-clock step, here or on another replica, never ends the
    /// alarm of a vehicle that is still streaming: a streaming vehicle's snapshot is rewritten far
    /// sooner than the confirmation takes.
    pub(super) async fn expire_snapshots(&self, held: impl Fn(&str) -> bool) -> usize {
        let ttl_ms = i64::try_from(self.policy.ttl.as_millis()).unwrap_or(i64::MAX);
        let stale = match self
            .store
            .stale_snapshots(now_unix_ms().saturating_sub(ttl_ms))
            .await
        {
            Ok(stale) => stale,
            Err(error) => {
                if self.expiry_fault.failed() {
                    tracing::warn!(%error, "could not read old session snapshots; retrying later");
                }
                return 0;
            }
        };
        let confirmed = self.confirmed(stale, held);
        let mut ended = 0;
        // A few hundred per transaction: a mass expiry never holds the database's write lock long.
        for batch in confirmed.chunks(EXPIRY_BATCH) {
            let expired = match self.store.expire_snapshots(batch).await {
                Ok(expired) => expired,
                Err(error) => {
                    if self.expiry_fault.failed() {
                        tracing::warn!(%error, "could not expire old session snapshots; retrying later");
                    }
                    return ended;
                }
            };
            let mut seen = self.stale_seen();
            for version in batch {
                seen.remove(version);
            }
            drop(seen);
            // Seen afresh, such a version is tried again after another confirmation period.
            for ((vehicle, updated_at_ms), reason) in expired.unreadable {
                tracing::warn!(
                    vehicle = %vehicle,
                    updated_at_ms,
                    reason,
                    "a session snapshot cannot expire: its rows cannot be read; the other \
                     snapshots expire as usual"
                );
            }
            ended += expired.abandoned.len();
            for (alarm, snapshot) in expired.abandoned {
                self.end_abandoned(alarm, &snapshot);
            }
        }
        if self.expiry_fault.succeeded() {
            tracing::info!("session snapshots expire again: the store reads and writes them");
        }
        ended
    }

    /// Ends an alarm whose stored session will not continue it, at the last alarming sample its
    /// `snapshot` holds (as stored at its onset when the snapshot cannot be read).
    fn end_abandoned(&self, alarm: AlarmEventRow, snapshot: &[u8]) {
        let last = SessionSnapshot::decode(snapshot)
            .ok()
            .and_then(|s| s.open_alarm)
            .filter(|open| open.id == alarm.id)
            .map(|open| (open.last_timestamp_s, open.peak, i64::from(open.samples)));
        self.outbox.end_abandoned(alarm, last);
    }

    /// Resets the stored session of a vehicle this process does not hold (its session evicted, or
    /// held by no process since a restart): its snapshot is deleted and the alarm it held open
    /// ends at its last alarming sample, as when the snapshot expires. Returns the model id the
    /// session ran, or `None` when no snapshot of the vehicle is stored.
    ///
    /// A snapshot still queued here is stored first (waiting at most [`SNAPSHOT_WAIT`]); a version
    /// rewritten meanwhile (the vehicle streaming on another process) is read again, a few times.
    pub(super) async fn reset_stored(
        &self,
        vehicle_id: &VehicleId,
    ) -> Result<Option<String>, StoredReset> {
        if let Some(stored) = self.outbox.snapshot_stored(vehicle_id.as_str())
            && !matches!(
                tokio::time::timeout(SNAPSHOT_WAIT, stored).await,
                Ok(Ok(()))
            )
        {
            return Err(StoredReset::NotStoredYet);
        }
        for _ in 0..RESET_ATTEMPTS {
            let Some(row) = self.store.load_snapshot(vehicle_id.as_str()).await? else {
                return Ok(None);
            };
            let version = (row.vehicle_id.clone(), row.updated_at_ms);
            let expired = self
                .store
                .expire_snapshots(std::slice::from_ref(&version))
                .await?;
            if let Some((_, reason)) = expired.unreadable.into_iter().next() {
                return Err(StoredReset::Unreadable(reason));
            }
            for (alarm, snapshot) in expired.abandoned {
                self.end_abandoned(alarm, &snapshot);
            }
            match self.store.load_snapshot(vehicle_id.as_str()).await? {
                Some(newer) if newer.updated_at_ms != version.1 || newer.writer != row.writer => {}
                _ => return Ok(Some(row.model_id)),
            }
        }
        Err(StoredReset::Rewritten)
    }

    /// Of the `stale` versions of vehicles this process does not hold, those seen unchanged for
    /// the confirmation period; the others are remembered with when they were first seen.
    fn confirmed(
        &self,
        stale: Vec<(String, i64)>,
        held: impl Fn(&str) -> bool,
    ) -> Vec<(String, i64)> {
        let mut seen = self.stale_seen();
        let now = Instant::now();
        let candidates: HashMap<(String, i64), Instant> = stale
            .into_iter()
            .filter(|(vehicle, _)| !held(vehicle))
            .map(|version| {
                let first_seen = seen.get(&version).copied().unwrap_or(now);
                (version, first_seen)
            })
            .collect();
        *seen = candidates;
        seen.iter()
            .filter(|(_, first_seen)| now.duration_since(**first_seen) >= self.confirmation)
            .map(|(version, _)| version.clone())
            .collect()
    }

    fn stale_seen(&self) -> std::sync::MutexGuard<'_, HashMap<(String, i64), Instant>> {
        self.stale_seen
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
    }
}

#[cfg(test)]
mod tests {
    use super::super::state::test_model;
    use super::*;

    fn model(id: &str) -> LoadedModel {
        test_model(id)
    }

    fn policy(every_samples: u64, every: Duration) -> SnapshotPolicy {
        SnapshotPolicy {
            every_samples,
            every,
            ttl: Duration::from_secs(3_600),
        }
    }

    async fn keeper(policy: SnapshotPolicy) -> (tempfile::TempDir, SessionKeeper) {
        let dir = tempfile::tempdir().expect("temp dir");
        let path = dir.path().join("spoofwatch.db");
        let store = Store::open(&path.to_string_lossy()).await.expect("open");
        let outbox = Arc::new(SessionOutbox::new(&store, 100).await.expect("outbox"));
        (
            dir,
            SessionKeeper::new(outbox, store, policy, Duration::ZERO),
        )
    }

    #[tokio::test]
    async fn a_saved_session_reads_back_queued_and_restores_under_its_model() {
        let (_dir, keeper) = keeper(policy(0, Duration::from_secs(60))).await;
        let vehicle = VehicleId::parse("car-1").expect("a vehicle id");
        let mut state = SessionState::new(model("m"));
        state.samples = 7;
        state.seqs.apply(3);
        state.since_snapshot = 7;
        let _receipt = keeper.save(&vehicle, &mut state);
        assert_eq!(state.since_snapshot, 0);
        let row = keeper
            .stored_snapshot(&vehicle)
            .await
            .expect("readable")
            .expect("queued");
        assert_eq!(
            (row.vehicle_id.as_str(), row.model_id.as_str()),
            ("car-1", "m")
        );
        assert_eq!((row.samples, row.last_seq), (7, 3));
        assert_eq!(row.schema_version, i64::from(SNAPSHOT_SCHEMA));
        assert_eq!(row.writer, keeper.writer());
        let (_, progress) = with_progress(row.clone()).expect("progress");
        assert_eq!((progress.samples, progress.last_seq), (7, 3));
        let restored = keeper.restore(&row, &model("m")).expect("restores");
        assert_eq!(restored.samples, 7);
        assert!(matches!(
            keeper.restore(&row, &model("other")),
            Err(SnapshotRefused::Model { .. })
        ));
        let future = SnapshotRow {
            schema_version: i64::from(SNAPSHOT_SCHEMA) + 1,
            ..row
        };
        assert!(matches!(
            with_progress(future),
            Err(SnapshotRefused::Schema { .. })
        ));
    }

    #[tokio::test]
    async fn a_snapshot_is_due_by_samples_or_by_time() {
        let (_dir, by_count) = keeper(policy(5, Duration::from_secs(3_600))).await;
        let mut state = SessionState::new(model("m"));
        state.since_snapshot = 4;
        assert!(!by_count.snapshot_due(&state));
        state.since_snapshot = 5;
        assert!(by_count.snapshot_due(&state));
        let (_dir, by_time) = keeper(policy(0, Duration::ZERO)).await;
        state.since_snapshot = 0;
        assert!(by_time.snapshot_due(&state));
    }

    #[tokio::test]
    async fn an_unchanged_session_is_not_saved_again() {
        let (_dir, keeper) = keeper(policy(0, Duration::from_secs(60))).await;
        let vehicle = VehicleId::parse("car-2").expect("a vehicle id");
        let mut state = SessionState::new(model("m"));
        keeper.save_if_changed(&vehicle, &mut state);
        assert!(keeper.outbox.queued_snapshot("car-2").is_none());
        state.since_snapshot = 1;
        keeper.save_if_changed(&vehicle, &mut state);
        assert!(keeper.outbox.queued_snapshot("car-2").is_some());
    }
}
