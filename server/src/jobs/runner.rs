//! The job runner: executes one admitted job's use case (training or evaluation) on blocking
//! threads, persists its progress and its end through the store, and keeps the real cause of a
//! failure ([`JobFailure`], mapped to a gRPC code and to the error the job records once in
//! `crate::error`). It must not queue or admit jobs (that is `jobs::manager`) nor know about wire
//! messages (that is `jobs::service`).

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Instant;

use spoofwatch_core::evaluation::evaluate_tracks;
use spoofwatch_core::fleet_fit::{FleetFitError, FleetFitSpec, fit_fleet};
use spoofwatch_core::metrics::EventRules;
use spoofwatch_core::model::artifact::ModelArtifact;
use spoofwatch_core::train::detector::{TrainDetectorError, TrainingData, train_detector};
use spoofwatch_core::train::spec::{AnchorRebase, KappaRho, TrainingSpec};
use spoofwatch_core::train::{EpochProgress, TrainError};
use spoofwatch_proto::wire::OperationName;
use tokio::sync::{mpsc, watch};
use tokio_util::sync::CancellationToken;

use super::records::{
    EvaluationRequest, JobRequest, JobResult, Progress, TrainingRequest, to_json,
};
use crate::datasets::{Catalog, DatasetError};
use crate::fault::Fault;
use crate::identity::new_id;
use crate::models::{Registry, RegistryError};
use crate::store::{EpochRow, JobEndError, JobOutcome, ModelSource, Store, StoreError};
use crate::telemetry;
use crate::work::at_low_priority;

/// Why a job did not succeed: its real cause, so the operation's error gets the right code.
#[derive(Debug, thiserror::Error)]
pub enum JobFailure {
    /// Cancelled on request (or by the shutdown).
    #[error("cancelled")]
    Cancelled,
    /// A dataset is gone or unreadable.
    #[error(transparent)]
    Dataset(#[from] DatasetError),
    /// The model is gone, or the trained one could not be registered.
    #[error(transparent)]
    Model(#[from] RegistryError),
    /// The store failed.
    #[error(transparent)]
    Store(#[from] StoreError),
    /// Training refused the data or found no operating point.
    #[error("training: {0}")]
    Training(TrainDetectorError),
    /// A fleet fit refused the recordings (naming the field) or could not inject its attacks.
    #[error("fleet fit: {0}")]
    Fit(FleetFitError),
    /// A fleet fit's request contradicts its starting model.
    #[error("{field}: {reason}")]
    FitRequest { field: &'static str, reason: String },
    /// A worker thread panicked or was aborted, or the job queue closed.
    #[error(transparent)]
    Worker(#[from] Fault),
    /// Its server stopped or died while it was queued or running (found by the recovery of
    /// abandoned jobs, never by a runner).
    #[error("server restarted while the job was queued or running")]
    Abandoned,
}

/// A job queued or running in this process.
#[derive(Debug)]
pub struct LiveJob {
    pub cancel: CancellationToken,
    /// Bumped on every change; watchers re-read the store.
    pub changes: watch::Sender<u64>,
}

impl LiveJob {
    pub fn new() -> Self {
        Self {
            cancel: CancellationToken::new(),
            changes: watch::channel(0).0,
        }
    }

    /// Tells watchers the job changed.
    pub fn notify(&self) {
        self.changes.send_modify(|n| *n += 1);
    }
}

/// A training failure as the job's: a cancelled training is a cancellation, not a failure.
fn training_failure(error: TrainDetectorError) -> JobFailure {
    match error {
        TrainDetectorError::Train(TrainError::Cancelled) => JobFailure::Cancelled,
        other => JobFailure::Training(other),
    }
}

/// Runs jobs' use cases; cheap to clone.
#[derive(Debug, Clone)]
pub struct Runner {
    pub store: Store,
    pub registry: Arc<Registry>,
    pub catalog: Catalog,
}

impl Runner {
    /// Marks the job running and executes it.
    pub async fn execute(
        &self,
        id: &OperationName,
        request: JobRequest,
        live: &LiveJob,
    ) -> Result<JobResult, JobFailure> {
        telemetry::db_timed("job_start", self.store.mark_running(id.id())).await?;
        live.notify();
        match request {
            JobRequest::Training(training) => self.train_model(id, training, live).await,
            JobRequest::Evaluation(evaluation) => self.evaluate(evaluation).await,
        }
    }

    /// Records how the job ended. A failure is recorded with the error its cause maps to.
    pub async fn record_end(&self, id: &OperationName, result: Result<JobResult, JobFailure>) {
        let outcome = match result {
            Ok(result) => JobOutcome::Succeeded {
                result: to_json(&result),
            },
            Err(failure @ JobFailure::Cancelled) => {
                JobOutcome::Cancelled(JobEndError::from(failure))
            }
            Err(failure) => JobOutcome::Failed(JobEndError::from(failure)),
        };
        // Nobody waits on this background task's result: the failure is logged with its cause, and
        // the row stays unfinished until the next start marks it failed.
        let finish = self.store.finish_job(id.id(), outcome);
        if let Err(error) = telemetry::db_timed("job_finish", finish).await {
            tracing::error!(%error, job = %id, "could not record the end of a job");
        }
    }

    /// Trains a detector on the request's datasets and registers it.
    async fn train_model(
        &self,
        id: &OperationName,
        request: TrainingRequest,
        live: &LiveJob,
    ) -> Result<JobResult, JobFailure> {
        if request.fleet_fit.is_some() {
            return self.fit_to_fleet(id, request, live).await;
        }
        let TrainingRequest {
            datasets,
            validation_datasets,
            seed,
            max_epochs,
            schema,
            ablation,
            select_kappa_rho,
            display_name,
            activate,
            fleet_fit: _,
        } = request;
        let data = TrainingData::split_unless_validation(
            self.catalog.load_tracks(&datasets).await?,
            self.catalog.load_tracks(&validation_datasets).await?,
        );
        let spec = TrainingSpec {
            data_description: datasets.iter().map(ToString::to_string).collect(),
            ..TrainingSpec::with(
                seed,
                max_epochs,
                schema,
                ablation,
                KappaRho::selected_if(select_kappa_rho),
            )
        };
        let trained = self
            .with_epochs(id, live, max_epochs, move |on_epoch, cancel| {
                train_detector(&spec, data, on_epoch, cancel)
            })
            .await?
            .map_err(training_failure)?;
        let trained = Arc::new(trained);
        let test_metrics = {
            let trained = Arc::clone(&trained);
            tokio::task::spawn_blocking(move || {
                at_low_priority(|| trained.held_out_metrics(EventRules::Spec))
            })
            .await
            .map_err(|e| Fault::new("evaluating the test split", e))?
        };
        let model_id = self
            .register_trained(id, &display_name, &trained.artifact, activate)
            .await?;
        Ok(JobResult::Training {
            model_id,
            validation: trained.validation.clone(),
            test: test_metrics,
            fleet_fit: None,
        })
    }

    /// Fits the starting model to the fleet of the request's datasets (attack-free recordings)
    /// and registers the fitted model with its report.
    async fn fit_to_fleet(
        &self,
        id: &OperationName,
        request: TrainingRequest,
        live: &LiveJob,
    ) -> Result<JobResult, JobFailure> {
        let Some(fit) = request.fleet_fit else {
            unreachable!("fit_to_fleet is only called for fleet-fit requests")
        };
        let starting = self.registry.resolve(Some(&fit.starting_model)).await?;
        let starting_schema = starting.artifact.model.config().schema;
        if let Some(named) = fit.schema.filter(|s| *s != starting_schema) {
            return Err(JobFailure::FitRequest {
                field: "spec.feature_schema",
                reason: format!(
                    "a fleet fit keeps its starting model's schema ({}), not {}",
                    starting_schema.name(),
                    named.name()
                ),
            });
        }
        let recordings = self.catalog.load_tracks(&request.datasets).await?;
        let validation = self
            .catalog
            .load_tracks(&request.validation_datasets)
            .await?;
        let spec = FleetFitSpec {
            seed: request.seed,
            max_epochs: request.max_epochs,
            from_scratch: fit.from_scratch,
            sample_rate_hz: fit.sample_rate_hz,
            data_description: request.datasets.iter().map(ToString::to_string).collect(),
            anchor_rebase: AnchorRebase::Margin,
        };
        let artifact = Arc::clone(&starting.artifact);
        let fitted = self
            .with_epochs(id, live, request.max_epochs, move |on_epoch, cancel| {
                fit_fleet(&spec, &recordings, &validation, &artifact, on_epoch, cancel)
            })
            .await?
            .map_err(|error| match error {
                FleetFitError::Train(error) => training_failure(error),
                other => JobFailure::Fit(other),
            })?;
        if fitted.cancelled {
            return Err(JobFailure::Cancelled);
        }
        let name = if request.display_name.is_empty() {
            format!("fitted to a fleet by {id}")
        } else {
            request.display_name
        };
        let model_id = self
            .register_trained(id, &name, &fitted.artifact, request.activate)
            .await?;
        Ok(JobResult::Training {
            model_id,
            validation: fitted.validation,
            test: None,
            fleet_fit: Some(Box::new(fitted.report)),
        })
    }

    /// Registers a model the job made, named `display_name` (or after the job).
    async fn register_trained(
        &self,
        id: &OperationName,
        display_name: &str,
        artifact: &ModelArtifact,
        activate: bool,
    ) -> Result<String, JobFailure> {
        let model_id = new_id();
        let name = if display_name.is_empty() {
            format!("trained by {id}")
        } else {
            display_name.to_string()
        };
        self.registry
            .register(
                &model_id,
                &name,
                ModelSource::Training,
                Some(id),
                artifact,
                activate,
            )
            .await?;
        Ok(model_id)
    }

    /// Evaluates the request's model on its datasets.
    async fn evaluate(&self, request: EvaluationRequest) -> Result<JobResult, JobFailure> {
        let loaded = self.registry.resolve(Some(&request.model)).await?;
        let tracks = self.catalog.load_tracks(&request.datasets).await?;
        let artifact = Arc::clone(&loaded.artifact);
        let evaluation = tokio::task::spawn_blocking(move || {
            at_low_priority(|| evaluate_tracks(&artifact, &tracks, EventRules::Spec))
        })
        .await
        .map_err(|e| Fault::new("evaluating a model", e))?;
        Ok(JobResult::Evaluation {
            model: loaded.name.to_string(),
            overall: evaluation.overall,
            per_vehicle: evaluation.per_vehicle,
        })
    }

    /// Runs `work` (training of some kind) on a blocking thread at low priority; its epochs stream
    /// back to be persisted and announced, and a cancellation of the job sets its flag.
    async fn with_epochs<T: Send + 'static>(
        &self,
        id: &OperationName,
        live: &LiveJob,
        max_epochs: u32,
        work: impl FnOnce(&mut dyn FnMut(&EpochProgress), &AtomicBool) -> T + Send + 'static,
    ) -> Result<T, JobFailure> {
        let cancel_flag = Arc::new(AtomicBool::new(false));
        let (epochs_tx, mut epochs_rx) = mpsc::unbounded_channel::<EpochProgress>();
        let flag = Arc::clone(&cancel_flag);
        let worker = tokio::task::spawn_blocking(move || {
            at_low_priority(|| {
                work(
                    &mut |p| {
                        // The receiver lives until the worker ends; a send can only fail after
                        // that.
                        let _ = epochs_tx.send(p.clone());
                    },
                    &flag,
                )
            })
        });
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
                    self.record_epoch(id, epoch_index, &p, &progress).await;
                    live.notify();
                }
            }
        }
        Ok(worker.await.map_err(|e| Fault::new("training", e))?)
    }

    /// Persists one epoch's history row and the job's live progress. Best effort: progress is
    /// informational and training must not stop because a progress write failed, so failures are
    /// logged with their cause.
    async fn record_epoch(
        &self,
        id: &OperationName,
        epoch: u32,
        p: &EpochProgress,
        progress: &Progress,
    ) {
        let row = EpochRow {
            epoch,
            train_loss: p.train_loss,
            val_loss: p.val_loss,
            val_auroc: p.val_auroc,
            learning_rate: p.learning_rate,
            elapsed_s: p.elapsed_s,
        };
        let append = self.store.append_epoch(id.id(), &row);
        if let Err(error) = telemetry::db_timed("job_progress", append).await {
            tracing::warn!(%error, job = %id, "could not record an epoch");
        }
        let metadata = to_json(progress);
        let update = self.store.update_job_metadata(id.id(), &metadata);
        if let Err(error) = telemetry::db_timed("job_progress", update).await {
            tracing::warn!(%error, job = %id, "could not record the job's progress");
        }
    }
}
