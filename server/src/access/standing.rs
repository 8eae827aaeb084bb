//! An open call's standing. A stream or a watch is admitted once, by the guard, and stays open for
//! as long as its client keeps it; so each new set of identities (a changed roles file or token
//! file, put in force by `super::reload`) judges its caller again, by what it presented when the
//! call started:
//! - no longer identified (its token or certificate revoked, its token no longer listed, no
//!   longer the admin token): the call ends with UNAUTHENTICATED, saying its credential is no
//!   longer accepted;
//! - identified, but its role no longer permits the call, or its scope no longer holds the
//!   vehicle its stream is for: the call ends with PERMISSION_DENIED, as a new call would be
//!   refused;
//! - otherwise the call goes on under its new grant and credential: a gateway's changed vehicles
//!   apply to its next messages, and so does a changed `independent_receivers` (the alarms they
//!   raise record the credential as the identities in force give it, and the incident correlator
//!   counts their sources by it).
//!
//! Both endings are logged and counted like the guard's refusals. It owns the judgement and its
//! status; it reads no file, and ends no call itself: each streaming or waiting service selects on
//! [`Caller::until_revoked`] (or runs each step through [`Caller::unless_revoked`], or asks
//! [`Caller::check_standing`] before it sends or stores) and ends its own call with the status.
//! The calls that stay open so: StreamDetect, StreamDetectFleet, WatchAlarms, WatchIncidents,
//! WatchJob, WaitOperation, ExportModel, UploadDataset and ImportModel.

use std::sync::Arc;

use tonic::Status;

use super::guard::identify;
use super::{Caller, Grant, denied};

impl Caller {
    /// Waits for a change of the identities after which this caller may no longer make its call,
    /// and gives the status that ends the call; a change that still admits it updates its grant
    /// and the wait goes on. `vehicle`: the one vehicle the call streams for, which the caller's
    /// scope must still hold. Cancel-safe: a change is judged once, whichever wait sees it.
    pub async fn until_revoked(&mut self, vehicle: Option<&str>) -> Status {
        loop {
            if self.identities.changed().await.is_err() {
                // The identities can no longer change (the server is going away).
                return std::future::pending().await;
            }
            if let Err(status) = self.judge_again(vehicle) {
                return status;
            }
        }
    }

    /// `work` (a step of a long call: the next message of an upload, a wait), unless a change of
    /// the identities no longer admits this caller first: then the status that ends the call.
    pub async fn unless_revoked<T>(
        &mut self,
        vehicle: Option<&str>,
        work: impl Future<Output = Result<T, Status>>,
    ) -> Result<T, Status> {
        tokio::select! {
            biased;
            status = self.until_revoked(vehicle) => Err(status),
            done = work => done,
        }
    }

    /// Whether this caller may still make its call under the identities in force now (judged
    /// again only when they changed since it was last judged): the status that ends the call, as
    /// [`Caller::until_revoked`] gives it.
    pub fn check_standing(&mut self, vehicle: Option<&str>) -> Result<(), Status> {
        if self.identities.has_changed().unwrap_or(false) {
            self.judge_again(vehicle)
        } else {
            Ok(())
        }
    }

    /// Judges the caller by what it presented, against the identities in force.
    fn judge_again(&mut self, vehicle: Option<&str>) -> Result<(), Status> {
        let identities = Arc::clone(&self.identities.borrow_and_update());
        let grant = identify(&identities, &self.presented).map_err(|refused| {
            tracing::warn!(
                caller = %self.grant.name,
                role = self.grant.role.as_str(),
                method = self.method,
                reason = refused.message(),
                "an open call's credential is no longer accepted; the call ends"
            );
            Status::unauthenticated(format!(
                "the credential this call was admitted with is no longer accepted (the identity \
                 files changed while it was open): {}",
                refused.message()
            ))
        })?;
        if !self.need.allows(grant.role) {
            return Err(no_longer(
                &grant,
                self.method,
                &format!("{} (it needs {:?})", self.method, self.need),
            ));
        }
        if let Some(vehicle) = vehicle
            && !grant.scope.contains(vehicle)
        {
            return Err(no_longer(
                &grant,
                self.method,
                &format!("stream for {vehicle:?}"),
            ));
        }
        // The credential follows the grant: a gateway newly marked as forwarding independent
        // receivers (or no longer marked) has its next alarms counted as such.
        self.credential = self.presented.credential(&identities, &grant);
        self.grant = grant;
        Ok(())
    }
}

/// PERMISSION_DENIED for an open call whose caller's grant no longer permits `what`.
fn no_longer(grant: &Grant, method: &'static str, what: &str) -> Status {
    denied(
        grant,
        method,
        &format!("{what} any more (the identity files changed while the call was open)"),
    )
}

#[cfg(test)]
mod tests {
    use tonic::Code;

    use super::*;
    use crate::access::roles::{Role, Roles};
    use crate::access::{Access, Identities, Sources};
    use crate::identity::sha256_hex;

    const STREAM_DETECT: &str = "/spoofwatch.v1.DetectionService/StreamDetect";
    const WATCH_ALARMS: &str = "/spoofwatch.v1.AlarmService/WatchAlarms";

    /// A roles file with a gateway token for `eu-` vehicles and an operator token, and `deny`.
    fn roles(gateway_prefix: &str, operator_role: &str, deny: &str) -> Roles {
        Roles::parse(&format!(
            "[tokens]\n\
             \"{}\" = {{ name = \"bridge\", role = \"gateway\", vehicle_prefixes = [\"{gateway_prefix}\"] }}\n\
             \"{}\" = {{ name = \"dashboard\", role = \"{operator_role}\" {} }}\n\
             [deny]\ntokens_sha256 = [{deny}]\n",
            sha256_hex(b"gateway-token"),
            sha256_hex(b"operator-token"),
            if operator_role == "gateway" {
                ", all_vehicles = true"
            } else {
                ""
            },
        ))
        .expect("a valid roles file")
    }

    fn access(roles: Roles) -> Access {
        let access = Access::load(Sources::default()).expect("no files to read");
        access.replace(Identities {
            admin_token_sha256: Some(sha256_hex(b"admin-token")),
            roles: Some(roles),
            mutual_tls: false,
        });
        access
    }

    fn admit(access: &Access, path: &str, token: &str) -> Caller {
        access
            .admit(path, Some(&format!("Bearer {token}")), None)
            .expect("admitted")
    }

    /// The status `caller`'s call ends with by the changes made so far, or `None` while it goes
    /// on (one poll: a change already made is seen at once).
    fn ended(caller: &mut Caller, vehicle: Option<&str>) -> Option<Status> {
        let waker = std::task::Waker::noop();
        let mut context = std::task::Context::from_waker(waker);
        let wait = std::pin::pin!(caller.until_revoked(vehicle));
        match wait.poll(&mut context) {
            std::task::Poll::Ready(status) => Some(status),
            std::task::Poll::Pending => None,
        }
    }

    #[test]
    fn a_revoked_token_ends_its_open_call_and_other_changes_do_not() {
        let access = access(roles("eu-", "operator", ""));
        let mut gateway = admit(&access, STREAM_DETECT, "gateway-token");
        let mut operator = admit(&access, WATCH_ALARMS, "operator-token");
        assert!(ended(&mut gateway, Some("eu-1")).is_none());

        // The operator's token revoked: the gateway's call goes on, the operator's ends.
        let revoked = format!("\"{}\"", sha256_hex(b"operator-token"));
        access.replace(Identities {
            roles: Some(roles("eu-", "operator", &revoked)),
            ..(*access.current()).clone()
        });
        assert!(ended(&mut gateway, Some("eu-1")).is_none());
        assert!(gateway.check_standing(Some("eu-1")).is_ok());
        let status = ended(&mut operator, None).expect("the operator's call ends");
        assert_eq!(status.code(), Code::Unauthenticated);
        assert!(
            status.message().contains("no longer accepted")
                && status.message().contains("the bearer token is revoked"),
            "{}",
            status.message()
        );
    }

    #[test]
    fn a_token_that_is_no_longer_the_admin_token_ends_its_open_call() {
        let access = access(roles("eu-", "operator", ""));
        let mut admin = admit(&access, WATCH_ALARMS, "admin-token");
        access.replace(Identities {
            admin_token_sha256: Some(sha256_hex(b"rotated-admin-token")),
            ..(*access.current()).clone()
        });
        let status = admin
            .check_standing(None)
            .expect_err("the old admin token is no longer accepted");
        assert_eq!(status.code(), Code::Unauthenticated);
        assert!(
            status.message().contains("missing or wrong bearer token"),
            "{}",
            status.message()
        );
    }

    #[test]
    fn a_demoted_caller_or_a_vehicle_out_of_scope_is_permission_denied() {
        let access = access(roles("eu-", "operator", ""));
        let mut operator = admit(&access, WATCH_ALARMS, "operator-token");
        let mut stream = admit(&access, STREAM_DETECT, "gateway-token");
        let mut fleet = admit(
            &access,
            "/spoofwatch.v1.DetectionService/StreamDetectFleet",
            "gateway-token",
        );
        // The dashboard becomes a gateway (it may no longer read), the bridge moves to `us-`.
        access.replace(Identities {
            roles: Some(roles("us-", "gateway", "")),
            ..(*access.current()).clone()
        });
        let status = ended(&mut operator, None).expect("demoted");
        assert_eq!(status.code(), Code::PermissionDenied);
        assert!(
            status.message().contains("dashboard (gateway) may not")
                && status.message().contains("WatchAlarms"),
            "{}",
            status.message()
        );
        let status = ended(&mut stream, Some("eu-1")).expect("out of scope");
        assert_eq!(status.code(), Code::PermissionDenied);
        assert!(
            status.message().contains("\"eu-1\""),
            "{}",
            status.message()
        );
        // A fleet stream names its vehicles per message: it goes on, under the new scope.
        assert!(ended(&mut fleet, None).is_none());
        assert_eq!(fleet.grant.role, Role::Gateway);
        assert!(fleet.grant.scope.contains("us-1") && !fleet.grant.scope.contains("eu-1"));
        assert!(fleet.check_vehicle("vehicles[0]", "eu-1").is_err());
    }
}
