//! Builders of gRPC statuses with google.rpc error details (BadRequest field violations,
//! ResourceInfo, ErrorInfo, RetryInfo), used by every service at the edge and by the one error
//! mapping in `crate::error`. Internal errors are logged and answered with a generic INTERNAL
//! message (no leaked internals). It must not know any subsystem: it imports nothing of the crate.
//!
//! Every status it builds fits in a trailer clients accept (grpcio's limit is 16 KiB; these stay
//! under 8 KiB): messages, field names and descriptions are cut to a bound (saying how long they
//! were), and at most [`MAX_VIOLATIONS`] field violations are listed, the last one counting those
//! left out. Whatever a client sent and a status echoes is therefore bounded here.

use std::borrow::Cow;

use prost::Message;
use tonic::{Code, Status};
use tonic_types::{ErrorDetails, FieldViolation, StatusExt};

/// Most field violations one status lists; one more then says how many were left out.
pub const MAX_VIOLATIONS: usize = 10;
/// Longest status message, in bytes (percent-encoded in the trailer: up to three times longer).
const MAX_MESSAGE_BYTES: usize = 512;
/// Longest field name of a violation, in bytes.
const MAX_FIELD_BYTES: usize = 100;
/// Longest description of a violation, in bytes.
const MAX_DESCRIPTION_BYTES: usize = 200;

/// `text` cut to at most `max_bytes` bytes on a character boundary; a cut text ends with
/// "… (N chars)", N its full length.
pub fn bounded(text: &str, max_bytes: usize) -> Cow<'_, str> {
    if text.len() <= max_bytes {
        return Cow::Borrowed(text);
    }
    let suffix = format!("… ({} chars)", text.chars().count());
    let mut end = max_bytes.saturating_sub(suffix.len());
    while !text.is_char_boundary(end) {
        end -= 1;
    }
    Cow::Owned(format!("{}{suffix}", &text[..end]))
}

/// A status message within the bound.
fn bounded_message(text: impl Into<String>) -> String {
    let text = text.into();
    match bounded(&text, MAX_MESSAGE_BYTES) {
        Cow::Borrowed(_) => text,
        Cow::Owned(cut) => cut,
    }
}

/// A status of `code` with `text` as its message, bounded (for codes without details).
pub fn with_code(code: Code, text: impl Into<String>) -> Status {
    Status::new(code, bounded_message(text))
}

/// INVALID_ARGUMENT with one BadRequest field violation per problem: the first
/// [`MAX_VIOLATIONS`], then one at the first field left out counting the rest.
pub fn invalid_argument(violations: Vec<(String, String)>) -> Status {
    let total = violations.len();
    let mut listed: Vec<FieldViolation> = violations
        .iter()
        .take(MAX_VIOLATIONS)
        .map(|(field, description)| {
            FieldViolation::new(
                bounded(field, MAX_FIELD_BYTES),
                bounded(description, MAX_DESCRIPTION_BYTES),
            )
        })
        .collect();
    let mut summary = listed
        .iter()
        .map(|v| format!("{}: {}", v.field, v.description))
        .collect::<Vec<_>>()
        .join("; ");
    if let Some((first_left_out, _)) = violations.get(MAX_VIOLATIONS) {
        let left_out = total - MAX_VIOLATIONS;
        let more = format!(
            "{left_out} more violation{} not shown (from this field on); only the first \
             {MAX_VIOLATIONS} are listed",
            if left_out == 1 { "" } else { "s" }
        );
        summary = format!("{}; and {more}", bounded(&summary, MAX_MESSAGE_BYTES - 100));
        listed.push(FieldViolation::new(
            bounded(first_left_out, MAX_FIELD_BYTES),
            more,
        ));
    }
    let details = ErrorDetails::with_bad_request(listed);
    Status::with_error_details(Code::InvalidArgument, bounded_message(summary), details)
}

/// INVALID_ARGUMENT for a single field.
pub fn invalid_field(field: impl Into<String>, description: impl Into<String>) -> Status {
    invalid_argument(vec![(field.into(), description.into())])
}

/// NOT_FOUND with ResourceInfo naming the resource.
pub fn not_found(kind: &str, name: &str) -> Status {
    let name = bounded(name, MAX_FIELD_BYTES);
    let details =
        ErrorDetails::with_resource_info(kind, name.as_ref(), "", format!("no such {kind}"));
    Status::with_error_details(
        Code::NotFound,
        bounded_message(format!("{kind} {name:?} not found")),
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
    Status::with_error_details(Code::FailedPrecondition, bounded_message(message), details)
}

/// RESOURCE_EXHAUSTED with a retry hint.
pub fn resource_exhausted(message: impl Into<String>) -> Status {
    retry_later(
        Code::ResourceExhausted,
        message,
        std::time::Duration::from_secs(5),
    )
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
    retry_later(code, message, retry_after)
}

/// UNAVAILABLE for a call that may succeed when retried after `retry_after`.
pub fn unavailable(message: impl Into<String>, retry_after: std::time::Duration) -> Status {
    retry_later(Code::Unavailable, message, retry_after)
}

/// UNAVAILABLE while the server drains.
pub fn shutting_down() -> Status {
    unavailable(
        "server is shutting down; reconnect to another replica or retry",
        std::time::Duration::from_secs(1),
    )
}

/// `code` with a RetryInfo detail: a retry after `retry_after` may succeed.
fn retry_later(code: Code, message: impl Into<String>, retry_after: std::time::Duration) -> Status {
    let details = ErrorDetails::with_retry_info(Some(retry_after));
    Status::with_error_details(code, bounded_message(message), details)
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

    /// Bytes of the trailer fields a status travels in (grpc-status, grpc-message
    /// percent-encoded, grpc-status-details-bin in base64), names included.
    fn trailer_bytes(status: &Status) -> usize {
        let mut headers = tonic::codegen::http::HeaderMap::new();
        status.add_header(&mut headers).expect("a valid status");
        headers
            .iter()
            .map(|(name, value)| name.as_str().len() + value.len())
            .sum()
    }

    #[test]
    fn ten_thousand_long_violations_fit_in_an_eight_kib_trailer() {
        // Non-ASCII text is the worst case: three bytes per character percent-encoded.
        let field = "é".repeat(5_000);
        let description = "ü".repeat(5_000);
        let violations = (0..10_000)
            .map(|i| (format!("{field}[{i}]"), description.clone()))
            .collect();
        let status = invalid_argument(violations);
        assert!(
            trailer_bytes(&status) <= 8 * 1024,
            "{}",
            trailer_bytes(&status)
        );
        let bad = status
            .get_details_bad_request()
            .expect("BadRequest details");
        assert_eq!(bad.field_violations.len(), MAX_VIOLATIONS + 1);
        let last = &bad.field_violations[MAX_VIOLATIONS].description;
        assert!(last.starts_with("9990 more violations not shown"), "{last}");
        assert!(status.message().ends_with("only the first 10 are listed"));
        assert!(
            bad.field_violations[0]
                .description
                .ends_with("… (5000 chars)")
        );

        let long = "x".repeat(100_000);
        for status in [
            not_found("model", &long),
            failed_precondition("REASON", long.clone()),
            resource_exhausted(long.clone()),
            with_code(Code::AlreadyExists, long.clone()),
            invalid_field(long.clone(), long.clone()),
        ] {
            assert!(trailer_bytes(&status) <= 8 * 1024, "{status:?}");
        }
    }

    #[test]
    fn a_short_list_is_kept_whole_and_a_cut_text_says_how_long_it_was() {
        let violations: Vec<(String, String)> = (0..MAX_VIOLATIONS)
            .map(|i| (format!("samples[{i}]"), "must be finite".to_string()))
            .collect();
        let bad = invalid_argument(violations)
            .get_details_bad_request()
            .expect("BadRequest details");
        assert_eq!(bad.field_violations.len(), MAX_VIOLATIONS);
        assert_eq!(bounded("short", 10), "short");
        let long = "a".repeat(500);
        let cut = bounded(&long, 100);
        assert!(cut.len() <= 100 && cut.ends_with("… (500 chars)"), "{cut}");
    }
}
