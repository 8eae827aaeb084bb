//! TrainingService and google.longrunning.Operations: the edge between the wire and the
//! [`JobManager`]. Validates requests and fills the training defaults, converts job rows to
//! operations, and maps [`super::JobError`] once (through `crate::error`); it must not run jobs nor
//! touch the store.

use std::pin::Pin;
use std::sync::Arc;
use std::time::Duration;

use prost::Message;
use prost_types::Any;
use spoofwatch_core::evidence::FeatureSchema;
use spoofwatch_core::model::{Ablation, FeatureGroups};
use spoofwatch_core::train::{DEFAULT_MAX_EPOCHS, DEFAULT_SEED};
use spoofwatch_proto::longrunning;
use spoofwatch_proto::longrunning::operations_server::Operations;
use spoofwatch_proto::v1;
use spoofwatch_proto::v1::training_service_server::TrainingService;
use spoofwatch_proto::wire::convert::{metrics_to_proto, timestamp_from_ms};
use spoofwatch_proto::wire::fit::fit_report_to_proto;
use spoofwatch_proto::wire::limits::{MAX_OPERATION_WAIT, MAX_TRAINING_EPOCHS};
use spoofwatch_proto::wire::{ModelName, OperationName};
use tokio::sync::mpsc;
use tokio_stream::Stream;
use tokio_stream::wrappers::ReceiverStream;
use tonic::{Request, Response, Status};

use super::manager::JobManager;
use super::records::{FleetFitRequest, JobRequest, JobResult, Progress, TrainingRequest};
use crate::access::Caller;
use crate::edge::{dataset_names, display_name, operation_name, optional_model_name, page_request};
use crate::models::wire::model_to_proto;
use crate::models::{Registry, RegistryError};
use crate::status::invalid_field;
use crate::store::{EpochRow, JobFilter, JobKind, JobRow, JobState};

fn pack<M: Message>(type_name: &str, message: &M) -> Any {
    Any {
        type_url: format!("type.googleapis.com/{type_name}"),
        value: message.encode_to_vec(),
    }
}

/// A wire name of a choice whose empty value means the default.
fn named_or_default<T: Default>(name: &str, from_name: fn(&str) -> Option<T>) -> Option<T> {
    if name.is_empty() {
        Some(T::default())
    } else {
        from_name(name)
    }
}

/// A CreateTrainingJob request, validated and with its defaults filled in.
fn training_request(request: v1::CreateTrainingJobRequest) -> Result<TrainingRequest, Status> {
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
    if max_epochs > MAX_TRAINING_EPOCHS {
        return Err(invalid_field(
            "spec.max_epochs",
            format!("must be 1 to {MAX_TRAINING_EPOCHS}"),
        ));
    }
    let schema =
        named_or_default(&spec.feature_schema, FeatureSchema::from_name).ok_or_else(|| {
            invalid_field(
                "spec.feature_schema",
                format!(
                    "one of {}",
                    FeatureSchema::NAMED.map(|(name, _)| name).join(", ")
                ),
            )
        })?;
    let features = named_or_default(&spec.features, FeatureGroups::from_name).ok_or_else(|| {
        invalid_field(
            "spec.features",
            format!(
                "one of {}",
                FeatureGroups::NAMED.map(|(name, _)| name).join(", ")
            ),
        )
    })?;
    Ok(TrainingRequest {
        datasets: dataset_names("datasets", &request.datasets)?,
        validation_datasets: dataset_names("validation_datasets", &request.validation_datasets)?,
        seed: if spec.seed == 0 {
            DEFAULT_SEED
        } else {
            spec.seed
        },
        max_epochs,
        schema,
        ablation: Ablation {
            no_exchange: spec.no_exchange,
            no_third_order: spec.no_third_order,
            first_order_cell: spec.first_order_cell,
            features,
            ..Ablation::default()
        },
        select_kappa_rho: spec.select_kappa_rho,
        display_name: display_name("display_name", &request.display_name)?.to_string(),
        activate: request.activate,
        fleet_fit: None,
    })
}

/// Most a fleet fit's claimed sample rate may be (Hz).
const MAX_SAMPLE_RATE_HZ: f64 = 100.0;

/// A fleet fit's parameters, the starting model fixed now (the active one when none is named).
async fn fleet_fit_request(
    fit: &v1::FleetFit,
    named_schema: Option<FeatureSchema>,
    manager: &JobManager,
) -> Result<FleetFitRequest, Status> {
    let rate = fit.sample_rate_hz;
    if !(rate.is_finite() && (0.0..=MAX_SAMPLE_RATE_HZ).contains(&rate)) {
        return Err(invalid_field(
            "fleet_fit.sample_rate_hz",
            format!("must be 0 (any) or a rate up to {MAX_SAMPLE_RATE_HZ} Hz, got {rate}"),
        ));
    }
    let requested = optional_model_name("fleet_fit.starting_model", &fit.starting_model)?;
    let starting_model = manager.fixed_model(requested.as_ref()).await?;
    Ok(FleetFitRequest {
        starting_model,
        from_scratch: fit.from_scratch,
        sample_rate_hz: (rate > 0.0).then_some(rate),
        schema: named_schema,
    })
}

/// The wire metadata of a job.
fn job_metadata(row: &JobRow, epochs: &[EpochRow]) -> v1::JobMetadata {
    // Progress is informational: an unreadable value (never written by this version) shows as none.
    let progress: Progress = serde_json::from_value(row.metadata.clone())
        .inspect_err(|error| tracing::warn!(%error, job = %row.id, "unreadable job progress"))
        .unwrap_or_default();
    let state = match row.state {
        JobState::Queued => v1::JobState::Queued,
        JobState::Running => v1::JobState::Running,
        JobState::Succeeded => v1::JobState::Succeeded,
        JobState::Failed => v1::JobState::Failed,
        JobState::Cancelled => v1::JobState::Cancelled,
    };
    v1::JobMetadata {
        name: OperationName::from_id(row.id.as_str()).to_string(),
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

/// Shared by both services: turning job rows into operations.
#[derive(Debug, Clone)]
pub struct Jobs {
    pub manager: Arc<JobManager>,
    pub registry: Arc<Registry>,
}

impl Jobs {
    async fn metadata(&self, row: &JobRow) -> Result<v1::JobMetadata, Status> {
        let epochs = self.manager.epochs(row).await?;
        Ok(job_metadata(row, &epochs))
    }

    /// The model a training job produced, if it still exists.
    async fn trained_model(&self, model_id: &str) -> Result<Option<v1::Model>, Status> {
        match self.registry.get(&ModelName::from_id(model_id)).await {
            Ok(row) => Ok(Some(model_to_proto(&row))),
            Err(RegistryError::NotFound(_)) => Ok(None), // deleted since: the result still shows
            Err(other) => Err(other.into()),
        }
    }

    async fn operation(&self, row: &JobRow) -> Result<longrunning::Operation, Status> {
        use longrunning::operation::Result as OpResult;
        let metadata = self.metadata(row).await?;
        let result = match row.state {
            JobState::Succeeded => {
                // An unreadable result (never written by this version) leaves the response empty.
                let result: Option<JobResult> = row.result.clone().and_then(|v| {
                    serde_json::from_value(v)
                        .inspect_err(
                            |error| tracing::warn!(%error, job = %row.id, "unreadable job result"),
                        )
                        .ok()
                });
                match result {
                    Some(JobResult::Training {
                        model_id,
                        validation,
                        test,
                        fleet_fit,
                    }) => {
                        let model = self.trained_model(&model_id).await?;
                        Some(OpResult::Response(pack(
                            "spoofwatch.v1.TrainingJobResult",
                            &v1::TrainingJobResult {
                                model,
                                validation: Some(metrics_to_proto(&validation)),
                                test: test.as_ref().map(metrics_to_proto),
                                fleet_fit: fleet_fit.as_deref().map(fit_report_to_proto),
                            },
                        )))
                    }
                    Some(JobResult::Evaluation {
                        model,
                        overall,
                        per_vehicle,
                    }) => Some(OpResult::Response(pack(
                        "spoofwatch.v1.EvaluationJobResult",
                        &v1::EvaluationJobResult {
                            model,
                            overall: Some(metrics_to_proto(&overall)),
                            per_vehicle: per_vehicle
                                .iter()
                                .map(|(v, m)| (v.clone(), metrics_to_proto(m)))
                                .collect(),
                        },
                    ))),
                    None => None,
                }
            }
            JobState::Failed | JobState::Cancelled => Some(OpResult::Error(tonic_types::Status {
                code: row.error_code.unwrap_or(tonic::Code::Unknown as i32),
                message: row.error_message.clone().unwrap_or_default(),
                details: Vec::new(),
            })),
            JobState::Queued | JobState::Running => None,
        };
        Ok(longrunning::Operation {
            name: OperationName::from_id(row.id.as_str()).to_string(),
            metadata: Some(pack("spoofwatch.v1.JobMetadata", &metadata)),
            done: row.state.is_finished(),
            result,
        })
    }
}

/// The TrainingService implementation.
#[derive(Debug, Clone)]
pub struct TrainingApi {
    pub jobs: Jobs,
}

/// The google.longrunning.Operations implementation.
#[derive(Debug, Clone)]
pub struct OperationsApi {
    pub jobs: Jobs,
}

type WatchStream = Pin<Box<dyn Stream<Item = Result<v1::JobMetadata, Status>> + Send>>;

#[tonic::async_trait]
impl TrainingService for TrainingApi {
    async fn create_training_job(
        &self,
        request: Request<v1::CreateTrainingJobRequest>,
    ) -> Result<Response<longrunning::Operation>, Status> {
        let request = request.into_inner();
        let fit = request.fleet_fit.clone();
        let spec = request.spec.clone().unwrap_or_default();
        let mut training = training_request(request)?;
        if let Some(fit) = fit {
            let named = (!spec.feature_schema.is_empty()).then_some(training.schema);
            training.fleet_fit = Some(fleet_fit_request(&fit, named, &self.jobs.manager).await?);
        }
        let row = self
            .jobs
            .manager
            .create(JobRequest::Training(training))
            .await?;
        tracing::info!(job = %row.id, "training job queued");
        Ok(Response::new(self.jobs.operation(&row).await?))
    }

    async fn create_evaluation_job(
        &self,
        request: Request<v1::CreateEvaluationJobRequest>,
    ) -> Result<Response<longrunning::Operation>, Status> {
        let r = request.into_inner();
        if r.datasets.is_empty() {
            return Err(invalid_field(
                "datasets",
                "at least one dataset is required",
            ));
        }
        let model = optional_model_name("model", &r.model)?;
        let datasets = dataset_names("datasets", &r.datasets)?;
        let row = self
            .jobs
            .manager
            .create_evaluation(model.as_ref(), datasets)
            .await?;
        Ok(Response::new(self.jobs.operation(&row).await?))
    }

    type WatchJobStream = WatchStream;

    async fn watch_job(
        &self,
        request: Request<v1::WatchJobRequest>,
    ) -> Result<Response<Self::WatchJobStream>, Status> {
        let caller = Caller::of(&request)?;
        let name = operation_name("name", &request.into_inner().name)?;
        let first = self.jobs.manager.get(&name).await?;
        let (tx, rx) = mpsc::channel(8);
        tokio::spawn(watch(self.jobs.clone(), name, first, caller, tx));
        Ok(Response::new(Box::pin(ReceiverStream::new(rx))))
    }
}

/// Sends `first` and then each change of job `name` to a WatchJob client until the job finishes,
/// the client goes away, or the identity files no longer admit `caller`: the watch then ends with
/// the status [`Caller::until_revoked`] gives, and sends nothing after the change.
async fn watch(
    jobs: Jobs,
    name: OperationName,
    first: JobRow,
    mut caller: Caller,
    tx: mpsc::Sender<Result<v1::JobMetadata, Status>>,
) {
    let mut changes = jobs.manager.subscribe(&name);
    let mut row = first;
    loop {
        let metadata = jobs.metadata(&row).await;
        let done = row.state.is_finished();
        // Judged again just before sending: a change in force is never followed by an update.
        let update = caller.check_standing(None).and(metadata);
        let failed = update.is_err();
        if tx.send(update).await.is_err() || done || failed {
            return;
        }
        let changed = async {
            match changes.as_mut() {
                Some(rx) => {
                    if rx.changed().await.is_err() {
                        changes = None;
                    }
                }
                None => tokio::time::sleep(Duration::from_millis(200)).await,
            }
        };
        tokio::select! {
            biased;
            status = caller.until_revoked(None) => {
                let _ = tx.send(Err(status)).await;
                return;
            }
            () = changed => {}
        }
        match jobs.manager.get(&name).await {
            Ok(r) => row = r,
            Err(error) => {
                // The stream ends here either way; a gone client just misses the error.
                let _ = tx.send(Err(error.into())).await;
                return;
            }
        }
    }
}

fn parse_filter(filter: &str) -> Result<JobFilter, Status> {
    let mut parsed = JobFilter::default();
    for term in filter
        .split(" AND ")
        .map(str::trim)
        .filter(|t| !t.is_empty())
    {
        match term.split_once('=').map(|(k, v)| (k.trim(), v.trim())) {
            Some(("kind", "training")) => parsed.kind = Some(JobKind::Training),
            Some(("kind", "evaluation")) => parsed.kind = Some(JobKind::Evaluation),
            Some(("done", "true")) => parsed.done = Some(true),
            Some(("done", "false")) => parsed.done = Some(false),
            _ => {
                return Err(invalid_field(
                    "filter",
                    format!(
                        "unsupported term {term:?} (use kind=training|evaluation, done=true|false)"
                    ),
                ));
            }
        }
    }
    Ok(parsed)
}

#[tonic::async_trait]
impl Operations for OperationsApi {
    async fn list_operations(
        &self,
        request: Request<longrunning::ListOperationsRequest>,
    ) -> Result<Response<longrunning::ListOperationsResponse>, Status> {
        let r = request.into_inner();
        let page = page_request(r.page_size, &r.page_token)?;
        let page = self
            .jobs
            .manager
            .list(&parse_filter(&r.filter)?, &page)
            .await?;
        let mut operations = Vec::with_capacity(page.items.len());
        for row in &page.items {
            operations.push(self.jobs.operation(row).await?);
        }
        Ok(Response::new(longrunning::ListOperationsResponse {
            operations,
            next_page_token: page.next_page_token.unwrap_or_default(),
        }))
    }

    async fn get_operation(
        &self,
        request: Request<longrunning::GetOperationRequest>,
    ) -> Result<Response<longrunning::Operation>, Status> {
        let name = operation_name("name", &request.into_inner().name)?;
        let row = self.jobs.manager.get(&name).await?;
        Ok(Response::new(self.jobs.operation(&row).await?))
    }

    async fn delete_operation(
        &self,
        request: Request<longrunning::DeleteOperationRequest>,
    ) -> Result<Response<()>, Status> {
        let name = operation_name("name", &request.into_inner().name)?;
        self.jobs.manager.delete(&name).await?;
        Ok(Response::new(()))
    }

    async fn cancel_operation(
        &self,
        request: Request<longrunning::CancelOperationRequest>,
    ) -> Result<Response<()>, Status> {
        let name = operation_name("name", &request.into_inner().name)?;
        self.jobs.manager.cancel(&name).await?;
        Ok(Response::new(()))
    }

    async fn wait_operation(
        &self,
        request: Request<longrunning::WaitOperationRequest>,
    ) -> Result<Response<longrunning::Operation>, Status> {
        let mut caller = Caller::of(&request)?;
        let r = request.into_inner();
        let name = operation_name("name", &r.name)?;
        let timeout = match r.timeout {
            Some(d) if d.seconds < 0 || d.nanos < 0 => {
                return Err(invalid_field("timeout", "must not be negative"));
            }
            Some(d) => Duration::new(d.seconds as u64, d.nanos as u32).min(MAX_OPERATION_WAIT),
            None => MAX_OPERATION_WAIT,
        };
        // A wait lasts up to minutes: a change of the identity files that no longer admits the
        // caller ends it, as it ends a watch.
        let row = caller
            .unless_revoked(None, async {
                Ok(self.jobs.manager.wait(&name, timeout).await?)
            })
            .await?;
        caller.check_standing(None)?;
        Ok(Response::new(self.jobs.operation(&row).await?))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_training_request_without_a_schema_trains_the_bundled_default_s() {
        let request = v1::CreateTrainingJobRequest {
            datasets: vec!["datasets/d".to_string()],
            ..v1::CreateTrainingJobRequest::default()
        };
        let training = training_request(request).expect("valid");
        assert_eq!(training.schema, FeatureSchema::V3);
        assert!(training.fleet_fit.is_none());
    }

    #[test]
    fn filters_parse_and_bad_terms_are_named() {
        let f = parse_filter("kind=training AND done=false").expect("valid");
        assert_eq!((f.kind, f.done), (Some(JobKind::Training), Some(false)));
        assert_eq!(parse_filter("").expect("empty").kind, None);
        let err = parse_filter("state=running").unwrap_err();
        assert_eq!(err.code(), tonic::Code::InvalidArgument);
    }
}
