//! The detection subsystem's one error: everything a session operation can fail with.
//!
//! Owns [`SessionError`] and its messages. Must not map it to a gRPC status (that is
//! `crate::error`) or decide when it happens.

use spoofwatch_proto::wire::ModelName;

use super::persistence::StoredReset;
use super::snapshot_reads::UNREAD_GRACE;
use crate::models::RegistryError;

/// Everything a session operation can fail with.
#[derive(Debug, thiserror::Error)]
pub enum SessionError {
    /// The batch is invalid; one `(field, problem)` per violation. Nothing was applied.
    #[error("invalid batch")]
    InvalidBatch(Vec<(String, String)>),
    /// No session for this vehicle.
    #[error("session {0:?} not found")]
    NotFound(String),
    /// The session table is full, and every session in it has a stream.
    #[error("the server holds its maximum of {0} vehicle sessions, each with a live stream")]
    Full(usize),
    /// The caller created its quota of sessions.
    #[error("{identity} holds its quota of {limit} vehicle sessions (--max-sessions-per-identity)")]
    Quota { identity: String, limit: usize },
    /// The requested model cannot be served.
    #[error(transparent)]
    Model(#[from] RegistryError),
    /// The vehicle's stored session could not be read, and this process holds none to go on
    /// with: the stream is refused rather than start afresh behind it.
    #[error(
        "the vehicle's stored session could not be read ({0}); retry to resume it (after {grace} s \
         of this it starts afresh without it), or start with reset to begin afresh now",
        grace = UNREAD_GRACE.as_secs()
    )]
    SnapshotUnreadable(String),
    /// The stored session of a vehicle this process does not hold could not be reset.
    #[error("the session could not be reset: {0}")]
    Stored(#[from] StoredReset),
    /// The session's model was deleted: the session ended.
    #[error(
        "{0} was deleted, which ended this session; start a new one (an empty model follows the active model)"
    )]
    ModelDeleted(ModelName),
}
