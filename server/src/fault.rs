//! A server-side fault carried inside a subsystem's error: what the server was doing and the text of
//! what went wrong (a crashed worker thread, data-directory I/O, an artifact that will not
//! serialise). It only carries them; `crate::error` answers every fault with INTERNAL. It must not
//! depend on any other module of the crate.

use std::fmt::Display;

/// An unexpected server-side failure, safe to log but not to show to clients.
#[derive(Debug, thiserror::Error)]
#[error("{context}: {reason}")]
pub struct Fault {
    /// What the server was doing, e.g. "parsing a dataset".
    pub context: &'static str,
    /// The underlying error's text.
    pub reason: String,
}

impl Fault {
    /// The fault `cause` raised while the server was doing `context`.
    pub fn new(context: &'static str, cause: impl Display) -> Self {
        Fault {
            context,
            reason: cause.to_string(),
        }
    }
}
