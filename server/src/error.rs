//! The one deliberate mapping of every subsystem's error to a gRPC status, with google.rpc error
//! details: status builders, then one `impl From<XError> for Status` per subsystem. Internal errors
//! are logged and answered with a generic INTERNAL message (no leaked internals). Nothing else in
//! the server chooses codes for subsystem errors; this module must not hold any logic.

use prost::Message;
use spoofwatch_core::train::TrainError;
use spoofwatch_core::train::detector::TrainDetectorError;
use tonic::{Code, Status};
use tonic_types::{ErrorDetails, FieldViolation, StatusExt};

use crate::datasets::DatasetError;
use crate::detection::SessionError;
use crate::fault::Fault;
use crate::jobs::{JobError, JobFailure};
use crate::models::RegistryError;
use crate::store::StoreError;

/// INVALID_ARGUMENT with one BadRequest field violation per problem.
pub fn invalid_argument(violations: Vec<(String, String)>) -> Status {
    let summary = violations
        .iter()
        .map(|(field, description)| format!("{field}: {description}"))
        .collect::<Vec<_>>()
        .join("; ");
    let details = ErrorDetails::with_bad_request(
        violations
            .into_iter()
            .map(|(field, description)| FieldViolation::new(field, description))
            .collect::<Vec<_>>(),
    );
    Status::with_error_details(Code::InvalidArgument, summary, details)
}

/// INVALID_ARGUMENT for a single field.
pub fn invalid_field(field: impl Into<String>, description: impl Into<String>) -> Status {
    invalid_argument(vec![(field.into(), description.into())])
}

/// NOT_FOUND with ResourceInfo naming the resource.
pub fn not_found(kind: &str, name: &str) -> Status {
    let details = ErrorDetails::with_resource_info(kind, name, "", format!("no such {kind}"));
    Status::with_error_details(
        Code::NotFound,
        format!("{kind} {name:?} not found"),
        details,
    )
}

/// FAILED_PRECONDITION with an ErrorInfo reason (machine-readable, UPPER_SNAKE_CASE).
pub fn failed_precondition(reason: &str, message: impl Into<String>) -> Status {
    let details = ErrorDetails::with_error_info(
        reason,
        "spoofwatch",
        std::collections::HashMap::<String, String>::new(),
    );
    Status::with_error_details(Code::FailedPrecondition, message, details)
}

/// RESOURCE_EXHAUSTED with a retry hint.
pub fn resource_exhausted(message: impl Into<String>) -> Status {
    let details = ErrorDetails::with_retry_info(Some(std::time::Duration::from_secs(5)));
    Status::with_error_details(Code::ResourceExhausted, message, details)
}

/// UNAVAILABLE while the server drains.
pub fn shutting_down() -> Status {
    let details = ErrorDetails::with_retry_info(Some(std::time::Duration::from_secs(1)));
    Status::with_error_details(
        Code::Unavailable,
        "server is shutting down; reconnect to another replica or retry",
        details,
    )
}

/// INTERNAL for an unexpected failure, logged with its cause.
pub fn internal(context: &str, error: &dyn std::fmt::Display) -> Status {
    tracing::error!(%error, "{context}");
    Status::internal(format!("internal error while {context}"))
}

/// INVALID_ARGUMENT for a streamed upload whose first message is not its header.
pub fn header_first() -> Status {
    invalid_field("header", "the first message must be a header")
}

/// INVALID_ARGUMENT for a streamed upload with a second header.
pub fn header_not_first() -> Status {
    invalid_field("header", "only the first message may be a header")
}

/// A tonic status as the google.rpc.Status message (for ItemError).
pub fn to_rpc_status(status: &Status) -> tonic_types::Status {
    tonic_types::Status::decode(status.details()).unwrap_or_else(|_| tonic_types::Status {
        code: status.code() as i32,
        message: status.message().to_string(),
        details: Vec::new(),
    })
}

impl From<StoreError> for Status {
    fn from(error: StoreError) -> Self {
        match &error {
            StoreError::NotFound { kind, id } => not_found(kind, id),
            StoreError::AlreadyExists { .. } => Status::already_exists(error.to_string()),
            StoreError::ModelActive { .. } => {
                failed_precondition("MODEL_ACTIVE", error.to_string())
            }
            StoreError::JobNotFinished { .. } => {
                failed_precondition("JOB_NOT_FINISHED", error.to_string())
            }
            StoreError::InvalidState { .. } => {
                failed_precondition("INVALID_STATE", error.to_string())
            }
            StoreError::InvalidPageToken => invalid_field("page_token", "invalid page token"),
            StoreError::InvalidValue { field, reason } => invalid_field(field.to_string(), reason),
            StoreError::Database(_) | StoreError::Migration(_) => {
                internal("accessing the database", &error)
            }
        }
    }
}

impl From<RegistryError> for Status {
    fn from(error: RegistryError) -> Self {
        match error {
            RegistryError::NotFound(name) => not_found("model", &name.to_string()),
            RegistryError::NoActiveModel => {
                failed_precondition("NO_ACTIVE_MODEL", error.to_string())
            }
            RegistryError::InvalidArtifact(_) => invalid_field("chunk", error.to_string()),
            RegistryError::Internal(Fault { context, .. }) => internal(context, &error),
            RegistryError::Store(store) => store.into(),
        }
    }
}

impl From<DatasetError> for Status {
    fn from(error: DatasetError) -> Self {
        match error {
            DatasetError::NotFound(name) => not_found("dataset", &name.to_string()),
            DatasetError::Invalid { field, reason } => invalid_field(field, reason),
            DatasetError::NoDataDir => failed_precondition("NO_DATA_DIR", error.to_string()),
            DatasetError::PathDenied { .. } => Status::permission_denied(error.to_string()),
            DatasetError::FileNotFound(path) => not_found("file", &path),
            DatasetError::Internal(Fault { context, .. }) => internal(context, &error),
            DatasetError::Store(store) => store.into(),
        }
    }
}

impl From<SessionError> for Status {
    fn from(error: SessionError) -> Self {
        match error {
            SessionError::InvalidBatch(violations) => invalid_argument(violations),
            SessionError::NotFound(vehicle) => not_found("session", &vehicle),
            SessionError::Full(_) => resource_exhausted(error.to_string()),
            SessionError::Model(model) => model.into(),
        }
    }
}

impl From<JobError> for Status {
    fn from(error: JobError) -> Self {
        match error {
            JobError::DatasetNotFound {
                ref field,
                ref name,
            } => {
                let status = not_found("dataset", &name.to_string());
                Status::with_details(
                    status.code(),
                    format!("{field}: {}", status.message()),
                    status.details().to_vec().into(),
                )
            }
            JobError::QueueFull(_) => resource_exhausted(error.to_string()),
            JobError::NotFound(name) => not_found("operation", &name.to_string()),
            JobError::Model(model) => model.into(),
            JobError::Dataset(dataset) => dataset.into(),
            JobError::Store(store) => store.into(),
        }
    }
}

/// A failed job's operation error: the code of its real cause (missing data NOT_FOUND, bad data
/// INVALID_ARGUMENT, no operating point FAILED_PRECONDITION, store faults INTERNAL...).
impl From<JobFailure> for Status {
    fn from(failure: JobFailure) -> Self {
        match failure {
            JobFailure::Cancelled => Status::cancelled("cancelled"),
            JobFailure::Dataset(error) => error.into(),
            JobFailure::Model(error) => error.into(),
            JobFailure::Store(error) => error.into(),
            JobFailure::Training(error) => training_status(error),
            JobFailure::Worker(Fault { context, .. }) => internal(context, &failure),
        }
    }
}

/// Training's own failures: the data's fault, a missing precondition, or ours.
fn training_status(error: TrainDetectorError) -> Status {
    match &error {
        TrainDetectorError::NoOperatingPoint | TrainDetectorError::OverBudget(_) => {
            failed_precondition("NO_OPERATING_POINT", error.to_string())
        }
        TrainDetectorError::Train(TrainError::Diverged { .. }) => {
            failed_precondition("TRAINING_DIVERGED", error.to_string())
        }
        TrainDetectorError::Train(TrainError::Model(_)) => internal("training a model", &error),
        TrainDetectorError::Data(_) | TrainDetectorError::Train(_) => {
            invalid_field("datasets", error.to_string())
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn field_violations_travel_in_the_status_details() {
        let status = invalid_argument(vec![
            (
                "batch.samples[2].latitude_deg".into(),
                "must be finite".into(),
            ),
            ("batch.samples[3].speed_mps".into(), "too fast".into()),
        ]);
        assert_eq!(status.code(), Code::InvalidArgument);
        let bad = status
            .get_details_bad_request()
            .expect("BadRequest details");
        assert_eq!(bad.field_violations.len(), 2);
        assert_eq!(
            bad.field_violations[0].field,
            "batch.samples[2].latitude_deg"
        );
        let rpc = to_rpc_status(&status);
        assert_eq!(rpc.code, Code::InvalidArgument as i32);
        assert_eq!(rpc.details.len(), 1);
    }

    #[test]
    fn store_errors_map_to_deliberate_codes() {
        let active: Status = StoreError::ModelActive { id: "m".into() }.into();
        assert_eq!(active.code(), Code::FailedPrecondition);
        let missing: Status = StoreError::NotFound {
            kind: "model",
            id: "x".into(),
        }
        .into();
        assert_eq!(missing.code(), Code::NotFound);
        assert_eq!(
            Status::from(StoreError::InvalidPageToken).code(),
            Code::InvalidArgument
        );
    }

    #[test]
    fn job_failures_keep_the_code_of_their_cause() {
        use spoofwatch_proto::wire::DatasetName;
        let code = |failure: JobFailure| Status::from(failure).code();
        let missing = DatasetError::NotFound(DatasetName::from_id("d"));
        assert_eq!(code(JobFailure::Dataset(missing)), Code::NotFound);
        let no_op = JobFailure::Training(TrainDetectorError::NoOperatingPoint);
        assert_eq!(code(no_op), Code::FailedPrecondition);
        let empty = TrainDetectorError::Train(TrainError::EmptySplit { split: "training" });
        assert_eq!(code(JobFailure::Training(empty)), Code::InvalidArgument);
        let store = StoreError::InvalidState {
            kind: "job",
            id: "j".into(),
            action: "finish",
            state: "succeeded",
        };
        assert_eq!(code(JobFailure::Store(store)), Code::FailedPrecondition);
        let database = StoreError::Database(sqlx::Error::PoolClosed);
        assert_eq!(code(JobFailure::Store(database)), Code::Internal);
    }
}
