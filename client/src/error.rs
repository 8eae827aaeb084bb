//! Client-side errors, and readable renderings of gRPC statuses (code, message, BadRequest field
//! violations and the other google.rpc error details the server attaches).
//!
//! It must not decide what to do about an error (retry, exit codes): callers do.

use std::fmt;

use tonic::Code;
use tonic_types::{ErrorDetails, RpcStatusExt, StatusExt};

/// Everything the client library can fail with.
#[derive(Debug, thiserror::Error)]
pub enum ClientError {
    /// The server URL cannot be used.
    #[error("invalid server URL {url:?}: {reason}")]
    InvalidUrl { url: String, reason: String },
    /// The bearer token cannot be sent as an HTTP header value.
    #[error("invalid token: it must be printable ASCII without spaces or control characters")]
    InvalidToken,
    /// A TLS file cannot be read or holds no usable PEM item.
    #[error("{option} {}: {reason}", path.display())]
    TlsFile {
        option: &'static str,
        path: std::path::PathBuf,
        reason: String,
    },
    /// The TCP/HTTP2 connection could not be established.
    #[error("cannot connect to {url}: {reason}")]
    Connect { url: String, reason: String },
    /// A call failed with a gRPC status.
    #[error(transparent)]
    Rpc(#[from] RpcError),
    /// The server answered something the protocol does not allow (e.g. a detection count mismatch).
    #[error("protocol violation from the server: {0}")]
    Protocol(String),
    /// A stream ended before its protocol allows (its request side closed, or it ended with OK and
    /// batches unanswered) without a status saying why: the connection or a proxy dropped it.
    #[error("{0}")]
    StreamEnded(String),
    /// A stream kept failing over (reconnecting after its server went away) until the deadline.
    #[error("gave up failing over after {:.0} s and {attempts} attempts; last error: {last}", after.as_secs_f64())]
    FailoverExhausted {
        after: std::time::Duration,
        attempts: u32,
        last: Box<ClientError>,
    },
    /// No reply arrived in time.
    #[error("{context}: no reply within {after:?}")]
    Timeout {
        context: String,
        after: std::time::Duration,
    },
    /// Options given to a client helper are out of range.
    #[error("invalid option {option}: {reason}")]
    InvalidOption {
        option: &'static str,
        reason: String,
    },
    /// Local I/O (temporary directories, sockets of an in-process server).
    #[error("{context}: {source}")]
    Io {
        context: String,
        source: std::io::Error,
    },
    /// The in-process server failed.
    #[error("in-process server: {0}")]
    Server(String),
}

impl ClientError {
    /// The gRPC status a failed call returned, if this is one.
    pub fn status(&self) -> Option<&tonic::Status> {
        match self {
            ClientError::Rpc(error) => Some(&error.status),
            _ => None,
        }
    }
}

/// A failed call: what the client was doing and the status the server returned.
#[derive(Debug)]
pub struct RpcError {
    /// What was being attempted, e.g. `listing models`.
    pub context: String,
    /// The status returned.
    pub status: tonic::Status,
}

impl RpcError {
    /// Wraps a status with what the client was doing.
    pub fn new(context: impl Into<String>, status: tonic::Status) -> Self {
        Self {
            context: context.into(),
            status,
        }
    }

    /// The status code.
    pub fn code(&self) -> Code {
        self.status.code()
    }
}

impl fmt::Display for RpcError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}: {}", self.context, describe_status(&self.status))
    }
}

impl std::error::Error for RpcError {}

/// A closure for `map_err` that wraps a status with `context`.
pub fn rpc(context: impl Into<String>) -> impl FnOnce(tonic::Status) -> ClientError {
    let context = context.into();
    move |status| ClientError::Rpc(RpcError::new(context, status))
}

/// Awaits one gRPC call (a unary call or the opening of a stream) and unwraps its message; a
/// failure becomes an [`RpcError`] naming `context`. Every call goes through here, so none
/// repeats the unwrapping.
pub async fn reply<T>(
    context: impl Into<String>,
    call: impl Future<Output = Result<tonic::Response<T>, tonic::Status>>,
) -> Result<T, ClientError> {
    call.await
        .map(tonic::Response::into_inner)
        .map_err(rpc(context))
}

/// The canonical name of a gRPC code (`INVALID_ARGUMENT`), as grpcurl and the docs spell it.
pub fn code_name(code: Code) -> &'static str {
    match code {
        Code::Ok => "OK",
        Code::Cancelled => "CANCELLED",
        Code::Unknown => "UNKNOWN",
        Code::InvalidArgument => "INVALID_ARGUMENT",
        Code::DeadlineExceeded => "DEADLINE_EXCEEDED",
        Code::NotFound => "NOT_FOUND",
        Code::AlreadyExists => "ALREADY_EXISTS",
        Code::PermissionDenied => "PERMISSION_DENIED",
        Code::ResourceExhausted => "RESOURCE_EXHAUSTED",
        Code::FailedPrecondition => "FAILED_PRECONDITION",
        Code::Aborted => "ABORTED",
        Code::OutOfRange => "OUT_OF_RANGE",
        Code::Unimplemented => "UNIMPLEMENTED",
        Code::Internal => "INTERNAL",
        Code::Unavailable => "UNAVAILABLE",
        Code::DataLoss => "DATA_LOSS",
        Code::Unauthenticated => "UNAUTHENTICATED",
    }
}

/// `CODE: message` followed by one indented line per error detail (field violations first).
pub fn describe_status(status: &tonic::Status) -> String {
    let mut out = describe(status.code(), status.message(), &status.get_error_details());
    // A status made on this side from a transport failure (e.g. a TLS alert) keeps its cause.
    if let Some(source) = std::error::Error::source(status) {
        let cause = error_chain(source);
        if !out.contains(&cause) {
            out.push_str(&format!(" ({cause})"));
        }
    }
    out
}

/// Like [`describe_status`], for a `google.rpc.Status` message (e.g. from an `ItemError` or a failed
/// operation).
pub fn describe_rpc_status(status: &tonic_types::Status) -> String {
    describe(
        Code::from(status.code),
        &status.message,
        &status.get_error_details(),
    )
}

fn describe(code: Code, message: &str, details: &ErrorDetails) -> String {
    let mut out = format!("{}: {message}", code_name(code));
    if let Some(bad_request) = details.bad_request() {
        // The Spoofwatch server's message is already `field: problem; …`: list each once.
        let summary = bad_request
            .field_violations
            .iter()
            .map(|v| format!("{}: {}", v.field, v.description))
            .collect::<Vec<_>>()
            .join("; ");
        if summary == message {
            out = format!("{}: invalid request", code_name(code));
        }
        for violation in &bad_request.field_violations {
            out.push_str(&format!(
                "\n    - {}: {}",
                violation.field, violation.description
            ));
        }
    }
    if let Some(info) = details.resource_info() {
        out.push_str(&format!(
            "\n    resource: {} {}",
            info.resource_type, info.resource_name
        ));
    }
    if let Some(info) = details.error_info() {
        out.push_str(&format!("\n    reason: {}", info.reason));
    }
    if let Some(failure) = details.precondition_failure() {
        for violation in &failure.violations {
            out.push_str(&format!(
                "\n    - precondition {} {}: {}",
                violation.r#type, violation.subject, violation.description
            ));
        }
    }
    if let Some(retry) = details.retry_info()
        && let Some(delay) = retry.retry_delay
    {
        out.push_str(&format!("\n    retry after {:.1} s", delay.as_secs_f64()));
    }
    out
}

/// An error and its chain of causes on one line (`a: b: c`), for transport errors whose own
/// message is terse.
pub fn error_chain(error: &dyn std::error::Error) -> String {
    let mut out = error.to_string();
    let mut source = error.source();
    while let Some(cause) = source {
        let text = cause.to_string();
        if !out.contains(&text) {
            out.push_str(": ");
            out.push_str(&text);
        }
        source = cause.source();
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use tonic_types::FieldViolation;

    #[test]
    fn bad_request_violations_are_listed_under_the_code_and_message() {
        let details = ErrorDetails::with_bad_request(vec![
            FieldViolation::new(
                "batch.samples[3].latitude_deg",
                "must be in [-90, 90], got 91",
            ),
            FieldViolation::new(
                "batch.samples[4].speed_mps",
                "must be a finite number, got NaN",
            ),
        ]);
        let status =
            tonic::Status::with_error_details(Code::InvalidArgument, "2 problems", details);
        assert_eq!(
            describe_status(&status),
            "INVALID_ARGUMENT: 2 problems\n    \
             - batch.samples[3].latitude_deg: must be in [-90, 90], got 91\n    \
             - batch.samples[4].speed_mps: must be a finite number, got NaN"
        );
        let error = RpcError::new("streaming detections", status);
        assert!(
            error
                .to_string()
                .starts_with("streaming detections: INVALID_ARGUMENT: 2 problems\n")
        );
    }

    #[test]
    fn a_message_that_only_repeats_the_violations_is_not_printed_twice() {
        let details = ErrorDetails::with_bad_request(vec![FieldViolation::new(
            "spec.max_epochs",
            "must be 1 to 200",
        )]);
        let status = tonic::Status::with_error_details(
            Code::InvalidArgument,
            "spec.max_epochs: must be 1 to 200",
            details,
        );
        assert_eq!(
            describe_status(&status),
            "INVALID_ARGUMENT: invalid request\n    - spec.max_epochs: must be 1 to 200"
        );
    }

    #[test]
    fn a_plain_status_is_code_and_message() {
        let status = tonic::Status::not_found("model \"models/x\" not found");
        assert_eq!(
            describe_status(&status),
            "NOT_FOUND: model \"models/x\" not found"
        );
    }

    #[test]
    fn an_item_error_status_message_is_described_like_a_call_status() {
        let status = tonic_types::Status {
            code: Code::InvalidArgument as i32,
            message: "bad".into(),
            details: Vec::new(),
        };
        assert_eq!(describe_rpc_status(&status), "INVALID_ARGUMENT: bad");
    }
}
