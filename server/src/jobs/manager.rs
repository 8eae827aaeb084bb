//! The job manager: admission (datasets exist, the queue has room), the queue and its concurrency
//! limit, cancellation, waiting, and reads of job rows. It hands admitted jobs to the
//! [`Runner`]; it must not execute use cases itself nor know about wire messages.
//!
//! Replicas sharing one database: a job is owned by the server instance that admitted it, which
//! queues and runs it in memory and renews its lease in the store every [`LEASE_RENEWAL`]
//! ([`JobManager::keep_leases`]). The same loop applies cancellations requested through another
//! replica, and fails the jobs of replicas whose lease expired ([`JOB_LEASE`]): a replica that dies
//! mid-job leaves it failed as [`JobFailure::Abandoned`], as a restart always did. Reads, cancel and
//! wait work from any replica (waiting polls the store for jobs that live elsewhere).

use std::collections::HashMap;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use spoofwatch_proto::wire::{DatasetName, ModelName, OperationName};
use tokio::sync::{Semaphore, watch};
use tokio_util::sync::CancellationToken;

use super::records::{EvaluationRequest, JobRequest, Progress, to_json};
use super::runner::{JobFailure, LiveJob, Runner};
use crate::datasets::{Catalog, DatasetError};
use crate::fault::Fault;
use crate::fault_log::FaultLog;
use crate::identity::new_id;
use crate::models::{Registry, RegistryError};
use crate::store::{
    EpochRow, JobEndError, JobFilter, JobKind, JobRow, NewJob, Page, PageRequest, Store,
    StoreError, now_unix_ms,
};
use crate::telemetry;

/// How often a server renews the leases of its jobs (and looks for cancellations and abandoned
/// jobs): the delay of a cancellation requested through another replica.
pub const LEASE_RENEWAL: Duration = Duration::from_secs(1);

/// A job whose lease was not renewed for this long has lost its owner and is failed. Many renewals
/// long, so that a slow database or a busy owner is not taken for a dead one.
pub const JOB_LEASE: Duration = Duration::from_secs(30);

/// How often a wait re-reads a job that runs on another replica.
const REMOTE_POLL: Duration = Duration::from_millis(250);

/// Limits of the job manager.
#[derive(Clone, Copy, Debug)]
pub struct JobSettings {
    /// Jobs running at once.
    pub max_running: usize,
    /// Jobs queued or running at once; more are refused.
    pub max_pending: usize,
    /// KiB of stored dataset input that running jobs together may read.
    pub input_kib: usize,
}

/// Why a job request or a job operation was refused.
#[derive(Debug, thiserror::Error)]
pub enum JobError {
    /// A dataset the job would read does not exist.
    #[error("{field}: dataset {name} not found")]
    DatasetNotFound {
        /// The request field naming it, e.g. `datasets[1]`.
        field: String,
        /// The missing dataset.
        name: DatasetName,
    },
    /// The queue is full.
    #[error("{0} jobs are already queued or running")]
    QueueFull(usize),
    /// The job's datasets alone hold more than running jobs may read at once.
    #[error(
        "the job's datasets hold {} MiB, more than the {} MiB that running jobs may read at once \
         (--job-input-mib)",
        .input_kib.div_ceil(1024),
        .limit_kib / 1024
    )]
    InputTooLarge { input_kib: usize, limit_kib: usize },
    /// No job has this name.
    #[error("operation {0} not found")]
    NotFound(OperationName),
    /// The model to evaluate cannot be served.
    #[error(transparent)]
    Model(#[from] RegistryError),
    /// A dataset could not be read.
    #[error(transparent)]
    Dataset(#[from] DatasetError),
    /// The store failed or refused (e.g. deleting an unfinished job).
    #[error(transparent)]
    Store(#[from] StoreError),
}

/// Queues, runs (through the [`Runner`]) and tracks jobs.
#[derive(Debug)]
pub struct JobManager {
    /// Executes admitted jobs and records their ends.
    runner: Runner,
    /// The job rows: admission, reads, cancellation and leases (the runner's store, shared).
    store: Store,
    /// Where an evaluation's model is resolved at admission.
    registry: Arc<Registry>,
    /// Where admission finds a job's datasets and their sizes.
    catalog: Catalog,
    settings: JobSettings,
    /// This server's instance id: the owner of the jobs it admits.
    instance: String,
    slots: Arc<Semaphore>,
    /// KiB of dataset input, taken by each running job for its datasets' stored size.
    input: Arc<Semaphore>,
    live: Mutex<HashMap<OperationName, Arc<LiveJob>>>,
}

impl JobManager {
    pub fn new(runner: Runner, settings: JobSettings, instance: String) -> Arc<Self> {
        Arc::new(Self {
            slots: Arc::new(Semaphore::new(settings.max_running.max(1))),
            input: Arc::new(Semaphore::new(settings.input_kib)),
            store: runner.store.clone(),
            registry: Arc::clone(&runner.registry),
            catalog: runner.catalog.clone(),
            runner,
            settings,
            instance,
            live: Mutex::new(HashMap::new()),
        })
    }

    fn live(&self) -> std::sync::MutexGuard<'_, HashMap<OperationName, Arc<LiveJob>>> {
        // Single inserts/removes cannot leave the map inconsistent, so a poisoned lock is usable.
        self.live.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// A receiver that changes whenever the job does (None: the job is not live in this process).
    pub fn subscribe(&self, name: &OperationName) -> Option<watch::Receiver<u64>> {
        self.live().get(name).map(|j| j.changes.subscribe())
    }

    /// Queues an evaluation of `model` (`None`: the model active now) on `datasets`.
    pub async fn create_evaluation(
        self: &Arc<Self>,
        model: Option<&ModelName>,
        datasets: Vec<DatasetName>,
    ) -> Result<JobRow, JobError> {
        let model = self.registry.resolve(model).await?;
        let request = JobRequest::Evaluation(EvaluationRequest {
            model: model.name,
            datasets,
        });
        self.create(request).await
    }

    /// The model a job starts from, fixed when it is created: `requested`, or the active model.
    pub async fn fixed_model(&self, requested: Option<&ModelName>) -> Result<ModelName, JobError> {
        Ok(self.registry.resolve(requested).await?.name)
    }

    /// Checks that every dataset of `request` exists and that together they fit the input budget,
    /// then queues it.
    pub async fn create(self: &Arc<Self>, request: JobRequest) -> Result<JobRow, JobError> {
        let mut input_bytes = 0_usize;
        for (field, name) in request.datasets() {
            match self.catalog.get(name).await {
                Ok(row) => {
                    let size = usize::try_from(row.size_bytes).unwrap_or(usize::MAX);
                    input_bytes = input_bytes.saturating_add(size);
                }
                Err(DatasetError::NotFound(name)) => {
                    return Err(JobError::DatasetNotFound { field, name });
                }
                Err(other) => return Err(other.into()),
            }
        }
        let (kind, progress) = match &request {
            JobRequest::Training(t) => (
                JobKind::Training,
                Progress {
                    max_epochs: t.max_epochs,
                    ..Progress::default()
                },
            ),
            JobRequest::Evaluation(_) => (JobKind::Evaluation, Progress::default()),
        };
        let input_kib = input_bytes.div_ceil(1024);
        if input_kib > self.settings.input_kib {
            return Err(JobError::InputTooLarge {
                input_kib,
                limit_kib: self.settings.input_kib,
            });
        }
        if self.live().len() >= self.settings.max_pending {
            return Err(JobError::QueueFull(self.settings.max_pending));
        }
        let name = OperationName::from_id(new_id());
        let insert = self.store.insert_job(NewJob {
            id: name.id().to_string(),
            kind,
            request: to_json(&request),
            metadata: to_json(&progress),
            owner: self.instance.clone(),
        });
        let row = telemetry::db_timed("job_create", insert).await?;
        let live = Arc::new(LiveJob::new());
        self.live().insert(name.clone(), Arc::clone(&live));
        let manager = Arc::clone(self);
        tokio::spawn(async move { manager.run(name, request, input_kib, live).await });
        Ok(row)
    }

    /// Waits for room for its input and a slot (or a cancellation), has the runner execute the
    /// job, records its end.
    async fn run(
        self: Arc<Self>,
        name: OperationName,
        request: JobRequest,
        input_kib: usize,
        live: Arc<LiveJob>,
    ) {
        // Admission checked that the input fits the budget, so the count fits u32 permits.
        let input_permits = u32::try_from(input_kib).unwrap_or(u32::MAX);
        let admitted = async {
            let input = Arc::clone(&self.input)
                .acquire_many_owned(input_permits)
                .await?;
            let slot = Arc::clone(&self.slots).acquire_owned().await?;
            Ok::<_, tokio::sync::AcquireError>((input, slot))
        };
        let result = tokio::select! {
            permits = admitted => match permits {
                Ok(_permits) => self.runner.execute(&name, request, &live).await,
                Err(_) => Err(JobFailure::Worker(Fault::new(
                    "waiting for a job slot",
                    "the job queue is closed",
                ))),
            },
            _ = live.cancel.cancelled() => Err(JobFailure::Cancelled),
        };
        telemetry::job_finished(match &result {
            Ok(_) => "succeeded",
            Err(JobFailure::Cancelled) => "cancelled",
            Err(_) => "failed",
        });
        self.runner.record_end(&name, result).await;
        self.live().remove(&name);
        live.notify();
        tracing::info!(job = %name, "job finished");
    }

    /// A job's row.
    pub async fn get(&self, name: &OperationName) -> Result<JobRow, JobError> {
        self.store
            .get_job(name.id())
            .await?
            .ok_or_else(|| JobError::NotFound(name.clone()))
    }

    /// A job's per-epoch history.
    pub async fn epochs(&self, row: &JobRow) -> Result<Vec<EpochRow>, JobError> {
        Ok(self.store.job_epochs(&row.id).await?)
    }

    /// One page of jobs, newest first.
    pub async fn list(
        &self,
        filter: &JobFilter,
        page: &PageRequest,
    ) -> Result<Page<JobRow>, JobError> {
        Ok(self.store.list_jobs(filter, page).await?)
    }

    /// Deletes a finished job.
    pub async fn delete(&self, name: &OperationName) -> Result<(), JobError> {
        Ok(self.store.delete_job(name.id()).await?)
    }

    /// Requests cancellation (queued jobs end at once, running ones at the next batch boundary).
    pub async fn cancel(&self, name: &OperationName) -> Result<(), JobError> {
        let row = self.get(name).await?;
        if row.state.is_finished() {
            return Ok(()); // google.longrunning: cancelling a finished operation is a no-op.
        }
        self.store.request_cancel(name.id()).await?;
        if let Some(job) = self.live().get(name) {
            job.cancel.cancel();
        }
        Ok(())
    }

    /// Waits until the job finishes or `timeout` passes; returns its latest row. A job live in this
    /// process is watched; one that runs on another replica is polled.
    pub async fn wait(&self, name: &OperationName, timeout: Duration) -> Result<JobRow, JobError> {
        let deadline = tokio::time::Instant::now() + timeout;
        let mut changes = self.subscribe(name);
        loop {
            let row = self.get(name).await?;
            let now = tokio::time::Instant::now();
            if row.state.is_finished() || now >= deadline {
                return Ok(row);
            }
            match changes.as_mut() {
                Some(rx) => match tokio::time::timeout_at(deadline, rx.changed()).await {
                    Ok(Ok(())) => {}
                    Ok(Err(_)) => changes = None, // the job left the live set: read the final row
                    Err(_) => return Ok(row),
                },
                None => tokio::time::sleep_until(deadline.min(now + REMOTE_POLL)).await,
            }
        }
    }

    /// Startup recovery: fails the jobs an earlier run of this instance left, and those of
    /// replicas whose lease expired. Returns how many were failed.
    pub async fn fail_abandoned_at_start(&self) -> Result<u64, StoreError> {
        let cutoff = now_unix_ms() - JOB_LEASE.as_millis() as i64;
        let store = &self.store;
        store
            .fail_abandoned_jobs(&abandoned(), &self.instance, true, cutoff)
            .await
    }

    /// Until `stop`: every [`LEASE_RENEWAL`], renews this instance's job leases, cancels the live
    /// jobs flagged for cancellation (through any replica) or finished elsewhere, and fails the
    /// jobs of other instances whose lease expired. A failing database is logged and retried.
    pub async fn keep_leases(self: Arc<Self>, stop: CancellationToken) {
        let mut tick = tokio::time::interval(LEASE_RENEWAL);
        tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
        // Each store fault is logged once when it starts and once when it clears.
        let (renewing, looking) = (FaultLog::default(), FaultLog::default());
        loop {
            tokio::select! {
                _ = stop.cancelled() => return,
                _ = tick.tick() => {}
            }
            let store = &self.store;
            match store.renew_job_leases(&self.instance, now_unix_ms()).await {
                Ok(owned) => {
                    if renewing.succeeded() {
                        tracing::info!("the leases of this server's jobs are renewed again");
                    }
                    self.apply_stored_state(&owned);
                }
                Err(error) => {
                    if renewing.failed() {
                        tracing::warn!(
                            %error,
                            "could not renew the leases of this server's jobs; retrying every second"
                        );
                    }
                    continue; // never judge others' leases while ours may be lapsing
                }
            }
            let cutoff = now_unix_ms() - JOB_LEASE.as_millis() as i64;
            let found = store
                .fail_abandoned_jobs(&abandoned(), &self.instance, false, cutoff)
                .await;
            match found {
                Ok(failed) => {
                    if looking.succeeded() {
                        tracing::info!("looking for abandoned jobs works again");
                    }
                    if failed > 0 {
                        tracing::warn!(
                            failed,
                            "failed jobs whose server stopped renewing their lease"
                        );
                    }
                }
                Err(error) => {
                    if looking.failed() {
                        tracing::warn!(%error, "could not look for abandoned jobs; retrying every second");
                    }
                }
            }
        }
    }

    /// Cancels the live jobs that `owned` (this instance's unfinished jobs in the store, with
    /// their cancel flag) flags, or no longer lists because they were finished elsewhere.
    fn apply_stored_state(&self, owned: &[(String, bool)]) {
        for (name, job) in self.live().iter() {
            let stored = owned.iter().find(|(id, _)| id == name.id());
            let cancel = match stored {
                Some((_, cancel_requested)) => *cancel_requested,
                None => true,
            };
            if cancel && !job.cancel.is_cancelled() {
                tracing::info!(job = %name, "cancelling a job as the store says");
                job.cancel.cancel();
            }
        }
    }

    /// Jobs waiting for a slot and jobs running (for metrics): a running job holds a slot.
    pub fn counts(&self) -> (usize, usize) {
        let live = self.live().len();
        let held = self.settings.max_running.max(1) - self.slots.available_permits();
        (live.saturating_sub(held), held.min(live))
    }

    /// Cancels every live job and waits (bounded) for them to record their end.
    pub async fn shutdown(&self, wait: Duration) {
        let jobs: Vec<Arc<LiveJob>> = self.live().values().cloned().collect();
        for job in &jobs {
            job.cancel.cancel();
        }
        let deadline = Instant::now() + wait;
        while !self.live().is_empty() && Instant::now() < deadline {
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
    }
}

/// The error recorded for a job whose server stopped or died while it was queued or running.
fn abandoned() -> JobEndError {
    JobEndError::from(JobFailure::Abandoned)
}
