//! The one deliberate mapping of every subsystem's error to a gRPC status: one
//! `impl From<XError> for Status` per subsystem, built with `crate::status`, and the error a job
//! that did not succeed records (`impl From<JobFailure> for JobEndError`), which is its operation's
//! error when read back. Nothing else in the server chooses codes for subsystem errors; this module
//! must not hold any logic, and nothing in the crate imports it (the services reach it through `?`
//! and `From`), so it may depend on every subsystem.

use spoofwatch_core::fleet_fit::FleetFitError;
use spoofwatch_core::model::artifact::ArtifactError;
use spoofwatch_core::train::TrainError;
use spoofwatch_core::train::detector::TrainDetectorError;
use std::time::Duration;

use tonic::{Code, Status};

use crate::datasets::DatasetError;
use crate::detection::{SessionError, StoredReset};
use crate::fault::Fault;
use crate::jobs::{JobError, JobFailure};
use crate::models::RegistryError;
use crate::shadow::ShadowError;
use crate::status::{
    dependency_failed, failed_precondition, internal, invalid_argument, invalid_field, not_found,
    resource_exhausted, unavailable, with_code,
};
use crate::store::{FaultKind, JobEndError, StoreError, StoreFault};

impl From<StoreError> for Status {
    fn from(error: StoreError) -> Self {
        match &error {
            StoreError::NotFound { kind, id } => not_found(kind, id),
            StoreError::AlreadyExists { .. } => with_code(Code::AlreadyExists, error.to_string()),
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
            StoreError::Unavailable(fault) => store_fault(fault),
            StoreError::Database(_) | StoreError::Migration(_) => {
                internal("accessing the database", &error)
            }
        }
    }
}

/// A database fault: RESOURCE_EXHAUSTED when full, else UNAVAILABLE, each with a retry delay that
/// fits how soon the cause may clear.
fn store_fault(fault: &StoreFault) -> Status {
    let retry_after = match fault.kind {
        FaultKind::Busy | FaultKind::Closed => Duration::from_secs(1),
        FaultKind::Unreachable => Duration::from_secs(5),
        FaultKind::Full | FaultKind::ReadOnly | FaultKind::Io | FaultKind::CantOpen => {
            Duration::from_secs(30)
        }
        FaultKind::Corrupt | FaultKind::Lost => Duration::from_secs(300),
    };
    let exhausted = fault.kind == FaultKind::Full;
    dependency_failed(exhausted, fault.kind.describe(), &fault.cause, retry_after)
}

impl From<ShadowError> for Status {
    fn from(error: ShadowError) -> Self {
        match error {
            ShadowError::NotFound(ref name) => not_found("shadow", name),
            ShadowError::NoneStarted => not_found("shadow", "newest (none was started)"),
            ShadowError::AlreadyRunning(_) => {
                failed_precondition("SHADOW_RUNNING", error.to_string())
            }
            ShadowError::Scope(scope) => invalid_field(scope.field, scope.reason),
            ShadowError::Model(model) => model.into(),
            ShadowError::Store(store) => store.into(),
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
            // The field is the artifact's own JSON path under `artifact` (`artifact.evidence.mu_e`).
            RegistryError::InvalidArtifact(ref artifact) => {
                let field = match artifact.field() {
                    Some(path) => format!("artifact.{path}"),
                    None => "artifact".to_string(),
                };
                // A field's own reason, without repeating the field the violation names.
                let description = match artifact {
                    ArtifactError::Field { reason, .. } => reason.clone(),
                    other => other.to_string(),
                };
                invalid_field(field, description)
            }
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
            DatasetError::PathDenied { .. } => with_code(Code::PermissionDenied, error.to_string()),
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
            SessionError::Full(_) | SessionError::Quota { .. } => {
                resource_exhausted(error.to_string())
            }
            SessionError::Model(model) => model.into(),
            SessionError::ModelDeleted(_) => with_code(Code::Aborted, error.to_string()),
            // Retried soon: a burst of failovers or a short outage clears within seconds.
            SessionError::SnapshotUnreadable(_) => {
                unavailable(error.to_string(), Duration::from_secs(1))
            }
            SessionError::Stored(StoredReset::NotStoredYet) => {
                unavailable(error.to_string(), Duration::from_secs(1))
            }
            SessionError::Stored(StoredReset::Store(store)) => store.into(),
            SessionError::Stored(StoredReset::Unreadable(_) | StoredReset::Rewritten) => {
                with_code(Code::FailedPrecondition, error.to_string())
            }
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
            JobError::InputTooLarge { .. } => invalid_field("datasets", error.to_string()),
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
            JobFailure::Fit(FleetFitError::Data(error)) => {
                invalid_field(error.field(), error.to_string())
            }
            JobFailure::Fit(FleetFitError::Train(error)) => training_status(error),
            JobFailure::Fit(FleetFitError::StartingModel) => {
                invalid_field("fleet_fit.starting_model", failure.to_string())
            }
            JobFailure::Fit(FleetFitError::Scenario(_)) => {
                internal("injecting attacks into a fleet's drives", &failure)
            }
            JobFailure::FitRequest { field, reason } => invalid_field(field, reason),
            JobFailure::Worker(Fault { context, .. }) => internal(context, &failure),
            JobFailure::Abandoned => with_code(Code::Aborted, failure.to_string()),
        }
    }
}

/// The error a job that did not succeed records: the code and message of its operation's error.
impl From<JobFailure> for JobEndError {
    fn from(failure: JobFailure) -> Self {
        let status = Status::from(failure);
        JobEndError {
            code: status.code() as i32,
            message: status.message().to_string(),
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
        TrainDetectorError::StartingModel => {
            invalid_field("fleet_fit.starting_model", error.to_string())
        }
        TrainDetectorError::Data(_) | TrainDetectorError::Train(_) => {
            invalid_field("datasets", error.to_string())
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

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
        let closed = StoreError::from(sqlx::Error::PoolClosed);
        assert_eq!(code(JobFailure::Store(closed)), Code::Unavailable);
        let bug = StoreError::from(sqlx::Error::RowNotFound);
        assert_eq!(code(JobFailure::Store(bug)), Code::Internal);
    }

    #[test]
    fn jobs_that_end_without_a_result_record_fixed_codes() {
        assert_eq!(
            JobEndError::from(JobFailure::Cancelled),
            JobEndError {
                code: 1,
                message: "cancelled".into()
            }
        );
        assert_eq!(
            JobEndError::from(JobFailure::Abandoned),
            JobEndError {
                code: 10,
                message: "server restarted while the job was queued or running".into()
            }
        );
    }
}
