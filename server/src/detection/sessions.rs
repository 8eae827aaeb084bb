//! Per-vehicle sessions: a detector each, ownership by at most one stream (a newer stream takes
//! over), a bounded count, idle eviction, and alarm onsets/ends handed to the alarm outbox (never a
//! database call while a session is locked).
//!
//! Roll-out: a session started or resumed without a model follows the active model (a fresh
//! detector when it changed); deleting a model ends the sessions that use it.
//! Speaks core types ([`Sample`], [`Decision`]) and [`SessionError`]; it must not know about gRPC
//! messages or statuses (the edge is `detection::service`).

use std::collections::HashMap;
use std::sync::atomic::{AtomicI64, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use spoofwatch_core::detector::{Decision, Detector};
use spoofwatch_core::sample::Sample;
use spoofwatch_proto::wire::ModelName;
use tokio_util::sync::CancellationToken;

use super::validate::validate_batch;
use crate::alarms::AlarmOutbox;
use crate::models::{LoadedModel, Registry, RegistryError};
use crate::store::now_unix_ms;
use crate::telemetry;

/// Everything a session operation can fail with.
#[derive(Debug, thiserror::Error)]
pub enum SessionError {
    /// The batch is invalid; one `(field, problem)` per violation. Nothing was applied.
    #[error("invalid batch")]
    InvalidBatch(Vec<(String, String)>),
    /// No session for this vehicle.
    #[error("session {0:?} not found")]
    NotFound(String),
    /// The session table is full.
    #[error("the server holds its maximum of {0} vehicle sessions")]
    Full(usize),
    /// The requested model cannot be served.
    #[error(transparent)]
    Model(#[from] RegistryError),
    /// The session's model was deleted: the session ended.
    #[error(
        "{0} was deleted, which ended this session; start a new one (an empty model follows the active model)"
    )]
    ModelDeleted(ModelName),
}

/// What a stream learns when it attaches.
#[derive(Clone, Debug)]
pub struct Accepted {
    pub vehicle_id: String,
    pub model: ModelName,
    pub resumed: bool,
    pub samples_seen: u64,
    pub last_seq: u64,
    /// The session existed with this other model and started afresh with `model`.
    pub replaced_model: Option<ModelName>,
}

/// A processed batch: one decision per sample, in order, by `model`.
#[derive(Clone, Debug)]
pub struct Decisions {
    pub model: ModelName,
    pub decisions: Vec<Decision>,
}

/// A session as reported by ListSessions/GetSession.
#[derive(Clone, Debug)]
pub struct SessionSummary {
    pub vehicle_id: String,
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

/// Bounds on the in-memory session table.
#[derive(Clone, Copy, Debug)]
pub struct SessionLimits {
    pub max_sessions: usize,
    /// A session with no stream attached is evicted after this long without activity.
    pub idle: Duration,
    /// Most samples in one batch.
    pub max_batch_samples: usize,
}

/// An alarm currently on (its onset queued for `alarm_events` under `id`).
#[derive(Debug)]
struct OpenAlarm {
    id: i64,
    peak: f64,
    samples: u32,
    /// Sample time of the latest alarming sample: the event's end time (`alarm_events` semantics).
    last_timestamp_s: f64,
}

/// Everything a session knows; guarded by the slot's async mutex (batches of a vehicle serialise).
#[derive(Debug)]
struct SessionState {
    model: LoadedModel,
    detector: Detector,
    samples: u64,
    trajectories: u32,
    last_seq: u64,
    last_timestamp_s: Option<f64>,
    alarm_active: bool,
    alarms_raised: u64,
    open_alarm: Option<OpenAlarm>,
}

impl SessionState {
    fn new(model: LoadedModel) -> Self {
        Self {
            detector: Detector::new(Arc::clone(&model.artifact)),
            model,
            samples: 0,
            trajectories: 0,
            last_seq: 0,
            last_timestamp_s: None,
            alarm_active: false,
            alarms_raised: 0,
            open_alarm: None,
        }
    }
}

#[derive(Debug)]
struct StreamOwner {
    id: u64,
    evicted: CancellationToken,
}

/// One vehicle's session.
#[derive(Debug)]
pub struct SessionSlot {
    vehicle_id: String,
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

/// The session table.
#[derive(Debug)]
pub struct SessionManager {
    slots: Mutex<HashMap<String, Arc<SessionSlot>>>,
    registry: Arc<Registry>,
    alarms: Arc<AlarmOutbox>,
    limits: SessionLimits,
    next_stream_id: AtomicU64,
    /// Held (shared) while a model is resolved and installed in a session, and exclusively while a
    /// model is deleted and its sessions end, so that no session can start on a deleted model.
    model_gate: tokio::sync::RwLock<()>,
}

impl SessionManager {
    pub fn new(registry: Arc<Registry>, alarms: Arc<AlarmOutbox>, limits: SessionLimits) -> Self {
        Self {
            slots: Mutex::new(HashMap::new()),
            registry,
            alarms,
            limits,
            next_stream_id: AtomicU64::new(1),
            model_gate: tokio::sync::RwLock::new(()),
        }
    }

    fn slots(&self) -> std::sync::MutexGuard<'_, HashMap<String, Arc<SessionSlot>>> {
        // A panic while holding this lock cannot leave the map inconsistent (single inserts/removes).
        self.slots.lock().unwrap_or_else(|p| p.into_inner())
    }

    fn lookup(&self, vehicle_id: &str) -> Option<Arc<SessionSlot>> {
        self.slots().get(vehicle_id).cloned()
    }

    /// Finds or creates the slot of a vehicle, within the session limit.
    fn slot_for(
        &self,
        vehicle_id: &str,
        model: &LoadedModel,
    ) -> Result<(Arc<SessionSlot>, bool), SessionError> {
        let mut slots = self.slots();
        if let Some(slot) = slots.get(vehicle_id) {
            return Ok((Arc::clone(slot), true));
        }
        if slots.len() >= self.limits.max_sessions {
            telemetry::session_refused();
            return Err(SessionError::Full(self.limits.max_sessions));
        }
        let slot = Arc::new(SessionSlot {
            vehicle_id: vehicle_id.to_string(),
            state: tokio::sync::Mutex::new(SessionState::new(model.clone())),
            owner: Mutex::new(None),
            last_activity_ms: AtomicI64::new(now_unix_ms()),
            model_deleted: CancellationToken::new(),
        });
        slots.insert(vehicle_id.to_string(), Arc::clone(&slot));
        Ok((slot, false))
    }

    /// Attaches a stream to a vehicle's session (creating or resuming it); an older stream on the same
    /// session is told to end. `vehicle_id` must be valid (checked at the edge); `model` `None`
    /// is the active model. A session on another model starts afresh.
    pub async fn attach(
        &self,
        vehicle_id: &str,
        model: Option<&ModelName>,
        reset: bool,
    ) -> Result<Attachment, SessionError> {
        let _gate = self.model_gate.read().await;
        let model = self.registry.resolve(model).await?;
        let (slot, existed) = self.slot_for(vehicle_id, &model)?;
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
        let replaced_model =
            (existed && state.model.name != model.name).then(|| state.model.name.clone());
        let resumed = existed && !reset && replaced_model.is_none();
        if !resumed {
            self.close_alarm(&mut state);
            *state = SessionState::new(model);
        }
        let accepted = Accepted {
            vehicle_id: vehicle_id.to_string(),
            model: state.model.name.clone(),
            resumed,
            samples_seen: state.samples,
            last_seq: state.last_seq,
            replaced_model,
        };
        drop(state);
        Ok(Attachment {
            slot,
            stream_id,
            evicted,
            accepted,
        })
    }

    /// Releases a stream's hold (if it still holds the session).
    pub fn detach(&self, attachment: &Attachment) {
        let slot = &attachment.slot;
        if let Ok(mut owner) = slot.owner.lock()
            && owner.as_ref().is_some_and(|o| o.id == attachment.stream_id)
        {
            *owner = None;
        }
        slot.touch();
    }

    /// Validates and runs one batch on a session. A rejected batch changes nothing.
    pub async fn process(
        &self,
        slot: &SessionSlot,
        seq: u64,
        samples: &[Sample],
        field: &str,
    ) -> Result<Decisions, SessionError> {
        let mut state = slot.state.lock().await;
        self.process_locked(slot, &mut state, seq, samples, field)
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
        validate_batch(
            samples,
            state.last_timestamp_s,
            self.limits.max_batch_samples,
            field,
        )
        .map_err(SessionError::InvalidBatch)?;
        let mut decisions = Vec::with_capacity(samples.len());
        for sample in samples {
            let decision = state.detector.step(sample, false);
            state.samples += 1;
            state.trajectories = decision.evidence.trajectory + 1;
            state.last_timestamp_s = Some(
                state
                    .last_timestamp_s
                    .map_or(sample.timestamp_s, |t| t.max(sample.timestamp_s)),
            );
            if decision.alarm_onset {
                state.alarms_raised += 1;
                self.open_alarm(
                    state,
                    &slot.vehicle_id,
                    sample.timestamp_s,
                    decision.probability,
                );
            } else if decision.alarm {
                if let Some(open) = state.open_alarm.as_mut() {
                    open.peak = open.peak.max(decision.probability);
                    open.samples += 1;
                    open.last_timestamp_s = sample.timestamp_s;
                }
            } else if decision.alarm_end {
                // This sample is the first non-alarming one; the event ends at the previous sample.
                self.close_alarm(state);
            }
            state.alarm_active = decision.alarm;
            decisions.push(decision);
        }
        state.last_seq = seq;
        slot.touch();
        Ok(Decisions {
            model: state.model.name.clone(),
            decisions,
        })
    }

    /// Queues an alarm onset.
    fn open_alarm(&self, state: &mut SessionState, vehicle: &str, timestamp_s: f64, p: f64) {
        let id = self
            .alarms
            .onset(vehicle, state.model.name.id(), timestamp_s, p);
        telemetry::alarm_onset();
        state.open_alarm = Some(OpenAlarm {
            id,
            peak: p,
            samples: 1,
            last_timestamp_s: timestamp_s,
        });
    }

    /// Queues the end of the current alarm at its last alarming sample (also when the session
    /// ends, resets or changes model while alarming).
    fn close_alarm(&self, state: &mut SessionState) {
        if let Some(open) = state.open_alarm.take() {
            self.alarms
                .end(open.id, open.last_timestamp_s, open.peak, open.samples);
            telemetry::alarm_end();
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
        Ok(Decisions {
            model: model.name,
            decisions: samples.iter().map(|s| detector.step(s, false)).collect(),
        })
    }

    /// Runs a batch for a vehicle without attaching a stream (creating the session if needed).
    /// `model` `None` is the active model; a session on another model, or with `reset`, starts
    /// afresh if the batch is valid. `seq` becomes the session's `last_seq` (`None` keeps it).
    /// `vehicle_id` must be valid (checked at the edge); `field` names the samples in violations.
    pub async fn detect_unattached(
        &self,
        vehicle_id: &str,
        model: Option<&ModelName>,
        reset: bool,
        seq: Option<u64>,
        samples: &[Sample],
        field: &str,
    ) -> Result<Decisions, SessionError> {
        if !reset
            && let Some(slot) = self.lookup(vehicle_id)
            && !slot.model_deleted.is_cancelled()
        {
            let mut state = slot.state.lock().await;
            if self.runs(&state, model) {
                let seq = seq.unwrap_or(state.last_seq);
                return self.process_locked(&slot, &mut state, seq, samples, field);
            }
        }
        // A model to resolve and install: a new session, a reset, or another model.
        let _gate = self.model_gate.read().await;
        let model = self.registry.resolve(model).await?;
        // Starting afresh needs a batch valid on a fresh session: a refused batch changes nothing
        // and leaves no new session behind.
        validate_batch(samples, None, self.limits.max_batch_samples, field)
            .map_err(SessionError::InvalidBatch)?;
        let (slot, _) = self.slot_for(vehicle_id, &model)?;
        let mut state = slot.state.lock().await;
        if reset || state.model.name != model.name {
            self.close_alarm(&mut state);
            *state = SessionState::new(model);
        }
        let seq = seq.unwrap_or(state.last_seq);
        self.process_locked(&slot, &mut state, seq, samples, field)
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
            }
            ended += 1;
        }
        if ended > 0 {
            tracing::info!(model = %name, sessions = ended, "ended the sessions of a deleted model");
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
            alarm_active: state.alarm_active,
            alarms_raised: state.alarms_raised,
            last_seq: state.last_seq,
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
            (true, Some(last)) => last.vehicle_id.clone(),
            _ => String::new(),
        };
        (sessions, next_page_token)
    }

    /// One vehicle's session.
    pub async fn get(&self, vehicle_id: &str) -> Result<SessionSummary, SessionError> {
        let slot = self
            .lookup(vehicle_id)
            .ok_or_else(|| SessionError::NotFound(vehicle_id.to_string()))?;
        Ok(self.describe(&slot).await)
    }

    /// Forgets a session's history but keeps its model.
    pub async fn reset(&self, vehicle_id: &str) -> Result<SessionSummary, SessionError> {
        let slot = self
            .lookup(vehicle_id)
            .ok_or_else(|| SessionError::NotFound(vehicle_id.to_string()))?;
        {
            let mut state = slot.state.lock().await;
            self.close_alarm(&mut state);
            let model = state.model.clone();
            *state = SessionState::new(model);
        }
        slot.touch();
        Ok(self.describe(&slot).await)
    }

    /// Removes sessions without a stream that were idle longer than the limit; returns how many.
    pub async fn evict_idle(&self) -> usize {
        let cutoff = now_unix_ms() - self.limits.idle.as_millis() as i64;
        let idle: Vec<Arc<SessionSlot>> = {
            let mut slots = self.slots();
            let ids: Vec<String> = slots
                .values()
                .filter(|s| !s.connected() && s.last_activity_ms.load(Ordering::Relaxed) < cutoff)
                .map(|s| s.vehicle_id.clone())
                .collect();
            ids.iter().filter_map(|id| slots.remove(id)).collect()
        };
        for slot in &idle {
            let mut state = slot.state.lock().await;
            self.close_alarm(&mut state);
        }
        telemetry::sessions_evicted(idle.len());
        idle.len()
    }

    /// Sessions held, and how many of them have a live stream (for metrics; one pass under the
    /// table's lock, like the evictor's).
    pub fn counts(&self) -> (usize, usize) {
        let slots = self.slots();
        let connected = slots.values().filter(|s| s.connected()).count();
        (slots.len(), connected)
    }

    /// Closes every open alarm (shutdown).
    pub async fn close_all_alarms(&self) {
        let slots: Vec<Arc<SessionSlot>> = self.slots().values().cloned().collect();
        for slot in slots {
            let mut state = slot.state.lock().await;
            self.close_alarm(&mut state);
        }
    }
}
