//! One line of an error and its causes, for logs and operator-facing messages: the top-level text
//! of many errors (tonic's transport errors, the store's database errors) hides the cause. It
//! owns only that formatting and must not decide what is shown to clients.

/// `error` and its causes, joined by ": ".
pub(crate) fn error_chain(error: &dyn std::error::Error) -> String {
    let mut out = error.to_string();
    let mut source = error.source();
    while let Some(cause) = source {
        out.push_str(": ");
        out.push_str(&cause.to_string());
        source = cause.source();
    }
    out
}
