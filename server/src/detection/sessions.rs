//! Per-vehicle sessions: a detector each, ownership by at most one stream (a newer stream takes
//! over), a bounded count, idle eviction, and alarm onsets/ends persisted to SQLite.

use std::collections::HashMap;
use std::sync::atomic::{AtomicI64, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use spoofwatch_core::detector::Detector;
use spoofwatch_proto::v1;
use tokio_util::sync::CancellationToken;
use tonic::Status;

use super::validate::{validate_batch, vehicle_id_violation};
use crate::convert::{detection_to_proto, timestamp_from_ms};
use crate::error::{invalid_argument, invalid_field, not_found, resource_exhausted};
use crate::registry::{LoadedModel, Registry};
use crate::store::{Store, now_unix_ms};

/// Bounds on the in-memory session table.
#[derive(Clone, Copy, Debug)]
pub struct SessionLimits {
    pub max_sessions: usize,
    /// A session with no stream attached is evicted after this long without activity.
    pub idle: Duration,
    /// Most samples in one batch.
    pub max_batch_samples: usize,
}

/// An alarm currently on, as recorded in `alarm_events`.
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
    pub accepted: v1::SessionAccepted,
}

/// The session table.
#[derive(Debug)]
pub struct SessionManager {
    slots: Mutex<HashMap<String, Arc<SessionSlot>>>,
    registry: Arc<Registry>,
    store: Store,
    limits: SessionLimits,
    next_stream_id: AtomicU64,
}

impl SessionManager {
    pub fn new(registry: Arc<Registry>, store: Store, limits: SessionLimits) -> Self {
        Self {
            slots: Mutex::new(HashMap::new()),
            registry,
            store,
            limits,
            next_stream_id: AtomicU64::new(1),
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
    ) -> Result<(Arc<SessionSlot>, bool), Status> {
        let mut slots = self.slots();
        if let Some(slot) = slots.get(vehicle_id) {
            return Ok((Arc::clone(slot), true));
        }
        if slots.len() >= self.limits.max_sessions {
            return Err(resource_exhausted(format!(
                "the server holds its maximum of {} vehicle sessions",
                self.limits.max_sessions
            )));
        }
        let slot = Arc::new(SessionSlot {
            vehicle_id: vehicle_id.to_string(),
            state: tokio::sync::Mutex::new(SessionState::new(model.clone())),
            owner: Mutex::new(None),
            last_activity_ms: AtomicI64::new(now_unix_ms()),
        });
        slots.insert(vehicle_id.to_string(), Arc::clone(&slot));
        Ok((slot, false))
    }

    /// Attaches a stream to a vehicle's session (creating or resuming it); an older stream on the same
    /// session is told to end (ABORTED).
    pub async fn attach(&self, start: &v1::SessionStart) -> Result<Attachment, Status> {
        if let Some(problem) = vehicle_id_violation(&start.vehicle_id) {
            return Err(invalid_field("start.vehicle_id", problem));
        }
        let existing = self.lookup(&start.vehicle_id);
        let model = match (&existing, start.model.is_empty()) {
            (Some(slot), true) => slot.state.lock().await.model.clone(),
            _ => self.registry.resolve(&start.model).await?,
        };
        let (slot, existed) = self.slot_for(&start.vehicle_id, &model)?;
        let evicted = CancellationToken::new();
        let stream_id = self.next_stream_id.fetch_add(1, Ordering::Relaxed);
        if let Ok(mut owner) = slot.owner.lock()
            && let Some(previous) = owner.replace(StreamOwner {
                id: stream_id,
                evicted: evicted.clone(),
            })
        {
            previous.evicted.cancel();
            tracing::info!(vehicle = %start.vehicle_id, "a newer stream took the session over");
        }
        slot.touch();
        let mut state = slot.state.lock().await;
        let resumed = existed && !start.reset && state.model.id == model.id;
        if !resumed {
            self.close_alarm(&mut state).await;
            *state = SessionState::new(model);
        }
        let accepted = v1::SessionAccepted {
            vehicle_id: start.vehicle_id.clone(),
            model: state.model.name(),
            resumed,
            samples_seen: state.samples,
            last_seq: state.last_seq,
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
        samples: &[v1::Sample],
        field: &str,
    ) -> Result<Vec<v1::Detection>, Status> {
        let mut state = slot.state.lock().await;
        let batch = validate_batch(
            samples,
            state.last_timestamp_s,
            self.limits.max_batch_samples,
            field,
        )
        .map_err(invalid_argument)?;
        let model_name = state.model.name();
        let mut detections = Vec::with_capacity(batch.len());
        for sample in &batch {
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
                    &mut state,
                    &slot.vehicle_id,
                    sample.timestamp_s,
                    decision.probability,
                )
                .await;
            } else if decision.alarm {
                if let Some(open) = state.open_alarm.as_mut() {
                    open.peak = open.peak.max(decision.probability);
                    open.samples += 1;
                    open.last_timestamp_s = sample.timestamp_s;
                }
            } else if decision.alarm_end {
                // This sample is the first non-alarming one; the event ends at the previous sample.
                self.close_alarm(&mut state).await;
            }
            state.alarm_active = decision.alarm;
            detections.push(detection_to_proto(
                sample.timestamp_s,
                &decision,
                &model_name,
            ));
        }
        state.last_seq = seq;
        slot.touch();
        Ok(detections)
    }

    /// Records an alarm onset. A failed write is logged and retried at the alarm's end (as a closed
    /// event), so the alarm is not lost while the database recovers.
    async fn open_alarm(&self, state: &mut SessionState, vehicle: &str, timestamp_s: f64, p: f64) {
        match self
            .store
            .open_alarm(vehicle, &state.model.id, timestamp_s, p)
            .await
        {
            Ok(id) => {
                state.open_alarm = Some(OpenAlarm {
                    id,
                    peak: p,
                    samples: 1,
                    last_timestamp_s: timestamp_s,
                })
            }
            Err(error) => tracing::error!(%error, vehicle, "could not record an alarm onset"),
        }
    }

    /// Records the end of the current alarm at its last alarming sample (also when the session
    /// ends, resets or changes model while alarming).
    async fn close_alarm(&self, state: &mut SessionState) {
        let Some(open) = state.open_alarm.take() else {
            return;
        };
        if let Err(error) = self
            .store
            .close_alarm(open.id, open.last_timestamp_s, open.peak, open.samples)
            .await
        {
            tracing::error!(%error, alarm = open.id, "could not record an alarm end");
        }
    }

    /// Runs a batch for a vehicle without a stream (creating the session if needed), or on a
    /// throw-away detector when `vehicle_id` is empty.
    pub async fn detect_unary(
        &self,
        request: &v1::DetectRequest,
    ) -> Result<v1::DetectResponse, Status> {
        if request.vehicle_id.is_empty() {
            let model = self.registry.resolve(&request.model).await?;
            let batch = validate_batch(
                &request.samples,
                None,
                self.limits.max_batch_samples,
                "samples",
            )
            .map_err(invalid_argument)?;
            let mut detector = Detector::new(Arc::clone(&model.artifact));
            let name = model.name();
            let detections = batch
                .iter()
                .map(|s| detection_to_proto(s.timestamp_s, &detector.step(s, false), &name))
                .collect();
            return Ok(v1::DetectResponse {
                detections,
                model: name,
            });
        }
        if let Some(problem) = vehicle_id_violation(&request.vehicle_id) {
            return Err(invalid_field("vehicle_id", problem));
        }
        let slot = match self.lookup(&request.vehicle_id) {
            Some(slot) if request.model.is_empty() => slot,
            Some(slot) => {
                let model = self.registry.resolve(&request.model).await?;
                let mut state = slot.state.lock().await;
                if state.model.id != model.id {
                    self.close_alarm(&mut state).await;
                    *state = SessionState::new(model);
                }
                drop(state);
                slot
            }
            None => {
                let model = self.registry.resolve(&request.model).await?;
                self.slot_for(&request.vehicle_id, &model)?.0
            }
        };
        let last_seq = slot.state.lock().await.last_seq;
        let detections = self
            .process(&slot, last_seq, &request.samples, "samples")
            .await?;
        let model = slot.state.lock().await.model.name();
        Ok(v1::DetectResponse { detections, model })
    }

    async fn describe(&self, slot: &SessionSlot) -> v1::Session {
        let state = slot.state.lock().await;
        v1::Session {
            vehicle_id: slot.vehicle_id.clone(),
            model: state.model.name(),
            connected: slot.connected(),
            samples: state.samples,
            trajectories: state.trajectories,
            alarm_active: state.alarm_active,
            alarms_raised: state.alarms_raised,
            last_seq: state.last_seq,
            last_timestamp_s: state.last_timestamp_s.unwrap_or(0.0),
            last_activity: Some(timestamp_from_ms(
                slot.last_activity_ms.load(Ordering::Relaxed),
            )),
        }
    }

    /// Sessions ordered by vehicle id; the page token is the last vehicle id returned.
    pub async fn list(
        &self,
        page_size: i32,
        page_token: &str,
    ) -> Result<v1::ListSessionsResponse, Status> {
        if page_size < 0 {
            return Err(invalid_field("page_size", "must not be negative"));
        }
        let size = match page_size {
            0 => 100,
            n => (n as usize).min(1000),
        };
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
        Ok(v1::ListSessionsResponse {
            sessions,
            next_page_token,
        })
    }

    /// One vehicle's session.
    pub async fn get(&self, vehicle_id: &str) -> Result<v1::Session, Status> {
        let slot = self
            .lookup(vehicle_id)
            .ok_or_else(|| not_found("session", vehicle_id))?;
        Ok(self.describe(&slot).await)
    }

    /// Forgets a session's history but keeps its model.
    pub async fn reset(&self, vehicle_id: &str) -> Result<v1::Session, Status> {
        let slot = self
            .lookup(vehicle_id)
            .ok_or_else(|| not_found("session", vehicle_id))?;
        {
            let mut state = slot.state.lock().await;
            self.close_alarm(&mut state).await;
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
            self.close_alarm(&mut state).await;
        }
        idle.len()
    }

    /// Closes every open alarm (shutdown).
    pub async fn close_all_alarms(&self) {
        let slots: Vec<Arc<SessionSlot>> = self.slots().values().cloned().collect();
        for slot in slots {
            let mut state = slot.state.lock().await;
            self.close_alarm(&mut state).await;
        }
    }
}
