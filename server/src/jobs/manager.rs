//! The job manager: admission (datasets exist, the queue has room), the queue and its concurrency
//! limit, cancellation, waiting, and reads of job rows. It hands admitted jobs to the
//! [`Runner`]; it must not execute use cases itself nor know about wire messages.

use std::collections::HashMap;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use spoofwatch_proto::wire::{DatasetName, ModelName, OperationName};
use tokio::sync::{Semaphore, watch};

use super::records::{EvaluationRequest, JobRequest, Progress, to_json};
use super::runner::{JobFailure, LiveJob, Runner};
use crate::datasets::DatasetError;
use crate::fault::Fault;
use crate::identity::new_id;
use crate::models::RegistryError;
use crate::store::{EpochRow, JobFilter, JobKind, JobRow, NewJob, Page, PageRequest, StoreError};
use crate::telemetry;

/// Limits of the job manager.
#[derive(Clone, Copy, Debug)]
pub struct JobSettings {
    /// Jobs running at once.
    pub max_running: usize,
    /// Jobs queued or running at once; more are refused.
    pub max_pending: usize,
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
    runner: Runner,
    settings: JobSettings,
    slots: Arc<Semaphore>,
    live: Mutex<HashMap<OperationName, Arc<LiveJob>>>,
}

impl JobManager {
    pub fn new(runner: Runner, settings: JobSettings) -> Arc<Self> {
        Arc::new(Self {
            slots: Arc::new(Semaphore::new(settings.max_running.max(1))),
            runner,
            settings,
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
        let model = self.runner.registry.resolve(model).await?;
        let request = JobRequest::Evaluation(EvaluationRequest {
            model: model.name,
            datasets,
        });
        self.create(request).await
    }

    /// Checks that every dataset of `request` exists, then queues it.
    pub async fn create(self: &Arc<Self>, request: JobRequest) -> Result<JobRow, JobError> {
        for (field, name) in request.datasets() {
            match self.runner.catalog.get(name).await {
                Ok(_) => {}
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
        if self.live().len() >= self.settings.max_pending {
            return Err(JobError::QueueFull(self.settings.max_pending));
        }
        let name = OperationName::from_id(new_id());
        let insert = self.runner.store.insert_job(NewJob {
            id: name.id().to_string(),
            kind,
            request: to_json(&request),
            metadata: to_json(&progress),
        });
        let row = telemetry::db_timed("job_create", insert).await?;
        let live = Arc::new(LiveJob::new());
        self.live().insert(name.clone(), Arc::clone(&live));
        let manager = Arc::clone(self);
        tokio::spawn(async move { manager.run(name, request, live).await });
        Ok(row)
    }

    /// Waits for a slot (or a cancellation), has the runner execute the job, records its end.
    async fn run(self: Arc<Self>, name: OperationName, request: JobRequest, live: Arc<LiveJob>) {
        let result = tokio::select! {
            permit = Arc::clone(&self.slots).acquire_owned() => match permit {
                Ok(_permit) => self.runner.execute(&name, request, &live).await,
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
        self.runner
            .store
            .get_job(name.id())
            .await?
            .ok_or_else(|| JobError::NotFound(name.clone()))
    }

    /// A job's per-epoch history.
    pub async fn epochs(&self, row: &JobRow) -> Result<Vec<EpochRow>, JobError> {
        Ok(self.runner.store.job_epochs(&row.id).await?)
    }

    /// One page of jobs, newest first.
    pub async fn list(
        &self,
        filter: &JobFilter,
        page: &PageRequest,
    ) -> Result<Page<JobRow>, JobError> {
        Ok(self.runner.store.list_jobs(filter, page).await?)
    }

    /// Deletes a finished job.
    pub async fn delete(&self, name: &OperationName) -> Result<(), JobError> {
        Ok(self.runner.store.delete_job(name.id()).await?)
    }

    /// Requests cancellation (queued jobs end at once, running ones at the next batch boundary).
    pub async fn cancel(&self, name: &OperationName) -> Result<(), JobError> {
        let row = self.get(name).await?;
        if row.state.is_finished() {
            return Ok(()); // google.longrunning: cancelling a finished operation is a no-op.
        }
        self.runner.store.request_cancel(name.id()).await?;
        if let Some(job) = self.live().get(name) {
            job.cancel.cancel();
        }
        Ok(())
    }

    /// Waits until the job finishes or `timeout` passes; returns its latest row.
    pub async fn wait(&self, name: &OperationName, timeout: Duration) -> Result<JobRow, JobError> {
        let deadline = tokio::time::Instant::now() + timeout;
        let mut changes = self.subscribe(name);
        loop {
            let row = self.get(name).await?;
            if row.state.is_finished() {
                return Ok(row);
            }
            let Some(rx) = changes.as_mut() else {
                return Ok(row);
            };
            match tokio::time::timeout_at(deadline, rx.changed()).await {
                Ok(Ok(())) => {}
                Ok(Err(_)) => changes = None, // the job left the live set: read the final row
                Err(_) => return Ok(row),
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
