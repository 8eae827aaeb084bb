//! Per-vehicle sessions: a stream attaches to its vehicle's session (creating or resuming it; a
//! newer stream takes over), its batches are processed there, and it detaches; plus the calls
//! without a stream (one batch for a vehicle, or stateless), listing, reset and model deletion.
//!
//! Hand-off: a session's complete state is snapshotted ([`super::handoff`]) through the keeper
//! ([`super::persistence`]) when its stream ends, when it is evicted, at shutdown, when it starts
//! afresh, with every alarm onset or end, and by the snapshot policy. A stream that starts for a
//! vehicle this process does not hold (or holds an older copy of) continues from the stored
//! snapshot; one that cannot be used (corrupt, another schema or model) is refused with its reason
//! and the session starts afresh (the decision is [`super::resume`]'s). An alarm stays open across
//! a hand-off.
//!
//! Alarm episodes are followed by [`super::episodes`]; the keeper records what they report. A
//! sample inside an open area incident ([`IncidentAreas`]) is scored with the area prior.
//!
//! Shadow: every scored batch is offered to [`Shadows`], which copies it for a candidate model
//! when a shadow runs for the vehicle; the offer never waits and changes nothing here.
//!
//! Roll-out: a session started or resumed without a model follows the active model (a fresh
//! detector when it changed); deleting a model ends the sessions that use it.
//!
//! Owns attach, detach and process over the session table ([`super::table`]). Speaks core types
//! ([`Sample`], [`Decision`]) and [`SessionError`]; it must not know about gRPC messages or
//! statuses (the edge is `detection::service`), hold the table's map or build a snapshot row.

use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};

use spoofwatch_core::detector::{Decision, Detector};
use spoofwatch_core::sample::Sample;
use spoofwatch_proto::wire::{ModelName, VehicleId};
use tokio::sync::oneshot;
use tokio_util::sync::CancellationToken;

use super::episodes::{AlarmSignal, EpisodeChange};
use super::error::SessionError;
use super::handoff::SnapshotRefused;
use super::persistence::{SessionKeeper, SnapshotPolicy, with_progress};
use super::resume::{Origin, Resumption, Start};
use super::sequence::SeqCheck;
use super::state::SessionState;
use super::table::{Admitted, SessionLimits, SessionSlot, SessionTable};
use super::validate::validate_batch;
use crate::access::Credential;
use crate::incidents::areas::IncidentAreas;
use crate::models::{LoadedModel, Registry};
use crate::outbox::SessionOutbox;
use crate::shadow::Shadows;
use crate::store::Store;
use crate::telemetry;
use crate::work::HeavyWork;

/// A vehicle, and the identity of the caller that sends its batch (whose session quota a new
/// session counts against) and the credential it was sent with (recorded with the alarms it
/// raises).
#[derive(Clone, Copy, Debug)]
pub struct ForVehicle<'a> {
    pub vehicle_id: &'a VehicleId,
    pub identity: &'a Arc<str>,
    pub credential: &'a Credential,
}

/// One batch of samples for a session: its seq (0: not sequenced), the samples, the field that
/// names them in violations, and the credential that sent them.
#[derive(Clone, Copy, Debug)]
struct Batch<'a> {
    seq: u64,
    samples: &'a [Sample],
    field: &'a str,
    credential: &'a Credential,
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

/// A stream's hold on a session. The credential its batches are sent with is given with each
/// batch ([`SessionManager::process`]): a changed roles file may change it while the stream is open.
#[derive(Debug)]
pub struct Attachment {
    pub slot: Arc<SessionSlot>,
    pub stream_id: u64,
    /// Cancelled when a newer stream takes the session over.
    pub evicted: CancellationToken,
    pub accepted: Accepted,
}

/// A session reset in the store, as GetSession would describe it were it held: no stream, no
/// samples, no alarm, under the model it ran.
fn fresh_summary(vehicle_id: &VehicleId, model_id: &str) -> SessionSummary {
    SessionSummary {
        vehicle_id: vehicle_id.clone(),
        model: ModelName::from_id(model_id),
        connected: false,
        samples: 0,
        trajectories: 0,
        alarm_active: false,
        alarms_raised: 0,
        last_seq: 0,
        last_timestamp_s: None,
        last_activity_ms: crate::store::now_unix_ms(),
    }
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

/// The sessions: attach, detach and process over the session table, their snapshots and alarm
/// events through the keeper.
#[derive(Debug)]
pub struct SessionManager {
    table: SessionTable,
    keeper: SessionKeeper,
    registry: Arc<Registry>,
    next_stream_id: AtomicU64,
    /// Held (shared) while a model is resolved and installed in a session, and exclusively while a
    /// model is deleted and its sessions end, so that no session can start on a deleted model.
    model_gate: tokio::sync::RwLock<()>,
    /// Where batches of at least [`HEAVY_BATCH_COST`] are scored.
    heavy: HeavyWork,
    /// The open incidents' areas: a sample inside one is scored with the area prior.
    areas: Arc<IncidentAreas>,
    /// Offered a copy of every scored batch (a candidate scores it off the request path).
    shadows: Arc<Shadows>,
}

/// What scoring consults beside the model: the open incidents' areas (a sample inside one is
/// scored with the area prior) and the shadow (offered a copy of every scored batch).
#[derive(Clone, Debug)]
pub struct Beside {
    pub areas: Arc<IncidentAreas>,
    pub shadows: Arc<Shadows>,
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
        beside: Beside,
    ) -> Self {
        let Beside { areas, shadows } = beside;
        Self {
            heavy,
            areas,
            shadows,
            keeper: SessionKeeper::new(outbox, store, snapshots, limits.idle),
            table: SessionTable::new(limits),
            registry,
            next_stream_id: AtomicU64::new(1),
            model_gate: tokio::sync::RwLock::new(()),
        }
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
        } = self.table.admit(vehicle_id, model, identity)?;
        if let Some(evicted) = made_room {
            let mut state = evicted.state.lock().await;
            self.keeper.save_if_changed(&evicted.vehicle_id, &mut state);
            tracing::info!(vehicle = %evicted.vehicle_id, "evicted the session idle longest to make room for a new vehicle");
        }
        Ok((slot, existed))
    }

    /// Attaches a stream to a vehicle's session (creating or resuming it); an older stream on the same
    /// session is told to end. `model` `None` is the active model. A session on another model
    /// starts afresh.
    /// `identity`: the caller's, whose session quota a new session counts against.
    pub async fn attach(
        &self,
        vehicle_id: &VehicleId,
        identity: &Arc<str>,
        model: Option<&ModelName>,
        reset: bool,
    ) -> Result<Attachment, SessionError> {
        let _gate = self.model_gate.read().await;
        let model = self.registry.resolve(model).await?;
        // Read before any lock is taken: it may wait for the database.
        let stored = if reset {
            Ok(None)
        } else {
            self.keeper.stored_snapshot(vehicle_id).await
        };
        if let Err(SnapshotRefused::Unreadable { why, retry: true }) = &stored
            && self.table.lookup(vehicle_id).is_none()
        {
            return Err(self.refuse_unreadable(vehicle_id, why.clone()));
        }
        let (slot, existed) = self.admit(vehicle_id, &model, identity).await?;
        let evicted = CancellationToken::new();
        let stream_id = self.next_stream_id.fetch_add(1, Ordering::Relaxed);
        if slot.take_over(stream_id, evicted.clone()) {
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
        let resumption = match start.origin(stored, &self.keeper.writer()) {
            Origin::Snapshot(row) => match self.keeper.restore(&row, &model) {
                Ok(restored) => {
                    self.keeper.replace_state(vehicle_id, &mut state, restored);
                    Resumption::from_snapshot()
                }
                Err(refused) => {
                    tracing::warn!(vehicle = %vehicle_id, reason = %refused, "session snapshot not used: the session starts afresh");
                    if matches!(refused, SnapshotRefused::Model { .. }) {
                        self.keeper.end_alarm_of_replaced(vehicle_id, &row);
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
            self.keeper
                .replace_state(vehicle_id, &mut state, SessionState::new(model));
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
        slot.release(stream_id);
        if !existed {
            self.table.remove(slot);
        }
    }

    /// Releases a stream's hold (if it still holds the session) and snapshots the session; the
    /// receiver completes once the snapshot is stored. `None` when another stream took the
    /// session over or its model was deleted (nothing to hand off).
    pub async fn detach(&self, attachment: &Attachment) -> Option<oneshot::Receiver<()>> {
        let slot = &attachment.slot;
        let held = slot.release(attachment.stream_id);
        slot.touch();
        if !held || slot.model_deleted.is_cancelled() {
            return None;
        }
        let mut state = slot.state.lock().await;
        Some(self.keeper.save(&slot.vehicle_id, &mut state))
    }

    /// Validates and runs one batch on a session, sent with `credential` (as the identities in
    /// force judge the stream's caller now: the alarms it raises record it). A rejected batch
    /// changes nothing. `seq` 0 is not sequenced; a seq already applied is acknowledged
    /// (`duplicate`) without being scored again, and one before the last applied seq that never
    /// was is refused ([`super::sequence`]).
    pub async fn process(
        &self,
        attachment: &Attachment,
        credential: &Credential,
        seq: u64,
        samples: &[Sample],
        field: &str,
    ) -> Result<Decisions, SessionError> {
        let slot = &attachment.slot;
        let mut state = slot.state.lock().await;
        let batch = Batch {
            seq,
            samples,
            field,
            credential,
        };
        self.score(&mut state, samples.len(), |state| {
            self.process_locked(slot, state, batch)
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
        batch: Batch<'_>,
    ) -> Result<Decisions, SessionError> {
        let Batch {
            seq,
            samples,
            field,
            credential,
        } = batch;
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
            self.table.limits().max_batch_samples,
            field,
        )
        .map_err(SessionError::InvalidBatch)?;
        let mut decisions = Vec::with_capacity(samples.len());
        let mut in_area = Vec::with_capacity(samples.len());
        for sample in samples {
            let in_incident_area = self
                .areas
                .contains(sample.latitude_deg, sample.longitude_deg);
            in_area.push(in_incident_area);
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
            match state.alarm.step(
                signal,
                sample.timestamp_s,
                decision.probability,
                decision.escalation,
            ) {
                Some(EpisodeChange::Onset(severity)) => self.keeper.record_onset(
                    state,
                    &slot.vehicle_id,
                    sample,
                    (decision.probability, severity),
                    &decision.explanation,
                    credential,
                ),
                Some(EpisodeChange::Escalated) => {
                    self.keeper.record_escalation(state, sample.timestamp_s)
                }
                Some(EpisodeChange::Ended(episode)) => self.keeper.record_end(episode),
                None => {}
            }
            decisions.push(decision);
        }
        state.seqs.apply(seq);
        state.since_snapshot += samples.len() as u64;
        // A copy for the shadow, if one runs for this vehicle: never waited for.
        self.shadows
            .offer(&slot.vehicle_id, samples, &decisions, &in_area);
        // An alarm onset, escalation or end is stored together with a snapshot that includes it,
        // so that a session continued elsewhere neither repeats nor loses it.
        let alarm_changed = decisions
            .iter()
            .any(|d| d.alarm_onset || d.escalation || d.alarm_end);
        if alarm_changed || self.keeper.snapshot_due(state) {
            self.keeper.save(&slot.vehicle_id, state);
        }
        slot.touch();
        Ok(Decisions {
            model: state.model.name.clone(),
            decisions,
            duplicate: false,
        })
    }

    /// Runs a batch on a throw-away detector (no session).
    pub async fn detect_stateless(
        &self,
        model: Option<&ModelName>,
        samples: &[Sample],
        field: &str,
    ) -> Result<Decisions, SessionError> {
        let model = self.registry.resolve(model).await?;
        validate_batch(samples, None, self.table.limits().max_batch_samples, field)
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
            credential,
        } = vehicle;
        let batch = |seq: Option<u64>| Batch {
            seq: seq.unwrap_or(0),
            samples,
            field,
            credential,
        };
        if !reset
            && let Some(slot) = self.table.lookup(vehicle_id)
            && !slot.model_deleted.is_cancelled()
        {
            let mut state = slot.state.lock().await;
            if self.runs(&state, model) {
                return self
                    .score(&mut state, samples.len(), |state| {
                        self.process_locked(&slot, state, batch(seq))
                    })
                    .await;
            }
        }
        // A model to resolve and install: a new session, a reset, or another model.
        let _gate = self.model_gate.read().await;
        let model = self.registry.resolve(model).await?;
        // Starting afresh needs a batch valid on a fresh session: a refused batch changes nothing
        // and leaves no new session behind.
        validate_batch(samples, None, self.table.limits().max_batch_samples, field)
            .map_err(SessionError::InvalidBatch)?;
        let (slot, existed) = self.admit(vehicle_id, &model, identity).await?;
        let mut state = slot.state.lock().await;
        let start = Start {
            model: model.name.clone(),
            reset,
            held: existed.then(|| state.held()),
        };
        if !start.held_continues() {
            self.keeper
                .replace_state(vehicle_id, &mut state, SessionState::new(model));
        }
        self.score(&mut state, samples.len(), |state| {
            self.process_locked(&slot, state, batch(seq))
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
        let mut ended = 0;
        for slot in self.table.all() {
            let mut state = slot.state.lock().await;
            if state.model.name != *name {
                continue;
            }
            self.keeper.close_alarm(&mut state);
            slot.model_deleted.cancel();
            drop(state);
            self.table.remove(&slot);
            ended += 1;
        }
        if ended > 0 {
            tracing::info!(model = %name, sessions = ended, "ended the sessions of a deleted model");
        }
        self.keeper.delete_snapshots_of_model(name).await;
        Ok(ended)
    }

    /// The limits the table was made with.
    pub fn limits(&self) -> SessionLimits {
        self.table.limits()
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
            last_activity_ms: slot.last_activity_ms(),
        }
    }

    /// Up to `size` sessions ordered by vehicle id, after `page_token` (the last vehicle id of the
    /// previous page, or empty); the second value is the next page's token (empty on the last).
    pub async fn list(&self, size: usize, page_token: &str) -> (Vec<SessionSummary>, String) {
        let (slots, more) = self.table.page(size, page_token);
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
            .table
            .lookup(vehicle_id)
            .ok_or_else(|| SessionError::NotFound(vehicle_id.to_string()))?;
        Ok(self.describe(&slot).await)
    }

    /// Forgets a session's history but keeps its model; its open alarm ends. A vehicle this
    /// process no longer holds in memory (its session evicted, or not resumed since a restart) is
    /// reset in the store: its snapshot is deleted and the alarm it held open ends at its last
    /// alarming sample, as when the snapshot expires; its next stream starts afresh. Not found
    /// only when neither memory nor the store knows the vehicle.
    pub async fn reset(&self, vehicle_id: &VehicleId) -> Result<SessionSummary, SessionError> {
        let slot = match self.table.lookup(vehicle_id) {
            Some(slot) => slot,
            None => {
                let model_id = self
                    .keeper
                    .reset_stored(vehicle_id)
                    .await?
                    .ok_or_else(|| SessionError::NotFound(vehicle_id.to_string()))?;
                // A stream that started meanwhile may have continued the snapshot before it went:
                // its session is reset too, in memory.
                let Some(slot) = self.table.lookup(vehicle_id) else {
                    tracing::info!(vehicle = %vehicle_id, "reset a vehicle's stored session: its snapshot is deleted and its open alarm ended");
                    return Ok(fresh_summary(vehicle_id, &model_id));
                };
                slot
            }
        };
        {
            let mut state = slot.state.lock().await;
            let model = state.model.clone();
            self.keeper
                .replace_state(vehicle_id, &mut state, SessionState::new(model));
        }
        slot.touch();
        Ok(self.describe(&slot).await)
    }

    /// Removes sessions without a stream that were idle longer than the limit; returns how many.
    pub async fn evict_idle(&self) -> usize {
        let idle = self.table.take_idle();
        // The session leaves memory but not the fleet: its snapshot (with any open alarm) is where
        // it continues, here or on another process.
        for slot in &idle {
            let mut state = slot.state.lock().await;
            self.keeper.save_if_changed(&slot.vehicle_id, &mut state);
        }
        idle.len()
    }

    /// Deletes the stored snapshots whose vehicles did not come back (and this process does not
    /// hold) and ends the alarms they held open; returns how many alarms ended
    /// ([`SessionKeeper::expire_snapshots`]).
    pub async fn expire_snapshots(&self) -> usize {
        self.keeper
            .expire_snapshots(|vehicle| self.table.holds(vehicle))
            .await
    }

    /// Sessions held, and how many of them have a live stream (for metrics).
    pub fn counts(&self) -> (usize, usize) {
        self.table.counts()
    }

    /// Snapshots every session that changed since its last snapshot (shutdown): each continues
    /// from its snapshot, here after a restart or on another process, and its open alarm stays
    /// open.
    pub async fn save_all(&self) {
        for slot in self.table.all() {
            let mut state = slot.state.lock().await;
            if !slot.model_deleted.is_cancelled() {
                self.keeper.save_if_changed(&slot.vehicle_id, &mut state);
            }
        }
    }
}
