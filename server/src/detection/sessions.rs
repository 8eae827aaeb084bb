//! Per-vehicle sessions: a detector each, ownership by at most one stream (a newer stream takes
//! over), a bounded count, idle eviction, and alarm onsets/ends handed to the session outbox (never a
//! database call while a session is locked).
//!
//! Hand-off: a session's complete state is snapshotted ([`super::handoff`]) through the outbox when
//! its stream ends, when it is evicted, at shutdown, when it starts afresh, with every alarm onset or
//! end, and every [`SnapshotPolicy::every_samples`] samples or [`SnapshotPolicy::every`]. A stream
//! that starts for a vehicle this process does not hold (or holds an older copy of) continues from
//! the stored snapshot; one that cannot be used (corrupt, another schema or model) is refused with
//! its reason and the session starts afresh (the decision is [`super::resume`]'s). An alarm stays
//! open across a hand-off.
//!
//! Alarm episodes are followed by [`super::episodes`]; this module records what they report. A
//! sample inside an open area incident ([`IncidentAreas`]) is scored with the area prior.
//!
//! Roll-out: a session started or resumed without a model follows the active model (a fresh
//! detector when it changed); deleting a model ends the sessions that use it.
//! Speaks core types ([`Sample`], [`Decision`]) and [`SessionError`]; it must not know about gRPC
//! messages or statuses (the edge is `detection::service`).

use std::collections::HashMap;
use std::sync::atomic::{AtomicI64, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, PoisonError};
use std::time::{Duration, Instant};

use spoofwatch_core::detector::{Decision, Detector};
use spoofwatch_core::explain::Explanation;
use spoofwatch_core::geo::LatLon;
use spoofwatch_core::sample::Sample;
use spoofwatch_proto::wire::{ModelName, VehicleId};
use tokio::sync::oneshot;
use tokio_util::sync::CancellationToken;

use super::episodes::{AlarmSignal, EpisodeChange};
use super::handoff::{OpenAlarm, SNAPSHOT_SCHEMA, SessionSnapshot, SnapshotRefused, reads_schema};
use super::resume::{Origin, Progress, Resumption, Start};
use super::sequence::SeqCheck;
use super::snapshot_reads::{SnapshotReads, UNREAD_GRACE, Unread, UnreadSince};
use super::state::SessionState;
use super::validate::validate_batch;
use crate::alarms::why::OnsetWhy;
use crate::incidents::areas::IncidentAreas;
use crate::models::{LoadedModel, Registry, RegistryError};
use crate::outbox::SessionOutbox;
use crate::store::{SnapshotRow, Store, now_unix_ms};
use crate::telemetry;
use crate::work::HeavyWork;

/// Everything a session operation can fail with.
#[derive(Debug, thiserror::Error)]
pub enum SessionError {
    /// The batch is invalid; one `(field, problem)` per violation. Nothing was applied.
    #[error("invalid batch")]
    InvalidBatch(Vec<(String, String)>),
    /// No session for this vehicle.
    #[error("session {0:?} not found")]
    NotFound(String),
    /// The session table is full, and every session in it has a stream.
    #[error("the server holds its maximum of {0} vehicle sessions, each with a live stream")]
    Full(usize),
    /// The caller created its quota of sessions.
    #[error("{identity} holds its quota of {limit} vehicle sessions (--max-sessions-per-identity)")]
    Quota { identity: String, limit: usize },
    /// The requested model cannot be served.
    #[error(transparent)]
    Model(#[from] RegistryError),
    /// The vehicle's stored session could not be read, and this process holds none to go on
    /// with: the stream is refused rather than start afresh behind it.
    #[error(
        "the vehicle's stored session could not be read ({0}); retry to resume it (after {grace} s \
         of this it starts afresh without it), or start with reset to begin afresh now",
        grace = UNREAD_GRACE.as_secs()
    )]
    SnapshotUnreadable(String),
    /// The session's model was deleted: the session ended.
    #[error(
        "{0} was deleted, which ended this session; start a new one (an empty model follows the active model)"
    )]
    ModelDeleted(ModelName),
}

/// A vehicle, and the identity of the caller that sends its batch (whose session quota a new
/// session counts against).
#[derive(Clone, Copy, Debug)]
pub struct ForVehicle<'a> {
    pub vehicle_id: &'a VehicleId,
    pub identity: &'a Arc<str>,
}

/// A session found or made for a vehicle: `existed` before; `made_room`, the session evicted to
/// make room for it (to be snapshotted).
struct Admitted {
    slot: Arc<SessionSlot>,
    existed: bool,
    made_room: Option<Arc<SessionSlot>>,
}

/// What a stream learns when it attaches.
#[derive(Clone, Debug)]
pub struct Accepted {
    pub vehicle_id: VehicleId,
    pub model: ModelName,
    pub resumed: bool,
    pub samples_seen: u64,
    pub last_seq: u64,
    /// The session existed with this other model and started afresh with `model`.
    pub replaced_model: Option<ModelName>,
    /// The session continued from its stored snapshot (not from this process's memory).
    pub from_snapshot: bool,
    /// Why the vehicle's stored snapshot was not used (the session started afresh).
    pub snapshot_refused: Option<SnapshotRefused>,
}

/// A processed batch: one decision per sample, in order, by `model`; none when `duplicate` (its
/// seq was applied before, so it was not scored again).
#[derive(Clone, Debug)]
pub struct Decisions {
    pub model: ModelName,
    pub decisions: Vec<Decision>,
    pub duplicate: bool,
}

/// A session as reported by ListSessions/GetSession.
#[derive(Clone, Debug)]
pub struct SessionSummary {
    pub vehicle_id: VehicleId,
    pub model: ModelName,
    pub connected: bool,
    pub samples: u64,
    pub trajectories: u32,
    pub alarm_active: bool,
    pub alarms_raised: u64,
    pub last_seq: u64,
    pub last_timestamp_s: Option<f64>,
    pub last_activity_ms: i64,
}

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

/// Bounds on the in-memory session table.
#[derive(Clone, Copy, Debug)]
pub struct SessionLimits {
    pub max_sessions: usize,
    /// Most sessions one identity (a token or certificate) may create.
    pub max_per_identity: usize,
    /// A session with no stream attached is evicted after this long without activity.
    pub idle: Duration,
    /// Most samples in one batch.
    pub max_batch_samples: usize,
}

#[derive(Debug)]
struct StreamOwner {
    id: u64,
    evicted: CancellationToken,
}

/// One vehicle's session.
#[derive(Debug)]
pub struct SessionSlot {
    vehicle_id: VehicleId,
    /// The identity whose call created it (it counts against that identity's quota).
    created_by: Arc<str>,
    state: tokio::sync::Mutex<SessionState>,
    owner: Mutex<Option<StreamOwner>>,
    last_activity_ms: AtomicI64,
    /// Cancelled when the session's model is deleted: the session is gone and its stream ends.
    pub model_deleted: CancellationToken,
}

impl SessionSlot {
    fn touch(&self) {
        self.last_activity_ms
            .store(now_unix_ms(), Ordering::Relaxed);
    }

    fn connected(&self) -> bool {
        self.owner.lock().map(|o| o.is_some()).unwrap_or(false)
    }
}

/// A stream's hold on a session.
#[derive(Debug)]
pub struct Attachment {
    pub slot: Arc<SessionSlot>,
    pub stream_id: u64,
    /// Cancelled when a newer stream takes the session over.
    pub evicted: CancellationToken,
    pub accepted: Accepted,
}

/// One session fewer for `identity`.
fn forget_creator(per_identity: &mut HashMap<Arc<str>, usize>, identity: &Arc<str>) {
    if let Some(count) = per_identity.get_mut(identity) {
        *count = count.saturating_sub(1);
        if *count == 0 {
            per_identity.remove(identity);
        }
    }
}

/// A stored snapshot with how far its session got (read from its encoding, so that which copy is
/// newer never depends on the servers' clocks); one that cannot be read is refused.
fn with_progress(row: SnapshotRow) -> Result<(SnapshotRow, Progress), SnapshotRefused> {
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

/// The seq field beside a batch's samples field (`batch.samples` → `batch.seq`).
fn seq_field(samples_field: &str) -> String {
    let prefix = samples_field.strip_suffix("samples").unwrap_or("");
    format!("{prefix}seq")
}

/// What scoring `samples` samples with `model` costs, in parameters × samples.
fn batch_cost(model: &LoadedModel, samples: usize) -> usize {
    model
        .artifact
        .model
        .parameter_count()
        .saturating_mul(samples)
}

/// The session table.
#[derive(Debug)]
pub struct SessionManager {
    slots: Mutex<HashMap<VehicleId, Arc<SessionSlot>>>,
    registry: Arc<Registry>,
    outbox: Arc<SessionOutbox>,
    /// Where snapshots are deleted and expired (they are written through the outbox).
    store: Store,
    /// Where snapshots are read, many vehicles' in one query.
    reads: SnapshotReads,
    /// How long vehicles have waited for a store that could not be read.
    unread_since: UnreadSince,
    limits: SessionLimits,
    snapshots: SnapshotPolicy,
    next_stream_id: AtomicU64,
    /// Held (shared) while a model is resolved and installed in a session, and exclusively while a
    /// model is deleted and its sessions end, so that no session can start on a deleted model.
    model_gate: tokio::sync::RwLock<()>,
    /// Where batches of at least [`HEAVY_BATCH_COST`] are scored.
    heavy: HeavyWork,
    /// Stored snapshot versions (vehicle, written at) past the TTL, and when this process first
    /// saw each: they expire once seen unchanged long enough ([`Self::expire_snapshots`]).
    stale_seen: Mutex<HashMap<(String, i64), Instant>>,
    /// Sessions in the table by the identity that created them (the quota's count).
    per_identity: Mutex<HashMap<Arc<str>, usize>>,
    /// The open incidents' areas: a sample inside one is scored with the area prior.
    areas: Arc<IncidentAreas>,
}

/// A batch costing at least this many model parameters × samples is scored on the bounded pool of
/// heavy work, off the runtime's threads (with the bundled model's 21,883 parameters: 92 samples,
/// about 0.45 ms); smaller ones, a fleet's one-sample messages among them, are scored in place.
pub const HEAVY_BATCH_COST: usize = 2_000_000;

impl SessionManager {
    pub fn new(
        registry: Arc<Registry>,
        outbox: Arc<SessionOutbox>,
        store: Store,
        limits: SessionLimits,
        snapshots: SnapshotPolicy,
        heavy: HeavyWork,
        areas: Arc<IncidentAreas>,
    ) -> Self {
        Self {
            heavy,
            areas,
            stale_seen: Mutex::new(HashMap::new()),
            per_identity: Mutex::new(HashMap::new()),
            slots: Mutex::new(HashMap::new()),
            registry,
            outbox,
            reads: SnapshotReads::start(store.clone()),
            unread_since: UnreadSince::default(),
            store,
            limits,
            snapshots,
            next_stream_id: AtomicU64::new(1),
            model_gate: tokio::sync::RwLock::new(()),
        }
    }

    fn slots(&self) -> std::sync::MutexGuard<'_, HashMap<VehicleId, Arc<SessionSlot>>> {
        // A panic while holding this lock cannot leave the map inconsistent (single inserts/removes).
        self.slots.lock().unwrap_or_else(|p| p.into_inner())
    }

    fn lookup(&self, vehicle_id: &VehicleId) -> Option<Arc<SessionSlot>> {
        self.slots().get(vehicle_id).cloned()
    }

    /// Finds or creates the slot of a vehicle, within the caller's quota; a full table makes room by
    /// evicting the session idle longest without a stream (returned, to be snapshotted).
    fn slot_for(
        &self,
        vehicle_id: &VehicleId,
        model: &LoadedModel,
        identity: &Arc<str>,
    ) -> Result<Admitted, SessionError> {
        let mut slots = self.slots();
        if let Some(slot) = slots.get(vehicle_id) {
            return Ok(Admitted {
                slot: Arc::clone(slot),
                existed: true,
                made_room: None,
            });
        }
        let mut per_identity = self
            .per_identity
            .lock()
            .unwrap_or_else(PoisonError::into_inner);
        let created = per_identity.get(identity).copied().unwrap_or(0);
        if created >= self.limits.max_per_identity {
            telemetry::session_refused();
            return Err(SessionError::Quota {
                identity: identity.to_string(),
                limit: self.limits.max_per_identity,
            });
        }
        let mut evicted = None;
        if slots.len() >= self.limits.max_sessions {
            // Under pressure the session idle longest without a stream makes room: it leaves
            // memory, not the fleet (the caller snapshots it, as at idle eviction).
            let oldest = slots
                .values()
                .filter(|slot| !slot.connected())
                .min_by_key(|slot| slot.last_activity_ms.load(Ordering::Relaxed))
                .map(|slot| slot.vehicle_id.clone());
            let Some(oldest) = oldest.and_then(|id| slots.remove(&id)) else {
                telemetry::session_refused();
                return Err(SessionError::Full(self.limits.max_sessions));
            };
            forget_creator(&mut per_identity, &oldest.created_by);
            telemetry::sessions_evicted(1);
            evicted = Some(oldest);
        }
        *per_identity.entry(Arc::clone(identity)).or_insert(0) += 1;
        let slot = Arc::new(SessionSlot {
            created_by: Arc::clone(identity),
            vehicle_id: vehicle_id.clone(),
            state: tokio::sync::Mutex::new(SessionState::new(model.clone())),
            owner: Mutex::new(None),
            last_activity_ms: AtomicI64::new(now_unix_ms()),
            model_deleted: CancellationToken::new(),
        });
        slots.insert(vehicle_id.clone(), Arc::clone(&slot));
        Ok(Admitted {
            slot,
            existed: false,
            made_room: evicted,
        })
    }

    /// A session left the table: one fewer for the identity that created it.
    fn forget(&self, slot: &SessionSlot) {
        let mut per_identity = self
            .per_identity
            .lock()
            .unwrap_or_else(PoisonError::into_inner);
        forget_creator(&mut per_identity, &slot.created_by);
    }

    /// The vehicle's session, and whether it existed; a session evicted to make room for it is
    /// snapshotted (it continues from there, here or elsewhere).
    async fn admit(
        &self,
        vehicle_id: &VehicleId,
        model: &LoadedModel,
        identity: &Arc<str>,
    ) -> Result<(Arc<SessionSlot>, bool), SessionError> {
        let Admitted {
            slot,
            existed,
            made_room,
        } = self.slot_for(vehicle_id, model, identity)?;
        if let Some(evicted) = made_room {
            let mut state = evicted.state.lock().await;
            self.save_if_changed(&evicted.vehicle_id, &mut state);
            tracing::info!(vehicle = %evicted.vehicle_id, "evicted the session idle longest to make room for a new vehicle");
        }
        Ok((slot, existed))
    }

    /// Attaches a stream to a vehicle's session (creating or resuming it); an older stream on the same
    /// session is told to end. `model` `None` is the active model. A session on another model
    /// starts afresh.
    pub async fn attach(
        &self,
        vehicle_id: &VehicleId,
        model: Option<&ModelName>,
        reset: bool,
        identity: &Arc<str>,
    ) -> Result<Attachment, SessionError> {
        let _gate = self.model_gate.read().await;
        let model = self.registry.resolve(model).await?;
        // Read before any lock is taken: it may wait for the database.
        let stored = if reset {
            Ok(None)
        } else {
            self.stored_snapshot(vehicle_id).await
        };
        if let Err(SnapshotRefused::Unreadable { why, retry: true }) = &stored
            && self.lookup(vehicle_id).is_none()
        {
            return Err(self.refuse_unreadable(vehicle_id, why.clone()));
        }
        let (slot, existed) = self.admit(vehicle_id, &model, identity).await?;
        let evicted = CancellationToken::new();
        let stream_id = self.next_stream_id.fetch_add(1, Ordering::Relaxed);
        if let Ok(mut owner) = slot.owner.lock()
            && let Some(previous) = owner.replace(StreamOwner {
                id: stream_id,
                evicted: evicted.clone(),
            })
        {
            previous.evicted.cancel();
            tracing::info!(vehicle = %vehicle_id, "a newer stream took the session over");
        }
        slot.touch();
        let mut state = slot.state.lock().await;
        let start = Start {
            model: model.name.clone(),
            reset,
            held: existed.then(|| state.held()),
        };
        let stored = stored.and_then(|row| row.map(with_progress).transpose());
        let resumption = match start.origin(stored, &self.writer()) {
            Origin::Snapshot(row) => match self.restore(&row, &model) {
                Ok(restored) => {
                    self.replace_state(vehicle_id, &mut state, restored);
                    Resumption::from_snapshot()
                }
                Err(refused) => {
                    tracing::warn!(vehicle = %vehicle_id, reason = %refused, "session snapshot not used: the session starts afresh");
                    if matches!(refused, SnapshotRefused::Model { .. }) {
                        self.end_alarm_of_replaced(vehicle_id, &row);
                    }
                    start.afresh(Some(refused))
                }
            },
            Origin::Memory => Resumption::in_memory(),
            Origin::Unreadable(why) => {
                drop(state);
                self.abandon(&slot, stream_id, existed);
                return Err(self.refuse_unreadable(vehicle_id, why));
            }
            Origin::Fresh(refused) => {
                if let Some(refused) = &refused {
                    tracing::warn!(vehicle = %vehicle_id, reason = %refused, "session snapshot not read: the session starts afresh");
                }
                start.afresh(refused)
            }
        };
        if !resumption.resumed {
            self.replace_state(vehicle_id, &mut state, SessionState::new(model));
        }
        let accepted = Accepted {
            vehicle_id: vehicle_id.clone(),
            model: state.model.name.clone(),
            resumed: resumption.resumed,
            samples_seen: state.samples,
            last_seq: state.seqs.last(),
            replaced_model: resumption.replaced_model,
            from_snapshot: resumption.from_snapshot,
            snapshot_refused: resumption.snapshot_refused,
        };
        drop(state);
        Ok(Attachment {
            slot,
            stream_id,
            evicted,
            accepted,
        })
    }

    /// The refusal of a stream whose vehicle's stored session could not be read.
    fn refuse_unreadable(&self, vehicle_id: &VehicleId, why: String) -> SessionError {
        tracing::warn!(vehicle = %vehicle_id, reason = %why, "session snapshot not read: the stream is refused, to be retried");
        telemetry::snapshot_unread();
        SessionError::SnapshotUnreadable(why)
    }

    /// Undoes an attachment refused before it began: the stream lets go of the session, and a
    /// session made for it leaves the table again.
    fn abandon(&self, slot: &Arc<SessionSlot>, stream_id: u64, existed: bool) {
        if let Ok(mut owner) = slot.owner.lock()
            && owner.as_ref().is_some_and(|o| o.id == stream_id)
        {
            *owner = None;
        }
        if existed {
            return;
        }
        let removed = {
            let mut table = self.slots();
            let ours = table
                .get(&slot.vehicle_id)
                .is_some_and(|held| Arc::ptr_eq(held, slot));
            ours && table.remove(&slot.vehicle_id).is_some()
        };
        if removed {
            self.forget(slot);
        }
    }

    /// Releases a stream's hold (if it still holds the session) and snapshots the session; the
    /// receiver completes once the snapshot is stored. `None` when another stream took the
    /// session over or its model was deleted (nothing to hand off).
    pub async fn detach(&self, attachment: &Attachment) -> Option<oneshot::Receiver<()>> {
        let slot = &attachment.slot;
        let held = match slot.owner.lock() {
            Ok(mut owner) if owner.as_ref().is_some_and(|o| o.id == attachment.stream_id) => {
                *owner = None;
                true
            }
            _ => false,
        };
        slot.touch();
        if !held || slot.model_deleted.is_cancelled() {
            return None;
        }
        let mut state = slot.state.lock().await;
        Some(self.save(&slot.vehicle_id, &mut state))
    }

    /// The process id written with snapshots (this start's alarm run: unique per process).
    fn writer(&self) -> String {
        self.outbox.run_id().to_string()
    }

    /// Queues a snapshot of the session (see [`SessionOutbox::save_snapshot`]).
    fn save(&self, vehicle_id: &VehicleId, state: &mut SessionState) -> oneshot::Receiver<()> {
        let now_ms = now_unix_ms();
        state.since_snapshot = 0;
        state.snapshot_taken = Instant::now();
        let snapshot = state.snapshot();
        let open = snapshot.open_alarm.as_ref();
        self.outbox.save_snapshot(SnapshotRow {
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
        })
    }

    /// Snapshots a session that leaves this process (evicted, or at shutdown) unless nothing
    /// changed since its last snapshot: that copy is stored or queued already, and by now the
    /// vehicle may have moved on to another process, whose newer snapshot must not be overwritten
    /// by this stale one.
    fn save_if_changed(&self, vehicle_id: &VehicleId, state: &mut SessionState) {
        if state.since_snapshot > 0 {
            self.save(vehicle_id, state);
        }
    }

    /// Whether the policy wants a snapshot now (checked after each batch).
    fn snapshot_due(&self, state: &SessionState) -> bool {
        let policy = &self.snapshots;
        (policy.every_samples > 0 && state.since_snapshot >= policy.every_samples)
            || state.snapshot_taken.elapsed() >= policy.every
    }

    /// Replaces a session's state: the alarm the old state held ends (unless the new state holds
    /// it: a restore), and the new state is snapshotted at once, so that no process continues the
    /// old one.
    fn replace_state(&self, vehicle_id: &VehicleId, state: &mut SessionState, new: SessionState) {
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
    async fn stored_snapshot(
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
    fn restore(
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

    /// Validates and runs one batch on a session. A rejected batch changes nothing. `seq` 0 is not
    /// sequenced; a seq already applied is acknowledged (`duplicate`) without being scored again,
    /// and one before the last applied seq that never was is refused ([`super::sequence`]).
    pub async fn process(
        &self,
        slot: &SessionSlot,
        seq: u64,
        samples: &[Sample],
        field: &str,
    ) -> Result<Decisions, SessionError> {
        let mut state = slot.state.lock().await;
        self.score(&mut state, samples.len(), |state| {
            self.process_locked(slot, state, seq, samples, field)
        })
        .await
    }

    /// Runs `work` on `state` (a batch of `samples` samples): in place, or on the pool of heavy
    /// work when the batch costs at least [`HEAVY_BATCH_COST`].
    async fn score<T: Send>(
        &self,
        state: &mut SessionState,
        samples: usize,
        work: impl FnOnce(&mut SessionState) -> T + Send,
    ) -> T {
        if batch_cost(&state.model, samples) >= HEAVY_BATCH_COST {
            self.heavy.run(|| work(state)).await
        } else {
            work(state)
        }
    }

    fn process_locked(
        &self,
        slot: &SessionSlot,
        state: &mut SessionState,
        seq: u64,
        samples: &[Sample],
        field: &str,
    ) -> Result<Decisions, SessionError> {
        if slot.model_deleted.is_cancelled() {
            return Err(SessionError::ModelDeleted(state.model.name.clone()));
        }
        match state.seqs.check(seq) {
            SeqCheck::New => {}
            SeqCheck::Duplicate => {
                slot.touch();
                return Ok(Decisions {
                    model: state.model.name.clone(),
                    decisions: Vec::new(),
                    duplicate: true,
                });
            }
            SeqCheck::Backwards { last_seq } => {
                return Err(SessionError::InvalidBatch(vec![(
                    seq_field(field),
                    format!(
                        "{seq} is before this session's last applied seq {last_seq} and was never \
                         applied; send increasing numbers (a resent batch keeps its own)"
                    ),
                )]));
            }
        }
        validate_batch(
            samples,
            state.last_timestamp_s,
            self.limits.max_batch_samples,
            field,
        )
        .map_err(SessionError::InvalidBatch)?;
        let mut decisions = Vec::with_capacity(samples.len());
        for sample in samples {
            let in_incident_area = self
                .areas
                .contains(sample.latitude_deg, sample.longitude_deg);
            let decision = state
                .detector
                .step_with_prior(sample, false, in_incident_area);
            state.samples += 1;
            state.trajectories = decision.evidence.trajectory + 1;
            state.last_timestamp_s = Some(
                state
                    .last_timestamp_s
                    .map_or(sample.timestamp_s, |t| t.max(sample.timestamp_s)),
            );
            let signal = AlarmSignal::of(&decision);
            match state
                .alarm
                .step(signal, sample.timestamp_s, decision.probability)
            {
                Some(EpisodeChange::Onset) => self.record_onset(
                    state,
                    &slot.vehicle_id,
                    sample,
                    decision.probability,
                    &decision.explanation,
                ),
                Some(EpisodeChange::Ended(episode)) => self.record_end(episode),
                None => {}
            }
            decisions.push(decision);
        }
        state.seqs.apply(seq);
        state.since_snapshot += samples.len() as u64;
        // An alarm onset or end is stored together with a snapshot that includes it, so that a
        // session continued elsewhere neither repeats nor loses it.
        let alarm_changed = decisions.iter().any(|d| d.alarm_onset || d.alarm_end);
        if alarm_changed || self.snapshot_due(state) {
            self.save(&slot.vehicle_id, state);
        }
        slot.touch();
        Ok(Decisions {
            model: state.model.name.clone(),
            decisions,
            duplicate: false,
        })
    }

    /// Queues an alarm onset (with `why`, the onset sample's explanation) and opens its episode
    /// under the id the outbox gave it.
    fn record_onset(
        &self,
        state: &mut SessionState,
        vehicle: &VehicleId,
        sample: &Sample,
        p: f64,
        why: &Explanation,
    ) {
        let onset_at_ms = now_unix_ms();
        let timestamp_s = sample.timestamp_s;
        let id = self.outbox.onset(
            vehicle.as_str(),
            state.model.name.id(),
            timestamp_s,
            onset_at_ms,
            p,
            Some(OnsetWhy {
                explanation: why,
                fix: LatLon::new(sample.latitude_deg, sample.longitude_deg),
            }),
        );
        telemetry::alarm_onset();
        state.alarm.open(id, timestamp_s, onset_at_ms, p);
    }

    /// Queues the end of an episode at its last alarming sample.
    fn record_end(&self, episode: OpenAlarm) {
        self.outbox.end(
            episode.id,
            episode.last_timestamp_s,
            episode.peak,
            episode.samples,
        );
        telemetry::alarm_end();
    }

    /// Ends the alarm a stored session of another model held open: that session is replaced by a
    /// fresh one under the model now asked for (a roll-out), so no process will continue it. (A
    /// session replaced in this process's memory ends its alarm in [`Self::replace_state`].)
    fn end_alarm_of_replaced(&self, vehicle_id: &VehicleId, row: &SnapshotRow) {
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
    fn close_alarm(&self, state: &mut SessionState) {
        if let Some(episode) = state.alarm.close() {
            self.record_end(episode);
        }
    }

    /// Runs a batch on a throw-away detector (no session).
    pub async fn detect_stateless(
        &self,
        model: Option<&ModelName>,
        samples: &[Sample],
        field: &str,
    ) -> Result<Decisions, SessionError> {
        let model = self.registry.resolve(model).await?;
        validate_batch(samples, None, self.limits.max_batch_samples, field)
            .map_err(SessionError::InvalidBatch)?;
        let mut detector = Detector::new(Arc::clone(&model.artifact));
        let mut run = || samples.iter().map(|s| detector.step(s, false)).collect();
        let decisions = if batch_cost(&model, samples.len()) >= HEAVY_BATCH_COST {
            self.heavy.run(run).await
        } else {
            run()
        };
        Ok(Decisions {
            model: model.name,
            decisions,
            duplicate: false,
        })
    }

    /// Runs a batch for a vehicle without attaching a stream (creating the session if needed).
    /// `model` `None` is the active model; a session on another model, or with `reset`, starts
    /// afresh if the batch is valid. `seq` becomes the session's `last_seq` as in [`Self::process`] (`None`: not sequenced).
    /// `field` names the samples in violations.
    pub async fn detect_unattached(
        &self,
        vehicle: ForVehicle<'_>,
        model: Option<&ModelName>,
        reset: bool,
        seq: Option<u64>,
        samples: &[Sample],
        field: &str,
    ) -> Result<Decisions, SessionError> {
        let ForVehicle {
            vehicle_id,
            identity,
        } = vehicle;
        if !reset
            && let Some(slot) = self.lookup(vehicle_id)
            && !slot.model_deleted.is_cancelled()
        {
            let mut state = slot.state.lock().await;
            if self.runs(&state, model) {
                let seq = seq.unwrap_or(0);
                return self
                    .score(&mut state, samples.len(), |state| {
                        self.process_locked(&slot, state, seq, samples, field)
                    })
                    .await;
            }
        }
        // A model to resolve and install: a new session, a reset, or another model.
        let _gate = self.model_gate.read().await;
        let model = self.registry.resolve(model).await?;
        // Starting afresh needs a batch valid on a fresh session: a refused batch changes nothing
        // and leaves no new session behind.
        validate_batch(samples, None, self.limits.max_batch_samples, field)
            .map_err(SessionError::InvalidBatch)?;
        let (slot, existed) = self.admit(vehicle_id, &model, identity).await?;
        let mut state = slot.state.lock().await;
        let start = Start {
            model: model.name.clone(),
            reset,
            held: existed.then(|| state.held()),
        };
        if !start.held_continues() {
            self.replace_state(vehicle_id, &mut state, SessionState::new(model));
        }
        let seq = seq.unwrap_or(0);
        self.score(&mut state, samples.len(), |state| {
            self.process_locked(&slot, state, seq, samples, field)
        })
        .await
    }

    /// Whether a session already runs the model a request names (`None`: the active one).
    fn runs(&self, state: &SessionState, model: Option<&ModelName>) -> bool {
        match model {
            Some(name) => state.model.name == *name,
            None => self.registry.is_active(&state.model.name),
        }
    }

    /// Deletes a model (not the active one) and ends the sessions that use it: their open alarms
    /// end, they leave the table and their streams are told to end. Returns how many ended.
    pub async fn delete_model(&self, name: &ModelName) -> Result<usize, SessionError> {
        let _gate = self.model_gate.write().await;
        self.registry.delete(name).await?;
        let slots: Vec<Arc<SessionSlot>> = self.slots().values().cloned().collect();
        let mut ended = 0;
        for slot in slots {
            let mut state = slot.state.lock().await;
            if state.model.name != *name {
                continue;
            }
            self.close_alarm(&mut state);
            slot.model_deleted.cancel();
            drop(state);
            let mut table = self.slots();
            if table
                .get(&slot.vehicle_id)
                .is_some_and(|s| Arc::ptr_eq(s, &slot))
            {
                table.remove(&slot.vehicle_id);
                self.forget(&slot);
            }
            ended += 1;
        }
        if ended > 0 {
            tracing::info!(model = %name, sessions = ended, "ended the sessions of a deleted model");
        }
        // Stored snapshots of the model would be refused anyway; a failure only leaves them so.
        if let Err(error) = self.store.delete_snapshots_of_model(name.id()).await {
            tracing::warn!(%error, model = %name, "could not delete the deleted model's session snapshots");
        }
        Ok(ended)
    }

    /// The limits the table was made with.
    pub fn limits(&self) -> SessionLimits {
        self.limits
    }

    async fn describe(&self, slot: &SessionSlot) -> SessionSummary {
        let state = slot.state.lock().await;
        SessionSummary {
            vehicle_id: slot.vehicle_id.clone(),
            model: state.model.name.clone(),
            connected: slot.connected(),
            samples: state.samples,
            trajectories: state.trajectories,
            alarm_active: state.alarm.active,
            alarms_raised: state.alarm.raised,
            last_seq: state.seqs.last(),
            last_timestamp_s: state.last_timestamp_s,
            last_activity_ms: slot.last_activity_ms.load(Ordering::Relaxed),
        }
    }

    /// Up to `size` sessions ordered by vehicle id, after `page_token` (the last vehicle id of the
    /// previous page, or empty); the second value is the next page's token (empty on the last).
    pub async fn list(&self, size: usize, page_token: &str) -> (Vec<SessionSummary>, String) {
        let mut slots: Vec<Arc<SessionSlot>> = self
            .slots()
            .values()
            .filter(|s| page_token.is_empty() || s.vehicle_id.as_str() > page_token)
            .cloned()
            .collect();
        slots.sort_by(|a, b| a.vehicle_id.cmp(&b.vehicle_id));
        let more = slots.len() > size;
        slots.truncate(size);
        let mut sessions = Vec::with_capacity(slots.len());
        for slot in &slots {
            sessions.push(self.describe(slot).await);
        }
        let next_page_token = match (more, sessions.last()) {
            (true, Some(last)) => last.vehicle_id.to_string(),
            _ => String::new(),
        };
        (sessions, next_page_token)
    }

    /// One vehicle's session.
    pub async fn get(&self, vehicle_id: &VehicleId) -> Result<SessionSummary, SessionError> {
        let slot = self
            .lookup(vehicle_id)
            .ok_or_else(|| SessionError::NotFound(vehicle_id.to_string()))?;
        Ok(self.describe(&slot).await)
    }

    /// Forgets a session's history but keeps its model.
    pub async fn reset(&self, vehicle_id: &VehicleId) -> Result<SessionSummary, SessionError> {
        let slot = self
            .lookup(vehicle_id)
            .ok_or_else(|| SessionError::NotFound(vehicle_id.to_string()))?;
        {
            let mut state = slot.state.lock().await;
            let model = state.model.clone();
            self.replace_state(vehicle_id, &mut state, SessionState::new(model));
        }
        slot.touch();
        Ok(self.describe(&slot).await)
    }

    /// Removes sessions without a stream that were idle longer than the limit; returns how many.
    pub async fn evict_idle(&self) -> usize {
        let cutoff = now_unix_ms() - self.limits.idle.as_millis() as i64;
        let idle: Vec<Arc<SessionSlot>> = {
            let mut slots = self.slots();
            let ids: Vec<VehicleId> = slots
                .values()
                .filter(|s| !s.connected() && s.last_activity_ms.load(Ordering::Relaxed) < cutoff)
                .map(|s| s.vehicle_id.clone())
                .collect();
            ids.iter().filter_map(|id| slots.remove(id)).collect()
        };
        for slot in &idle {
            self.forget(slot);
        }
        // The session leaves memory but not the fleet: its snapshot (with any open alarm) is where
        // it continues, here or on another process.
        for slot in &idle {
            let mut state = slot.state.lock().await;
            self.save_if_changed(&slot.vehicle_id, &mut state);
        }
        telemetry::sessions_evicted(idle.len());
        idle.len()
    }

    /// Deletes the stored snapshots whose vehicles did not come back and ends the alarms they held
    /// open, at their last alarming sample; returns how many alarms ended.
    ///
    /// A snapshot expires when it is older than the policy's TTL by its writer's clock, and this
    /// process has also seen it unchanged for [`Self::expiry_confirmation`] by its own monotonic
    /// clock, and this process does not hold the vehicle's session. So a wall-clock step, here or
    /// on another replica, never ends the alarm of a vehicle that is still streaming: a streaming
    /// vehicle's snapshot is rewritten far sooner than the confirmation takes.
    pub async fn expire_snapshots(&self) -> usize {
        let ttl_ms = i64::try_from(self.snapshots.ttl.as_millis()).unwrap_or(i64::MAX);
        let stale = match self
            .store
            .stale_snapshots(now_unix_ms().saturating_sub(ttl_ms))
            .await
        {
            Ok(stale) => stale,
            Err(error) => {
                tracing::warn!(%error, "could not read old session snapshots; retrying later");
                return 0;
            }
        };
        let confirmed = {
            let held = self.slots();
            let mut seen = self
                .stale_seen
                .lock()
                .unwrap_or_else(PoisonError::into_inner);
            let now = Instant::now();
            let candidates: HashMap<(String, i64), Instant> = stale
                .into_iter()
                .filter(|(vehicle, _)| {
                    VehicleId::parse(vehicle).map_or(true, |id| !held.contains_key(&id))
                })
                .map(|version| {
                    let first_seen = seen.get(&version).copied().unwrap_or(now);
                    (version, first_seen)
                })
                .collect();
            *seen = candidates;
            seen.iter()
                .filter(|(_, first_seen)| {
                    now.duration_since(**first_seen) >= self.expiry_confirmation()
                })
                .map(|(version, _)| version.clone())
                .collect::<Vec<_>>()
        };
        let mut ended = 0;
        // A few hundred per transaction: a mass expiry never holds the database's write lock long.
        for batch in confirmed.chunks(EXPIRY_BATCH) {
            let expired = match self.store.expire_snapshots(batch).await {
                Ok(expired) => expired,
                Err(error) => {
                    tracing::warn!(%error, "could not expire old session snapshots; retrying later");
                    break;
                }
            };
            let mut seen = self
                .stale_seen
                .lock()
                .unwrap_or_else(PoisonError::into_inner);
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
                let last = SessionSnapshot::decode(&snapshot)
                    .ok()
                    .and_then(|s| s.open_alarm)
                    .filter(|open| open.id == alarm.id)
                    .map(|open| (open.last_timestamp_s, open.peak, i64::from(open.samples)));
                self.outbox.end_abandoned(alarm, last);
                telemetry::alarm_end();
            }
        }
        ended
    }

    /// How long this process must see a snapshot unchanged, by its own clock, before it expires:
    /// longer than a held session goes without rewriting it (at least every snapshot period while
    /// batches come; a session held without batches, up to the idle limit, keeps its last copy).
    fn expiry_confirmation(&self) -> Duration {
        self.limits.idle + self.snapshots.every
    }

    /// Sessions held, and how many of them have a live stream (for metrics; one pass under the
    /// table's lock, like the evictor's).
    pub fn counts(&self) -> (usize, usize) {
        let slots = self.slots();
        let connected = slots.values().filter(|s| s.connected()).count();
        (slots.len(), connected)
    }

    /// Snapshots every session that changed since its last snapshot (shutdown): each continues
    /// from its snapshot, here after a restart or on another process, and its open alarm stays
    /// open.
    pub async fn save_all(&self) {
        let slots: Vec<Arc<SessionSlot>> = self.slots().values().cloned().collect();
        for slot in slots {
            let mut state = slot.state.lock().await;
            if !slot.model_deleted.is_cancelled() {
                self.save_if_changed(&slot.vehicle_id, &mut state);
            }
        }
    }
}
