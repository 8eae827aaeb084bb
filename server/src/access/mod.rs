//! Who may do what: every API call's caller is identified (a bearer token, or the client
//! certificate of a mutual-TLS connection), given a role and a set of vehicles, and refused with
//! PERMISSION_DENIED (logged and counted) when the call is outside them.
//!
//! - `roles`: the roles file, parsed and checked;
//! - `policy`: which role may make which call;
//! - `guard`: the service wrapper that identifies each call's caller and applies the policy;
//! - `reload`: the roles file and the token file, read at start and re-read when they change.
//!
//! It owns identities and their checks, nothing else: which services are guarded is the router's
//! choice, and the vehicle a detection call names is checked by the detection service with
//! [`Caller::check_vehicle`].

mod guard;
mod policy;
mod reload;
mod roles;

use std::path::PathBuf;
use std::sync::{Arc, PoisonError, RwLock};

pub use guard::Guarded;
pub use reload::keep_current;
use roles::{Grant, Roles};
use tonic::Status;

use crate::telemetry;

/// The caller of a guarded call, in its request's extensions.
#[derive(Clone, Debug)]
pub struct Caller {
    pub grant: Arc<Grant>,
    /// The method's gRPC path (for logs and metrics).
    pub method: &'static str,
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
    /// The single admin token.
    pub admin_token: Option<String>,
    /// The roles file (`None`: there is none).
    pub roles: Option<Roles>,
    pub mutual_tls: bool,
}

impl Identities {
    /// Nothing is configured that identifies a caller: every caller is an admin (a development
    /// server on its own machine).
    pub fn open(&self) -> bool {
        self.admin_token.is_none() && self.roles.is_none() && !self.mutual_tls
    }
}

/// The identities in force, swapped whole when a file changes.
#[derive(Debug)]
pub struct Access {
    current: RwLock<Arc<Identities>>,
    pub sources: Sources,
}

impl Access {
    /// Reads every source once: a file that cannot be read or parsed stops the server's start.
    pub fn load(sources: Sources) -> Result<Access, String> {
        let identities = reload::read(&sources)?;
        Ok(Access {
            current: RwLock::new(Arc::new(identities)),
            sources,
        })
    }

    pub fn current(&self) -> Arc<Identities> {
        Arc::clone(&self.current.read().unwrap_or_else(PoisonError::into_inner))
    }

    fn replace(&self, identities: Identities) {
        *self.current.write().unwrap_or_else(PoisonError::into_inner) = Arc::new(identities);
    }

    /// How callers are identified, for the startup log.
    pub fn describe(&self) -> String {
        let current = self.current();
        if current.open() {
            return "none: every caller is an admin".to_string();
        }
        let mut parts = Vec::new();
        if current.admin_token.is_some() {
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
