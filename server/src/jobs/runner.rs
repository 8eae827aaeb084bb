//! The job manager: queue, concurrency limit, progress, cancellation, results.

use std::collections::HashMap;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use serde::{Deserialize, Serialize};
use spoofwatch_core::evaluation::evaluate_tracks;
use spoofwatch_core::metrics::{EventRules, Metrics};
use spoofwatch_core::model::{Ablation, FeatureGroups};
use spoofwatch_core::sample::Track;
use spoofwatch_core::train::detector::{
    TrainDetectorError, TrainedDetector, TrainingData, train_detector,
};
use spoofwatch_core::train::spec::{KappaRho, TrainingSpec};
use spoofwatch_core::train::{
    DEFAULT_MAX_EPOCHS, DEFAULT_SEED, EpochProgress, MAX_EPOCHS, TrainError,
};
use spoofwatch_proto::v1;
use tokio::sync::{Semaphore, mpsc, watch};
use tokio_util::sync::CancellationToken;
use tonic::Status;

use crate::convert::timestamp_from_ms;
use crate::datasets::load_dataset;
use crate::error::{invalid_field, not_found, resource_exhausted};
use crate::registry::{Registry, new_id};
use crate::store::{EpochRow, JobKind, JobOutcome, JobRow, JobState, ModelSource, NewJob, Store};

/// Limits of the job manager.
#[derive(Clone, Copy, Debug)]
pub struct JobSettings {
    /// Jobs running at once.
    pub max_running: usize,
    /// Jobs queued or running at once; more are refused with RESOURCE_EXHAUSTED.
    pub max_pending: usize,
}

/// What a job was asked to do (the `request_json` column).
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum JobRequest {
    Training {
        datasets: Vec<String>,
        validation_datasets: Vec<String>,
        seed: u64,
        max_epochs: u32,
        ablation: Ablation,
        select_kappa_rho: bool,
        display_name: String,
        activate: bool,
    },
    Evaluation {
        model: String,
        datasets: Vec<String>,
    },
}

/// Live progress (the `metadata_json` column).
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
pub struct Progress {
    pub epoch: u32,
    pub max_epochs: u32,
    pub train_loss: f64,
    pub val_loss: f64,
    pub val_auroc: Option<f64>,
    pub eta_s: Option<f64>,
    pub message: String,
}

/// A finished job's result (the `result_json` column).
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum JobResult {
    Training {
        model_id: String,
        validation: Metrics,
        test: Option<Metrics>,
    },
    Evaluation {
        model: String,
        overall: Metrics,
        per_vehicle: Vec<(String, Metrics)>,
    },
}

/// A job known to this process (queued or running).
#[derive(Debug)]
struct LiveJob {
    cancel: CancellationToken,
    /// Bumped on every change; watchers re-read the store.
    changes: watch::Sender<u64>,
}

/// Queues, runs and tracks jobs.
#[derive(Debug)]
pub struct JobManager {
    store: Store,
    registry: Arc<Registry>,
    settings: JobSettings,
    slots: Arc<Semaphore>,
    live: Mutex<HashMap<String, Arc<LiveJob>>>,
}

/// The wire's feature-group name; empty means the default.
fn features_from_name(name: &str) -> Option<FeatureGroups> {
    if name.is_empty() {
        Some(FeatureGroups::default())
    } else {
        FeatureGroups::from_name(name)
    }
}

impl JobManager {
    pub fn new(store: Store, registry: Arc<Registry>, settings: JobSettings) -> Arc<Self> {
        Arc::new(Self {
            slots: Arc::new(Semaphore::new(settings.max_running.max(1))),
            store,
            registry,
            settings,
            live: Mutex::new(HashMap::new()),
        })
    }

    fn live(&self) -> std::sync::MutexGuard<'_, HashMap<String, Arc<LiveJob>>> {
        self.live.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// A receiver that changes whenever the job does (None: the job is not live in this process).
    pub fn subscribe(&self, id: &str) -> Option<watch::Receiver<u64>> {
        self.live().get(id).map(|j| j.changes.subscribe())
    }

    /// Validates and queues a training job.
    pub async fn create_training(
        self: &Arc<Self>,
        request: v1::CreateTrainingJobRequest,
    ) -> Result<JobRow, Status> {
        if request.datasets.is_empty() {
            return Err(invalid_field(
                "datasets",
                "at least one dataset is required",
            ));
        }
        let spec = request.spec.unwrap_or_default();
        let max_epochs = if spec.max_epochs == 0 {
            DEFAULT_MAX_EPOCHS
        } else {
            spec.max_epochs
        };
        if max_epochs > MAX_EPOCHS {
            return Err(invalid_field(
                "spec.max_epochs",
                format!("must be 1 to {MAX_EPOCHS}"),
            ));
        }
        let features = features_from_name(&spec.features).ok_or_else(|| {
            invalid_field(
                "spec.features",
                "one of all, no-accumulation, no-evolution, no-evolution-no-q, low-order-only, validity-only",
            )
        })?;
        for (field, names) in [
            ("datasets", &request.datasets),
            ("validation_datasets", &request.validation_datasets),
        ] {
            for (i, name) in names.iter().enumerate() {
                let id = crate::convert::strip_collection("datasets", name);
                if self.store.get_dataset(id).await?.is_none() {
                    let mut status = not_found("dataset", name);
                    status =
                        Status::new(status.code(), format!("{field}[{i}]: {}", status.message()));
                    return Err(status);
                }
            }
        }
        let job = JobRequest::Training {
            datasets: request.datasets,
            validation_datasets: request.validation_datasets,
            seed: if spec.seed == 0 {
                DEFAULT_SEED
            } else {
                spec.seed
            },
            max_epochs,
            ablation: Ablation {
                no_exchange: spec.no_exchange,
                no_third_order: spec.no_third_order,
                first_order_cell: spec.first_order_cell,
                features,
            },
            select_kappa_rho: spec.select_kappa_rho,
            display_name: request.display_name,
            activate: request.activate,
        };
        let progress = Progress {
            max_epochs,
            ..Progress::default()
        };
        self.enqueue(JobKind::Training, job, progress).await
    }

    /// Validates and queues an evaluation job.
    pub async fn create_evaluation(
        self: &Arc<Self>,
        request: v1::CreateEvaluationJobRequest,
    ) -> Result<JobRow, Status> {
        if request.datasets.is_empty() {
            return Err(invalid_field(
                "datasets",
                "at least one dataset is required",
            ));
        }
        let model = self.registry.resolve(&request.model).await?;
        for name in &request.datasets {
            let id = crate::convert::strip_collection("datasets", name);
            if self.store.get_dataset(id).await?.is_none() {
                return Err(not_found("dataset", name));
            }
        }
        let job = JobRequest::Evaluation {
            model: model.id,
            datasets: request.datasets,
        };
        self.enqueue(JobKind::Evaluation, job, Progress::default())
            .await
    }

    async fn enqueue(
        self: &Arc<Self>,
        kind: JobKind,
        request: JobRequest,
        progress: Progress,
    ) -> Result<JobRow, Status> {
        if self.live().len() >= self.settings.max_pending {
            return Err(resource_exhausted(format!(
                "{} jobs are already queued or running",
                self.settings.max_pending
            )));
        }
        let id = new_id();
        let row = self
            .store
            .insert_job(NewJob {
                id: id.clone(),
                kind,
                request: to_json(&request),
                metadata: to_json(&progress),
            })
            .await?;
        let live = Arc::new(LiveJob {
            cancel: CancellationToken::new(),
            changes: watch::channel(0).0,
        });
        self.live().insert(id.clone(), Arc::clone(&live));
        let manager = Arc::clone(self);
        tokio::spawn(async move { manager.run(id, request, live).await });
        Ok(row)
    }

    /// Requests cancellation (queued jobs end at once, running ones at the next batch boundary).
    pub async fn cancel(&self, id: &str) -> Result<(), Status> {
        let row = self
            .store
            .get_job(id)
            .await?
            .ok_or_else(|| not_found("operation", &format!("operations/{id}")))?;
        if row.state.is_finished() {
            return Ok(()); // google.longrunning: cancelling a finished operation is a no-op.
        }
        self.store.request_cancel(id).await?;
        if let Some(job) = self.live().get(id) {
            job.cancel.cancel();
        }
        Ok(())
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

    fn notify(live: &LiveJob) {
        live.changes.send_modify(|n| *n += 1);
    }

    async fn run(self: Arc<Self>, id: String, request: JobRequest, live: Arc<LiveJob>) {
        let outcome = tokio::select! {
            permit = Arc::clone(&self.slots).acquire_owned() => match permit {
                Ok(_permit) => self.execute(&id, request, &live).await,
                Err(_) => Err(JobFailure::Failed("the job queue is closed".into())),
            },
            _ = live.cancel.cancelled() => Err(JobFailure::Cancelled),
        };
        let outcome = match outcome {
            Ok(result) => JobOutcome::Succeeded {
                result: to_json(&result),
            },
            Err(JobFailure::Cancelled) => JobOutcome::Cancelled {
                message: "cancelled".into(),
            },
            Err(JobFailure::Failed(message)) => JobOutcome::Failed {
                code: tonic::Code::FailedPrecondition as i32,
                message,
            },
        };
        if let Err(error) = self.store.finish_job(&id, outcome).await {
            tracing::error!(%error, job = %id, "could not record the end of a job");
        }
        self.live().remove(&id);
        Self::notify(&live);
        tracing::info!(job = %id, "job finished");
    }

    async fn execute(
        &self,
        id: &str,
        request: JobRequest,
        live: &Arc<LiveJob>,
    ) -> Result<JobResult, JobFailure> {
        self.store
            .mark_running(id)
            .await
            .map_err(JobFailure::from_status)?;
        Self::notify(live);
        match request {
            JobRequest::Training {
                datasets,
                validation_datasets,
                seed,
                max_epochs,
                ablation,
                select_kappa_rho,
                display_name,
                activate,
            } => {
                let data = TrainingData::split_unless_validation(
                    self.load(&datasets).await?,
                    self.load(&validation_datasets).await?,
                );
                let spec = TrainingSpec {
                    data_description: datasets.clone(),
                    ..TrainingSpec::with(
                        seed,
                        max_epochs,
                        ablation,
                        KappaRho::selected_if(select_kappa_rho),
                    )
                };
                let trained = Arc::new(self.train(id, live, spec, data).await?);
                if trained.cancelled {
                    return Err(JobFailure::Cancelled);
                }
                let test_metrics = {
                    let trained = Arc::clone(&trained);
                    tokio::task::spawn_blocking(move || trained.held_out_metrics(EventRules::Spec))
                        .await
                        .map_err(|e| JobFailure::Failed(e.to_string()))?
                };
                let model_id = new_id();
                let name = if display_name.is_empty() {
                    format!("trained by operations/{id}")
                } else {
                    display_name
                };
                self.registry
                    .register(
                        &model_id,
                        &name,
                        ModelSource::Training,
                        Some(format!("operations/{id}")),
                        &trained.artifact,
                    )
                    .await
                    .map_err(JobFailure::from_status)?;
                if activate {
                    self.registry
                        .activate(&model_id)
                        .await
                        .map_err(JobFailure::from_status)?;
                }
                Ok(JobResult::Training {
                    model_id,
                    validation: trained.validation.clone(),
                    test: test_metrics,
                })
            }
            JobRequest::Evaluation { model, datasets } => {
                let loaded = self
                    .registry
                    .resolve(&model)
                    .await
                    .map_err(JobFailure::from_status)?;
                let tracks = self.load(&datasets).await?;
                let artifact = Arc::clone(&loaded.artifact);
                let evaluation = tokio::task::spawn_blocking(move || {
                    evaluate_tracks(&artifact, &tracks, EventRules::Spec)
                })
                .await
                .map_err(|e| JobFailure::Failed(e.to_string()))?;
                Ok(JobResult::Evaluation {
                    model: loaded.name(),
                    overall: evaluation.overall,
                    per_vehicle: evaluation.per_vehicle,
                })
            }
        }
    }

    async fn load(&self, names: &[String]) -> Result<Vec<Track>, JobFailure> {
        let mut tracks = Vec::new();
        for name in names {
            tracks.extend(
                load_dataset(&self.store, name)
                    .await
                    .map_err(JobFailure::from_status)?,
            );
        }
        Ok(tracks)
    }

    /// Runs training on a blocking thread; epochs stream back to be persisted and announced.
    async fn train(
        &self,
        id: &str,
        live: &Arc<LiveJob>,
        spec: TrainingSpec,
        data: TrainingData,
    ) -> Result<TrainedDetector, JobFailure> {
        let cancel_flag = Arc::new(AtomicBool::new(false));
        let (epochs_tx, mut epochs_rx) = mpsc::unbounded_channel::<EpochProgress>();
        let flag = Arc::clone(&cancel_flag);
        let worker = tokio::task::spawn_blocking(move || {
            train_detector(
                &spec,
                data,
                &mut |p| {
                    let _ = epochs_tx.send(p.clone());
                },
                &flag,
            )
        });
        let max_epochs = match self.store.get_job(id).await {
            Ok(Some(row)) => serde_json::from_value::<Progress>(row.metadata)
                .map(|p| p.max_epochs)
                .unwrap_or(0),
            _ => 0,
        };
        let started = Instant::now();
        let mut epoch_index = 0u32;
        loop {
            tokio::select! {
                _ = live.cancel.cancelled(), if !cancel_flag.load(Ordering::Relaxed) => {
                    cancel_flag.store(true, Ordering::Relaxed);
                }
                epoch = epochs_rx.recv() => {
                    let Some(p) = epoch else { break };
                    epoch_index += 1;
                    let row = EpochRow {
                        epoch: epoch_index,
                        train_loss: p.train_loss,
                        val_loss: p.val_loss,
                        val_auroc: p.val_auroc,
                        learning_rate: p.learning_rate,
                        elapsed_s: p.elapsed_s,
                    };
                    if let Err(error) = self.store.append_epoch(id, &row).await {
                        tracing::warn!(%error, job = id, "could not record an epoch");
                    }
                    let per_epoch = started.elapsed().as_secs_f64() / f64::from(epoch_index);
                    let progress = Progress {
                        epoch: epoch_index,
                        max_epochs,
                        train_loss: p.train_loss,
                        val_loss: p.val_loss,
                        val_auroc: p.val_auroc,
                        eta_s: Some(per_epoch * f64::from(max_epochs.saturating_sub(epoch_index))),
                        message: String::new(),
                    };
                    let _ = self
                        .store
                        .update_job_metadata(id, &to_json(&progress))
                        .await;
                    Self::notify(live);
                }
            }
        }
        let trained = worker
            .await
            .map_err(|e| JobFailure::Failed(format!("training thread failed: {e}")))?;
        trained.map_err(|e| match e {
            // Cancelled before the first epoch completed: still a cancellation, not a failure.
            TrainDetectorError::Train(TrainError::Cancelled) => JobFailure::Cancelled,
            other => JobFailure::Failed(other.to_string()),
        })
    }
}

/// How a job failed.
#[derive(Debug)]
enum JobFailure {
    Cancelled,
    Failed(String),
}

impl JobFailure {
    fn from_status(status: impl Into<Status>) -> Self {
        let status: Status = status.into();
        JobFailure::Failed(status.message().to_string())
    }
}

/// JSON for the store's opaque columns (our own types always serialise).
fn to_json<T: Serialize>(value: &T) -> serde_json::Value {
    serde_json::to_value(value).unwrap_or_default()
}

/// The wire metadata of a job.
pub fn job_metadata(row: &JobRow, epochs: &[EpochRow]) -> v1::JobMetadata {
    let progress: Progress = serde_json::from_value(row.metadata.clone()).unwrap_or_default();
    let state = match row.state {
        JobState::Queued => v1::JobState::Queued,
        JobState::Running => v1::JobState::Running,
        JobState::Succeeded => v1::JobState::Succeeded,
        JobState::Failed => v1::JobState::Failed,
        JobState::Cancelled => v1::JobState::Cancelled,
    };
    v1::JobMetadata {
        name: format!("operations/{}", row.id),
        kind: match row.kind {
            JobKind::Training => "training",
            JobKind::Evaluation => "evaluation",
        }
        .to_string(),
        state: state as i32,
        create_time: Some(timestamp_from_ms(row.created_at_ms)),
        start_time: row.started_at_ms.map(timestamp_from_ms),
        end_time: row.finished_at_ms.map(timestamp_from_ms),
        epoch: progress.epoch,
        max_epochs: progress.max_epochs,
        train_loss: progress.train_loss,
        val_loss: progress.val_loss,
        val_auroc: progress.val_auroc,
        eta_s: if row.state.is_finished() {
            None
        } else {
            progress.eta_s
        },
        history: epochs
            .iter()
            .map(|e| v1::EpochRecord {
                epoch: e.epoch,
                train_loss: e.train_loss,
                val_loss: e.val_loss,
                val_auroc: e.val_auroc,
                learning_rate: e.learning_rate,
                elapsed_s: e.elapsed_s,
            })
            .collect(),
        message: row.error_message.clone().unwrap_or(progress.message),
    }
}
