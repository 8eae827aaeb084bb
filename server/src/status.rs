//! Builders of gRPC statuses with google.rpc error details (BadRequest field violations,
//! ResourceInfo, ErrorInfo, RetryInfo), used by every service at the edge and by the one error
//! mapping in `crate::error`. Internal errors are logged and answered with a generic INTERNAL
//! message (no leaked internals). It must not know any subsystem: it imports nothing of the crate.

use prost::Message;
use tonic::{Code, Status};
use tonic_types::{ErrorDetails, FieldViolation, StatusExt};

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

/// RESOURCE_EXHAUSTED (`exhausted`) or UNAVAILABLE for a resource the server depends on, with the
/// delay after which a retry may succeed; logged as an error naming the cause.
pub fn dependency_failed(
    exhausted: bool,
    message: &str,
    cause: &str,
    retry_after: std::time::Duration,
) -> Status {
    tracing::error!(cause, "{message}");
    let code = if exhausted {
        Code::ResourceExhausted
    } else {
        Code::Unavailable
    };
    let details = ErrorDetails::with_retry_info(Some(retry_after));
    Status::with_error_details(code, message, details)
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
    match tonic_types::Status::decode(status.details()) {
        // Statuses built without details carry none: empty bytes decode to an OK status.
        Ok(decoded) if decoded.code == status.code() as i32 => decoded,
        _ => tonic_types::Status {
            code: status.code() as i32,
            message: status.message().to_string(),
            details: Vec::new(),
        },
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_status_without_details_keeps_its_code_and_message() {
        let status = to_rpc_status(&Status::permission_denied("not yours"));
        assert_eq!(status.code, Code::PermissionDenied as i32);
        assert_eq!(status.message, "not yours");
    }

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
}
