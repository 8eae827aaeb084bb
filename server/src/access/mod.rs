//! Who may do what: every API call's caller is identified (a bearer token, or the client
//! certificate of a mutual-TLS connection), given a role and a set of vehicles, and refused with
//! PERMISSION_DENIED (logged and counted) when the call is outside them. A call that stays open
//! (a stream, a watch) keeps what its caller presented and is judged again at every change of the
//! identity files ([`Caller::until_revoked`]).
//!
//! - `roles`: the roles file, parsed and checked;
//! - `policy`: which role may make which call;
//! - `guard`: the service wrapper that identifies each call's caller and applies the policy;
//! - `standing`: an open call's caller judged again against each new set of identities;
//! - `reload`: the roles file and the token file, read at start and re-read when they change.
//!
//! It owns identities and their checks, nothing else: which services are guarded is the router's
//! choice, the vehicle a detection call names is checked by the detection service with
//! [`Caller::check_vehicle`], and each streaming service ends its own calls with the status
//! [`Caller::until_revoked`] gives it.

mod guard;
mod policy;
mod reload;
mod roles;
mod standing;

use std::path::PathBuf;
use std::sync::Arc;

pub use guard::Guarded;
use guard::Presented;
use policy::Need;
pub use reload::keep_current;
use roles::{Grant, Roles};
use tokio::sync::watch;
use tonic::Status;

use crate::telemetry;

/// The caller of a guarded call, in its request's extensions.
#[derive(Clone, Debug)]
pub struct Caller {
    /// What the identities in force grant it (as of the last change [`Caller::until_revoked`] or
    /// [`Caller::check_standing`] looked at).
    pub grant: Arc<Grant>,
    /// The method's gRPC path (for logs and metrics).
    pub method: &'static str,
    /// The credential the call was made with, as its alarms record it (set when it was admitted).
    pub credential: Credential,
    /// What the method needs of its caller.
    need: Need,
    /// What the caller presented (digests only), to identify it again when the identities change.
    presented: Presented,
    /// The identities in force; marked seen up to the set `grant` was given by.
    identities: watch::Receiver<Arc<Identities>>,
}

impl Caller {
    /// The caller of `request` (set by the guard). A request without one did not pass the guard,
    /// which only a wiring mistake allows: it is refused, never let through.
    pub fn of<T>(request: &tonic::Request<T>) -> Result<Caller, Status> {
        request
            .extensions()
            .get::<Caller>()
            .cloned()
            .ok_or_else(|| Status::permission_denied("the call was not identified"))
    }

    /// Whether this caller may detect for `vehicle_id` (the message's `field`): refused with
    /// PERMISSION_DENIED, logged and counted, when the vehicle is outside its scope.
    pub fn check_vehicle(&self, field: &str, vehicle_id: &str) -> Result<(), Status> {
        if self.grant.scope.contains(vehicle_id) {
            return Ok(());
        }
        Err(denied(
            &self.grant,
            self.method,
            &format!("{field}: {vehicle_id:?} is not a vehicle this caller may stream for"),
        ))
    }
}

/// The credential a call was made with, as the alarms it raises record it: what it is, never its
/// secret. An operator sees it beside each alarm and each incident's members, and the incident
/// correlator counts independent sources by it.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Credential {
    /// `certificate <name> sha256:<prefix>` (its subject's CN or first DNS SAN and the first 16 hex
    /// digits of its DER's SHA-256), `token <name> sha256:<prefix>` (the roles file's name and
    /// digest), `admin token` (the single configured one), or `unauthenticated` (a server without
    /// identities).
    pub label: Arc<str>,
    /// Each vehicle it streams for is its own source of evidence: a gateway whose roles-file entry
    /// says it forwards independent receivers, or any caller of a server without identities (which
    /// cannot tell its callers apart). Otherwise all its vehicles are one source.
    pub per_vehicle: bool,
}

impl Credential {
    /// The credential of every call to a server without identities.
    pub fn unauthenticated() -> Self {
        Credential {
            label: Arc::from("unauthenticated"),
            per_vehicle: true,
        }
    }
}

/// PERMISSION_DENIED for `grant` on `method`, logged and counted.
fn denied(grant: &Grant, method: &'static str, reason: &str) -> Status {
    tracing::warn!(
        caller = %grant.name,
        role = grant.role.as_str(),
        method,
        reason,
        "permission denied"
    );
    telemetry::permission_denied(grant.role.as_str(), method);
    Status::permission_denied(format!(
        "{} ({}) may not: {reason}",
        grant.name,
        grant.role.as_str()
    ))
}

/// Where identities come from: the configuration's part of them.
#[derive(Clone, Debug, Default)]
pub struct Sources {
    /// The single admin token, given directly (the environment).
    pub token: Option<String>,
    /// A file holding the single admin token (re-read when it changes).
    pub token_file: Option<PathBuf>,
    /// The roles file (re-read when it changes).
    pub roles_file: Option<PathBuf>,
    /// Client certificates are required (mutual TLS).
    pub mutual_tls: bool,
}

/// What the guard checks callers against, as last read.
#[derive(Clone, Debug, Default)]
pub struct Identities {
    /// The SHA-256 (lower-case hex) of the single admin token: a presented token is compared by
    /// its digest, so an open call keeps no token to be judged again by.
    pub admin_token_sha256: Option<String>,
    /// The roles file (`None`: there is none).
    pub roles: Option<Roles>,
    pub mutual_tls: bool,
}

impl Identities {
    /// Nothing is configured that identifies a caller: every caller is an admin (a development
    /// server on its own machine).
    pub fn open(&self) -> bool {
        self.admin_token_sha256.is_none() && self.roles.is_none() && !self.mutual_tls
    }
}

/// The identities in force, swapped whole when a file changes; every open call's [`Caller`] is
/// told of each swap through the channel.
#[derive(Debug)]
pub struct Access {
    current: watch::Sender<Arc<Identities>>,
    pub sources: Sources,
}

impl Access {
    /// Reads every source once: a file that cannot be read or parsed stops the server's start.
    pub fn load(sources: Sources) -> Result<Access, String> {
        let identities = reload::read(&sources)?;
        Ok(Access {
            current: watch::Sender::new(Arc::new(identities)),
            sources,
        })
    }

    pub fn current(&self) -> Arc<Identities> {
        Arc::clone(&self.current.borrow())
    }

    /// Puts `identities` in force, for new calls and for every open one.
    fn replace(&self, identities: Identities) {
        self.current.send_replace(Arc::new(identities));
    }

    /// How callers are identified, for the startup log.
    pub fn describe(&self) -> String {
        let current = self.current();
        if current.open() {
            return "none: every caller is an admin".to_string();
        }
        let mut parts = Vec::new();
        if current.admin_token_sha256.is_some() {
            parts.push("admin bearer token".to_string());
        }
        if let Some(roles) = &current.roles {
            parts.push(format!(
                "roles file ({} certificates, {} tokens, {} revoked)",
                roles.certificates.len(),
                roles.tokens.len(),
                roles.denied_certificate_names.len()
                    + roles.denied_certificate_sha256.len()
                    + roles.denied_token_sha256.len()
            ));
        }
        if current.mutual_tls {
            parts.push("client certificates".to_string());
        }
        parts.join(", ")
    }
}
