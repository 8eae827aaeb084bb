//! Shadow evaluation of a candidate model: beside the live model, a registered candidate scores
//! every sample the chosen vehicles send, and what it would have alarmed on is stored apart from
//! the real alarms, with counts that compare the two.
//!
//! - [`scope`]: which vehicles (all, a share by a stable hash, a list).
//! - [`queue`]: the bound. The request path offers a copy of each scored batch and never waits; a
//!   batch that does not fit is shed, counted, and its vehicle's shadow state starts afresh.
//! - [`worker`]: one OS thread that scores within a CPU budget ([`worker::CPU_SHARE`] of a core),
//!   at idle CPU priority ([`priority`]: Linux `SCHED_IDLE`), so a busy server sheds shadow work
//!   before its live replies wait.
//! - [`vehicle`] and [`tally`]: one vehicle's would-be alarm and comparison, and the counts.
//! - [`writer`]: stores the would-be alarms in order and follows the stored shadow (every replica
//!   runs the running one; a restart resumes it).
//! - [`service`]: the ModelService shadow calls, decoded and answered (the models edge calls it).
//!
//! A would-be alarm never reaches the alarm outbox, WatchAlarms, incidents or the real alarm
//! metrics: this module must not touch `crate::outbox`, `crate::alarms` or the alarm tables. The
//! live path only calls [`Shadows::offer`].

mod metrics;
pub mod priority;
pub mod queue;
pub mod scope;
pub mod service;
pub mod tally;
mod vehicle;
mod worker;
mod writer;

use std::sync::{Arc, Mutex, PoisonError, RwLock};
use std::time::Duration;

use spoofwatch_core::detector::Decision;
use spoofwatch_core::sample::Sample;
use spoofwatch_proto::wire::{ModelName, VehicleId};
use tokio::sync::mpsc;
use tokio_util::sync::CancellationToken;

use crate::models::{LoadedModel, Registry, RegistryError};
use crate::store::{ShadowRow, Store, StoreError};
use queue::{Job, LiveSignal, Offer, ShadowQueue};
use scope::{ScopeError, ShadowScope};
use tally::Tally;

/// Most samples queued for the shadow's worker: about 8 s of a 1,000-vehicle fleet at 1 Hz.
pub const QUEUE_SAMPLES: usize = 8_192;
/// How often a server reads the stored shadow (to follow a start or stop made elsewhere) and
/// stores its counts.
pub const SHADOW_POLL: Duration = Duration::from_secs(2);
/// Writes waiting for the store.
const WRITES: usize = 1_024;

/// A shadow this server runs.
#[derive(Debug)]
pub struct Running {
    pub id: i64,
    pub scope: ShadowScope,
    pub model: LoadedModel,
}

/// Everything a shadow call can fail with.
#[derive(Debug, thiserror::Error)]
pub enum ShadowError {
    #[error("shadow {0} not found")]
    NotFound(String),
    #[error("no shadow was ever started")]
    NoneStarted,
    #[error("shadows/{0} is running: stop it before starting another (one shadow runs at a time)")]
    AlreadyRunning(i64),
    #[error("{}: {}", .0.field, .0.reason)]
    Scope(ScopeError),
    #[error(transparent)]
    Model(#[from] RegistryError),
    #[error(transparent)]
    Store(#[from] StoreError),
}

/// This process's counts for the shadow it runs.
#[derive(Debug, Default)]
pub struct SharedTally {
    inner: Mutex<(i64, Tally, bool)>,
}

impl SharedTally {
    fn lock(&self) -> std::sync::MutexGuard<'_, (i64, Tally, bool)> {
        self.inner.lock().unwrap_or_else(PoisonError::into_inner)
    }

    /// Adds counts of shadow `shadow_id` (dropped if another one runs now).
    pub fn add(&self, shadow_id: i64, delta: &Tally) {
        let mut inner = self.lock();
        if inner.0 == shadow_id {
            inner.1.add(delta);
            inner.2 = true;
        }
    }

    /// Adds scoring time; returns the vehicle-hours covered so far.
    pub fn add_scoring_time(&self, spent: Duration) -> f64 {
        let mut inner = self.lock();
        inner.1.scoring_seconds += spent.as_secs_f64();
        inner.1.vehicle_hours()
    }

    /// The counts, if they changed since the last call.
    fn take_dirty(&self) -> Option<(i64, Tally)> {
        let mut inner = self.lock();
        let dirty = std::mem::replace(&mut inner.2, false);
        (dirty && inner.0 != 0).then(|| (inner.0, inner.1.clone()))
    }

    fn mark_dirty(&self) {
        self.lock().2 = true;
    }

    /// Starts counting for `shadow_id` from zero.
    fn reset(&self, shadow_id: i64) {
        *self.lock() = (shadow_id, Tally::default(), true);
    }

    fn shadow_id(&self) -> i64 {
        self.lock().0
    }
}

/// The shadow subsystem of one server.
#[derive(Debug)]
pub struct Shadows {
    store: Store,
    registry: Arc<Registry>,
    queue: Arc<ShadowQueue>,
    running: Arc<RwLock<Option<Arc<Running>>>>,
    tally: Arc<SharedTally>,
    /// This process among the replicas: its instance id and start time (its counts' key).
    process: String,
    /// Serialises following the stored shadow with starting and stopping one.
    change: tokio::sync::Mutex<()>,
    worker: Mutex<Option<std::thread::JoinHandle<()>>>,
    writer: Mutex<Option<tokio::task::JoinHandle<()>>>,
}

impl Shadows {
    /// Starts the worker thread and the writer task (no shadow runs until [`Self::follow`] or a
    /// start). `idle`: vehicle states not scored for this long are let go.
    pub fn new(
        store: Store,
        registry: Arc<Registry>,
        instance: &str,
        idle: Duration,
    ) -> std::io::Result<Self> {
        let queue = Arc::new(ShadowQueue::new(QUEUE_SAMPLES));
        let running = Arc::new(RwLock::new(None));
        let tally = Arc::new(SharedTally::default());
        let (writes, pending) = mpsc::channel(WRITES);
        let worker = worker::Worker {
            queue: Arc::clone(&queue),
            running: Arc::clone(&running),
            tally: Arc::clone(&tally),
            writes,
            idle,
        };
        let worker = std::thread::Builder::new()
            .name("shadow".into())
            .spawn(move || worker.run())?;
        let writer = tokio::spawn(writer::store_writes(store.clone(), pending));
        Ok(Self {
            process: format!("{instance}/{}", crate::store::now_unix_ms()),
            store,
            registry,
            queue,
            running,
            tally,
            change: tokio::sync::Mutex::new(()),
            worker: Mutex::new(Some(worker)),
            writer: Mutex::new(Some(writer)),
        })
    }

    fn current(&self) -> Option<Arc<Running>> {
        self.running
            .read()
            .unwrap_or_else(PoisonError::into_inner)
            .clone()
    }

    /// The candidate of the running shadow, if any (a model under shadow is not deleted).
    pub fn candidate(&self) -> Option<ModelName> {
        self.current().map(|r| r.model.name.clone())
    }

    /// Offers a batch the live model scored (`decisions`, one per sample; `in_area`: each sample
    /// lay in an open incident's area) to the shadow, if it runs for this vehicle. Never waits: a
    /// batch that does not fit is shed and counted.
    pub fn offer(
        &self,
        vehicle_id: &VehicleId,
        samples: &[Sample],
        decisions: &[Decision],
        in_area: &[bool],
    ) {
        let Some(running) = self.current() else {
            return;
        };
        if !running.scope.includes(vehicle_id.as_str()) {
            return;
        }
        let live = decisions
            .iter()
            .zip(in_area)
            .map(|(d, &in_incident_area)| LiveSignal {
                alarm: d.alarm,
                onset: d.alarm_onset,
                escalation: d.escalation,
                in_incident_area,
            })
            .collect();
        let job = Job {
            shadow_id: running.id,
            vehicle_id: vehicle_id.to_string(),
            samples: samples.to_vec(),
            live,
            after_gap: false,
        };
        if self.queue.offer(job) == Offer::Shed {
            let shed = samples.len() as u64;
            self.tally.add(
                running.id,
                &Tally {
                    samples_shed: shed,
                    ..Tally::default()
                },
            );
            crate::telemetry::shadow_samples("shed", shed);
        }
    }

    /// Runs `row` (the stored running shadow) or nothing, as the store says; stores the counts of
    /// a shadow that stops running here.
    async fn run(&self, row: Option<ShadowRow>) -> Result<(), ShadowError> {
        let current = self.current();
        if current.as_ref().map(|r| r.id) == row.as_ref().map(|r| r.id) {
            return Ok(());
        }
        let next = match row {
            Some(row) => Some(Arc::new(self.load(row).await?)),
            None => None,
        };
        if let Some(old) = &current {
            self.flush().await;
            self.queue.stop(old.id);
            crate::telemetry::shadow_running(&old.model.name.to_string(), false);
        }
        if let Some(next) = &next {
            self.tally.reset(next.id);
            crate::telemetry::shadow_running(&next.model.name.to_string(), true);
            tracing::info!(shadow = next.id, model = %next.model.name, scope = %next.scope.describe(), "the shadow runs on this server");
        }
        *self.running.write().unwrap_or_else(PoisonError::into_inner) = next;
        Ok(())
    }

    /// A stored shadow made runnable: its scope decoded and its candidate loaded.
    async fn load(&self, row: ShadowRow) -> Result<Running, ShadowError> {
        let scope: ShadowScope = serde_json::from_value(row.scope_json.0.clone()).map_err(|e| {
            StoreError::InvalidValue {
                field: "shadows.scope_json",
                reason: e.to_string(),
            }
        })?;
        let name = ModelName::parse(&row.model_id).map_err(|e| StoreError::InvalidValue {
            field: "shadows.model_id",
            reason: e.to_string(),
        })?;
        let model = self.registry.resolve(Some(&name)).await?;
        Ok(Running {
            id: row.id,
            scope,
            model,
        })
    }

    /// Follows the stored shadow once: a start or stop made through another server (or before a
    /// restart) takes effect here.
    pub async fn follow(&self) -> Result<(), ShadowError> {
        let _change = self.change.lock().await;
        let row = self.store.running_shadow().await?;
        self.run(row).await
    }

    /// Stores this process's counts, if they changed.
    pub async fn flush(&self) {
        if let Some((shadow_id, tally)) = self.tally.take_dirty() {
            let value = serde_json::to_value(&tally).unwrap_or_default();
            if let Err(error) = self
                .store
                .put_shadow_tally(shadow_id, &self.process, &value)
                .await
            {
                tracing::warn!(%error, shadow = shadow_id, "the shadow's counts were not stored; retried");
                self.tally.mark_dirty();
            }
        }
    }

    /// Follows the stored shadow and stores the counts every [`SHADOW_POLL`] until `stop`; then
    /// lets the worker finish what is queued and stores the counts a last time.
    pub async fn keep_following(&self, stop: CancellationToken) {
        let mut tick = tokio::time::interval(SHADOW_POLL);
        loop {
            tokio::select! {
                _ = stop.cancelled() => break,
                _ = tick.tick() => {
                    if let Err(error) = self.follow().await {
                        tracing::warn!(%error, "the stored shadow was not read; retried");
                    }
                    self.flush().await;
                }
            }
        }
        self.queue.close();
        let worker = self
            .worker
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .take();
        if let Some(worker) = worker {
            let _ = tokio::task::spawn_blocking(move || worker.join()).await;
        }
        let writer = self
            .writer
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .take();
        if let Some(writer) = writer {
            let _ = writer.await;
        }
        self.flush().await;
    }

    /// The shadow id this process counts for (0: none yet).
    pub fn counting(&self) -> i64 {
        self.tally.shadow_id()
    }
}

impl Drop for Shadows {
    /// The worker ends with the server even when the follower did not get to close its queue.
    fn drop(&mut self) {
        self.queue.close();
    }
}
