//! TrainingService and google.longrunning.Operations over the job manager.

use std::pin::Pin;
use std::sync::Arc;
use std::time::Duration;

use prost::Message;
use prost_types::Any;
use spoofwatch_proto::longrunning;
use spoofwatch_proto::longrunning::operations_server::Operations;
use spoofwatch_proto::v1;
use spoofwatch_proto::v1::training_service_server::TrainingService;
use tokio::sync::mpsc;
use tokio_stream::Stream;
use tokio_stream::wrappers::ReceiverStream;
use tonic::{Request, Response, Status};

use super::runner::{JobManager, JobResult, job_metadata};
use crate::convert::{metrics_to_proto, strip_collection};
use crate::error::invalid_field;
use crate::registry::Registry;
use crate::store::{JobFilter, JobKind, JobRow, JobState, PageRequest, Store};

/// Longest WaitOperation wait.
const MAX_WAIT: Duration = Duration::from_secs(60);

fn pack<M: Message>(type_name: &str, message: &M) -> Any {
    Any {
        type_url: format!("type.googleapis.com/{type_name}"),
        value: message.encode_to_vec(),
    }
}

/// Shared by both services: turning job rows into operations.
#[derive(Debug, Clone)]
pub struct Jobs {
    pub manager: Arc<JobManager>,
    pub store: Store,
    pub registry: Arc<Registry>,
}

impl Jobs {
    async fn row(&self, name: &str) -> Result<JobRow, Status> {
        let id = strip_collection("operations", name);
        self.store
            .get_job(id)
            .await?
            .ok_or_else(|| crate::error::not_found("operation", &format!("operations/{id}")))
    }

    async fn metadata(&self, row: &JobRow) -> Result<v1::JobMetadata, Status> {
        let epochs = self.store.job_epochs(&row.id).await?;
        Ok(job_metadata(row, &epochs))
    }

    async fn operation(&self, row: &JobRow) -> Result<longrunning::Operation, Status> {
        use longrunning::operation::Result as OpResult;
        let metadata = self.metadata(row).await?;
        let result = match row.state {
            JobState::Succeeded => {
                let result: Option<JobResult> = row
                    .result
                    .clone()
                    .and_then(|v| serde_json::from_value(v).ok());
                match result {
                    Some(JobResult::Training {
                        model_id,
                        validation,
                        test,
                    }) => {
                        let model = self.registry.get_proto(&model_id).await.ok();
                        Some(OpResult::Response(pack(
                            "spoofwatch.v1.TrainingJobResult",
                            &v1::TrainingJobResult {
                                model,
                                validation: Some(metrics_to_proto(&validation)),
                                test: test.as_ref().map(metrics_to_proto),
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
            name: format!("operations/{}", row.id),
            metadata: Some(pack("spoofwatch.v1.JobMetadata", &metadata)),
            done: row.state.is_finished(),
            result,
        })
    }

    /// Waits until the job finishes or `timeout` passes; returns its latest row.
    async fn wait(&self, name: &str, timeout: Duration) -> Result<JobRow, Status> {
        let deadline = tokio::time::Instant::now() + timeout;
        let id = strip_collection("operations", name).to_string();
        let mut changes = self.manager.subscribe(&id);
        loop {
            let row = self.row(&id).await?;
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

impl TrainingApi {
    pub fn new(jobs: Jobs) -> Self {
        Self { jobs }
    }
}

type WatchStream = Pin<Box<dyn Stream<Item = Result<v1::JobMetadata, Status>> + Send>>;

#[tonic::async_trait]
impl TrainingService for TrainingApi {
    async fn create_training_job(
        &self,
        request: Request<v1::CreateTrainingJobRequest>,
    ) -> Result<Response<longrunning::Operation>, Status> {
        let row = self
            .jobs
            .manager
            .create_training(request.into_inner())
            .await?;
        tracing::info!(job = %row.id, "training job queued");
        Ok(Response::new(self.jobs.operation(&row).await?))
    }

    async fn create_evaluation_job(
        &self,
        request: Request<v1::CreateEvaluationJobRequest>,
    ) -> Result<Response<longrunning::Operation>, Status> {
        let row = self
            .jobs
            .manager
            .create_evaluation(request.into_inner())
            .await?;
        Ok(Response::new(self.jobs.operation(&row).await?))
    }

    type WatchJobStream = WatchStream;

    async fn watch_job(
        &self,
        request: Request<v1::WatchJobRequest>,
    ) -> Result<Response<Self::WatchJobStream>, Status> {
        let name = request.into_inner().name;
        let first = self.jobs.row(&name).await?;
        let jobs = self.jobs.clone();
        let (tx, rx) = mpsc::channel(8);
        tokio::spawn(async move {
            let mut changes = jobs.manager.subscribe(&first.id);
            let mut row = first;
            loop {
                let metadata = jobs.metadata(&row).await;
                let done = row.state.is_finished();
                if tx.send(metadata).await.is_err() || done {
                    break;
                }
                match changes.as_mut() {
                    Some(rx) => {
                        if rx.changed().await.is_err() {
                            changes = None;
                        }
                    }
                    None => tokio::time::sleep(Duration::from_millis(200)).await,
                }
                match jobs.row(&row.id).await {
                    Ok(r) => row = r,
                    Err(status) => {
                        let _ = tx.send(Err(status)).await;
                        break;
                    }
                }
            }
        });
        Ok(Response::new(Box::pin(ReceiverStream::new(rx))))
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
        if r.page_size < 0 {
            return Err(invalid_field("page_size", "must not be negative"));
        }
        let page = self
            .jobs
            .store
            .list_jobs(
                &parse_filter(&r.filter)?,
                &PageRequest {
                    page_size: r.page_size as u32,
                    page_token: (!r.page_token.is_empty()).then_some(r.page_token),
                },
            )
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
        let row = self.jobs.row(&request.into_inner().name).await?;
        Ok(Response::new(self.jobs.operation(&row).await?))
    }

    async fn delete_operation(
        &self,
        request: Request<longrunning::DeleteOperationRequest>,
    ) -> Result<Response<()>, Status> {
        let name = request.into_inner().name;
        self.jobs
            .store
            .delete_job(strip_collection("operations", &name))
            .await?;
        Ok(Response::new(()))
    }

    async fn cancel_operation(
        &self,
        request: Request<longrunning::CancelOperationRequest>,
    ) -> Result<Response<()>, Status> {
        let name = request.into_inner().name;
        self.jobs
            .manager
            .cancel(strip_collection("operations", &name))
            .await?;
        Ok(Response::new(()))
    }

    async fn wait_operation(
        &self,
        request: Request<longrunning::WaitOperationRequest>,
    ) -> Result<Response<longrunning::Operation>, Status> {
        let r = request.into_inner();
        let timeout = match r.timeout {
            Some(d) if d.seconds < 0 || d.nanos < 0 => {
                return Err(invalid_field("timeout", "must not be negative"));
            }
            Some(d) => Duration::new(d.seconds as u64, d.nanos as u32).min(MAX_WAIT),
            None => MAX_WAIT,
        };
        let row = self.jobs.wait(&r.name, timeout).await?;
        Ok(Response::new(self.jobs.operation(&row).await?))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn filters_parse_and_bad_terms_are_named() {
        let f = parse_filter("kind=training AND done=false").expect("valid");
        assert_eq!((f.kind, f.done), (Some(JobKind::Training), Some(false)));
        assert_eq!(parse_filter("").expect("empty").kind, None);
        let err = parse_filter("state=running").unwrap_err();
        assert_eq!(err.code(), tonic::Code::InvalidArgument);
    }
}
